"""``label`` and ``evaluate`` with 1-2 labeled init frames and no model: ``auto`` falls back to
the labeler trained in place, which cannot train on them either; the error names
``--init-frames`` (it named only "labeled frames")."""

from __future__ import annotations

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main


@pytest.fixture
def mixed(rng, tmp_path):
    pos, names = articulated(rng, subjects=2, frames=160)
    path = tmp_path / "take.npz"
    write_capture(Capture(pos, names, 120.0, source="take"), path)
    return path, names


def test_too_few_init_frames_name_the_option(mixed, tmp_path, capsys):
    src, _ = mixed
    for n in ("1", "2"):
        assert main(["label", str(src), str(tmp_path / "o.npz"), "--init-frames", n]) == 2
        assert "--init-frames must be >= 3" in capsys.readouterr().err
        assert main(["evaluate", str(src), "--method", "online", "--init-frames", n]) == 2
        assert "--init-frames must be >= 3" in capsys.readouterr().err
    # the closest-point baseline alone needs no training window
    assert main(["evaluate", str(src), "--method", "closest-point", "--init-frames", "1"]) == 0
