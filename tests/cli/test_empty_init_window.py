"""A take that starts before anyone is in view (BTS's gait walk: nothing visible for its first
239 frames): ``label`` and ``evaluate`` said "no marker is seen in 3 or more of its 50 labeled
training frames ... start where the subject is in the volume" without saying where that is.
``replay`` sent the empty frames and the service logged "the init frames carry no labels".
They now name the first frame that shows a marker, as a ``FILE:start`` to run."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main


@pytest.fixture
def late_take(rng, tmp_path):
    pos, names = articulated(rng, subjects=1, frames=300)
    pos = np.array(pos, dtype=np.float32)
    pos[:80] = np.nan  # the performer walks in at frame 80
    pos[:120, 0] = np.nan  # one marker first seen at frame 120
    return write_capture(Capture(pos, names, 100.0, source="late"), tmp_path / "late.npz")


@pytest.mark.parametrize("command", ["label", "evaluate", "replay"])
def test_an_empty_init_window_names_the_first_frame_with_a_marker(late_take, tmp_path, command,
                                                                  capsys):  # fmt: skip
    out = {"label": [str(tmp_path / "out.c3d")], "replay": ["--to", "udp://127.0.0.1:9/x"]}.get(
        command, []
    )
    assert main([command, str(late_take), *out]) == 2
    err = capsys.readouterr().err
    assert "no labeled marker is seen in the first 50 frames" in err, err
    assert f"{late_take}:80" in err
    assert f"({late_take}:120; the markers a window does not show stay unlabeled)" in err
    # a range that starts inside the empty part: the frame is the file's, as the range's are
    assert main([command, f"{late_take}:20", *out]) == 2
    assert f"{late_take}:80" in capsys.readouterr().err


def test_the_suggested_start_labels(late_take, tmp_path, capsys):
    assert main(["label", f"{late_take}:80", str(tmp_path / "out.c3d")]) == 0


@pytest.mark.parametrize("command", ["label", "evaluate"])
def test_a_subject_who_enters_after_the_window_is_named(rng, tmp_path, command, capsys):
    """Two performers, the second walks in at frame 100: the training error named him but
    not where he is in view."""
    pos, names = articulated(rng, subjects=2, frames=300)
    pos = np.array(pos, dtype=np.float32)
    late = names[-1].split(":")[0]
    pos[:100, [i for i, n in enumerate(names) if n.startswith(late + ":")]] = np.nan
    path = write_capture(Capture(pos, names, 100.0, source="two"), tmp_path / "two.npz")
    out = [str(tmp_path / "out.c3d")] if command == "label" else []
    assert main([command, str(path), *out]) == 2
    err = capsys.readouterr().err
    assert f"subject {late} shows no marker in 3 or more of the first 50 frames" in err, err
    assert f"every subject is in view from frame 100 ({path}:100)" in err
    assert main([command, f"{path}:100", *out]) == 0
