"""A capture path that holds ':' in a take spec (``TAKE[:start[:up[:subject]]]`` of compose,
``TAKE[:start[:stop]]`` of train structure, ``FILE[:start[:stop]]`` of evaluate, info, label,
replay): the longest prefix that is a capture file on disk is the file. Compose split at the
first ':' ("start '1/take.npz' is not a frame number") and train structure at the last two
("bad take") of ``day:1/take.npz:10``; evaluate's reader already took such paths (kept by the
last test), all three now share one splitter (``capture.io.split_spec``)."""

from __future__ import annotations

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.capture.io import split_segment
from labeler_service.cli.main import main
from labeler_service.errors import CaptureError, ModelError, SceneError
from labeler_service.scenes.compose import TakeSpec


@pytest.fixture
def odd(rng, tmp_path):
    """A one-subject take in a folder whose name holds a colon, and one named ``t:10.npz``."""
    pos, names = articulated(rng, subjects=1, frames=200)
    cap = Capture(pos, names, 120.0, source="take")
    folder = tmp_path / "day:1"
    folder.mkdir()
    write_capture(cap, folder / "take.npz")
    write_capture(cap, tmp_path / "t:10.npz")
    return folder / "take.npz", tmp_path / "t:10.npz"


def test_split_spec_takes_the_longest_prefix_that_exists(odd, tmp_path):
    from labeler_service.capture.io import split_spec

    take, t10 = odd
    assert split_spec(f"{take}:5:y", 3) == (str(take), ["5", "y"])
    assert split_spec(f"{t10}:20", 2) == (str(t10), ["20"])
    assert split_segment(f"{t10}:20:30") == (str(t10), 20, 30)
    assert split_segment(f"{take}:7") == (str(take), 7, None)
    # nothing exists: the capture-named prefix (its reader says "no such file")
    gone = tmp_path / "x:2" / "gone.c3d"
    assert split_spec(f"{gone}:5", 3) == (str(gone), ["5"])
    # a file then too many fields: said by the caller
    assert split_spec(f"{take}:1:2:3:4", 3) == (str(take), ["1", "2", "3", "4"])


def test_compose_reads_a_take_whose_path_holds_a_colon(odd, tmp_path, capsys):
    take, _ = odd
    spec = TakeSpec.parse(f"{take}:12:z")
    assert (str(spec.path), spec.start, spec.up) == (str(take), 12, "z")
    out = tmp_path / "scene.npz"
    argv = ["compose", str(out), f"{take}:10", "--radius", "300", "--frames", "50", "--seed", "1"]
    assert main(argv) == 0
    assert "from " + str(take) + " frame 10" in capsys.readouterr().out


def test_compose_says_which_spec_is_bad(odd, tmp_path):
    take, _ = odd
    with pytest.raises(SceneError, match=r"too many ':' fields after .*take\.npz: expected FILE"):
        TakeSpec.parse(f"{take}:0:z:P0:extra")
    with pytest.raises(SceneError, match=r"start 'x' is not a frame number \(and no file"):
        TakeSpec.parse(f"{tmp_path / 'none'}:x")


def test_train_structure_reads_a_take_whose_path_holds_a_colon(odd, tmp_path, capsys):
    from offline.structure_cli import parse_take

    take, t10 = odd
    assert parse_take(f"{take}:10") == (str(take), 10, None)
    assert parse_take(f"{t10}:20:150") == (str(t10), 20, 150)
    with pytest.raises(ModelError, match="too many ':' fields after"):
        parse_take(f"{take}:1:2:3")
    out = tmp_path / "model.json"
    assert main(["train", "structure", f"{take}:10", "--out", str(out)]) == 0
    assert out.is_file()


def test_evaluate_reads_a_range_of_a_file_named_like_a_range(odd, capsys):
    """``t:10.npz:20:150`` is frames 20-150 of ``t:10.npz`` (it was before the shared splitter);
    an existing ``t:10.npz`` with a bad range names it."""
    _, t10 = odd
    argv = ["evaluate", f"{t10}:20:150", "--init-frames", "30", "--method", "closest-point"]
    assert main([*argv, "--json", "--no-progress"]) == 0
    assert '"frames": 100' in capsys.readouterr().out
    with pytest.raises(CaptureError, match="bad frame range 'x'"):
        split_segment(f"{t10}:x")


def test_a_capture_file_comes_before_a_stray_file_or_folder_named_like_a_prefix(
    odd, tmp_path, monkeypatch
):
    """``take.npz:10:y`` beside a stray file named ``take.npz:10`` (no capture, by its suffix
    ``.npz:10``) read the stray file with start 'y' (compose: "start 'y' is not a frame
    number"; info and train structure ``take.npz:10:40``: "unknown capture format '.npz:10'")
    where compose and train structure had read frames of ``take.npz``; ``day:1/take.npz:5``
    beside a folder ``day`` (and no ``day:1``) was the folder with start '1/take.npz'."""
    from labeler_service.capture import read_segment
    from labeler_service.capture.io import split_spec
    from offline.structure_cli import parse_take

    take, _ = odd
    monkeypatch.chdir(take.parent)
    (take.parent / "take.npz:10").write_text("a stray file")
    assert split_spec("take.npz:10:y", 3) == ("take.npz", ["10", "y"])
    spec = TakeSpec.parse("take.npz:10:y")
    assert (str(spec.path), spec.start, spec.up) == ("take.npz", 10, "y")
    assert split_segment("take.npz:10:40") == ("take.npz", 10, 40)
    assert parse_take("take.npz:10:40") == ("take.npz", 10, 40)
    # nothing to read but the stray file: it is the file (its reader names it)
    (take.parent / "lone.c3d:10").write_text("a stray file")
    assert split_spec("lone.c3d:10", 2) == ("lone.c3d:10", [])

    monkeypatch.chdir(tmp_path)
    (tmp_path / "day").mkdir()
    assert split_spec("day:1/gone.npz:5", 3) == ("day:1/gone.npz", ["5"])
    assert split_segment("day:1/gone.npz:5") == ("day:1/gone.npz", 5, None)
    with pytest.raises(CaptureError, match=r"day:1/gone\.npz: no such file"):
        read_segment("day:1/gone.npz:5")
    assert split_spec("day:1/take.npz:5", 3) == ("day:1/take.npz", ["5"])  # (odd's file)
