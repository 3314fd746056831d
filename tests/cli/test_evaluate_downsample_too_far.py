"""``evaluate --downsample N`` that leaves no more frames than the init window says so; it
said "the labeled start through a window model needs at least 3 labeled init frames (got 1):
send more init frames", and more init frames could not help."""

from __future__ import annotations

from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main


def test_a_downsampling_that_leaves_too_few_frames_is_named(rng, tmp_path, capsys):
    pos, names = articulated(rng, subjects=1, frames=300)
    src = write_capture(Capture(pos, names, 120.0, source="take"), tmp_path / "take.npz")
    assert main(["evaluate", str(src), "--downsample", "100"]) == 2
    err = capsys.readouterr().err
    assert "--downsample 100 leaves 3 of the 300 frames" in err, err
    assert "50-frame init window" in err


def test_a_take_no_longer_than_the_init_window_is_named(rng, tmp_path, capsys):
    """A 1-frame scene (compose --frames 1) said "needs at least 3 labeled init frames (got 1):
    send more init frames"."""
    pos, names = articulated(rng, subjects=1, frames=2)
    src = write_capture(Capture(pos, names, 120.0, source="take"), tmp_path / "take.npz")
    assert main(["evaluate", str(src)]) == 2
    err = capsys.readouterr().err
    assert "2 frames is not more than the 50-frame init window" in err, err
