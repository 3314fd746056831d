"""Training on frames whose markers accelerate beyond any body (a capture whose POINT:RATE is
wrong, 1 MHz for 50 Hz): the error names the rate and what to check. It was the template
validator's "Value error, subject 'S': motion_noise[0] = 9.5e+21 (mm/s^2)^2 (C7) is outside
10-1e+13", which says nothing a user can act on."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main
from labeler_service.errors import LabelerError
from labeler_service.labeling.training import train_subject


def _walk(rng, frames: int = 60, rate: float = 50.0) -> np.ndarray:
    """A rigid body of 5 markers walking at 1 m/s and swaying, sampled at ``rate``."""
    t = np.arange(frames)[:, None, None] / rate
    body = rng.normal(scale=150.0, size=(1, 5, 3))
    sway = np.stack([np.zeros_like(t[..., 0]), 30 * np.sin(6 * t[..., 0]), 0 * t[..., 0]], -1)
    return body + np.array([1000.0, 0.0, 0.0]) * t + sway


def test_a_wrong_rate_is_named_in_the_training_error(rng, tmp_path, capsys):
    pos = _walk(rng)  # sampled at 50 Hz, declared 1 MHz
    with pytest.raises(LabelerError, match=r"frame rate \(1e\+06 Hz\)"):
        train_subject("S", [f"m{i}" for i in range(5)], pos, 1e6)
    path = write_capture(Capture(pos, tuple(f"S:m{i}" for i in range(5)), 1e6), tmp_path / "a.c3d")
    assert main(["train", "structure", str(path), "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert "frame rate" in err and "Value error" not in err


def test_the_right_rate_trains(rng):
    template = train_subject("S", [f"m{i}" for i in range(5)], _walk(rng), 50.0)
    assert template.name == "S"
