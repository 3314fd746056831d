"""Samples a file stores as infinite (or too large for float32: a C3D's float 1e39 becomes inf)
are missing, as NaN and (0,0,0) are: they reached the labeler, and ``evaluate`` stopped with
'points must be finite (drop missing points instead of NaN)', an error about the labeler's
input that the user never wrote."""

from __future__ import annotations

import json

import numpy as np

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main


def test_infinite_samples_read_as_missing_with_a_note(tmp_path, rng, capsys):
    t = np.arange(80)[:, None, None] / 100.0
    pos = rng.normal(scale=300.0, size=(1, 6, 3)) + np.array([200.0, 0.0, 0.0]) * t
    pos[10:14, 2] = np.inf
    pos[20, 3, 1] = -np.inf
    pos[30, 4] = 1e39  # a float64 beyond float32
    path = tmp_path / "inf.npz"
    np.savez(path, positions=pos, labels=np.array([f"S:m{i}" for i in range(6)]), rate=100.0)
    cap = read_capture(path)
    gone = ~np.isfinite(cap.positions).all(axis=2)
    expected = np.zeros((80, 6), dtype=bool)
    expected[10:14, 2] = expected[20, 3] = expected[30, 4] = True
    np.testing.assert_array_equal(gone, expected)
    assert np.isnan(cap.positions[gone]).all()
    assert any("6 infinite samples mapped to missing" in n for n in cap.notes), cap.notes
    # and the CLI scores it
    assert main(["evaluate", str(path), "--init-frames", "5", "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["frames"] > 0


def test_finite_captures_get_no_note(tmp_path, rng):
    pos = rng.normal(scale=300.0, size=(10, 3, 3)).astype(np.float32)
    pos[2, 1] = np.nan
    cap = read_capture(
        write_capture(Capture(pos, ("S:a", "S:b", "S:c"), 100.0), tmp_path / "a.c3d")
    )
    assert not any("infinite" in n for n in cap.notes)


def test_samples_beyond_ten_km_read_as_missing_with_a_note(tmp_path, rng, capsys):
    """A C3D holding 3e38 (finite in float32) at a few samples: ``compose`` printed numpy's
    cast-overflow warning, ``info`` said nothing, and ``evaluate``'s speed note quoted a marker
    moving at 2.6e40 mm/s. Such samples are missing now, as the service refuses such frames."""
    t = np.arange(60)[:, None, None] / 100.0
    pos = rng.normal(scale=300.0, size=(1, 5, 3)) + np.array([200.0, 0.0, 0.0]) * t
    pos[5:9, 1, 0] = 3e38
    pos[12, 2, 2] = -2e7
    pos[13, 2, 2] = 9e6  # within the limit: kept
    cap = read_capture(write_capture(Capture(pos.astype(np.float32), tuple(
        f"S:m{i}" for i in range(5)), 100.0), tmp_path / "far.c3d"))  # fmt: skip
    gone = np.isnan(cap.positions).any(axis=2)
    expected = np.zeros((60, 5), dtype=bool)
    expected[5:9, 1] = expected[12, 2] = True
    np.testing.assert_array_equal(gone, expected)
    assert any("5 samples beyond 1e+07 mm of the origin mapped to missing" in n
               for n in cap.notes), cap.notes  # fmt: skip
    assert main(["info", str(tmp_path / "far.c3d")]) == 0
    assert "5 samples beyond 1e+07 mm" in capsys.readouterr().out


def test_samples_with_some_coordinates_nan_read_as_missing_with_a_note(tmp_path, rng, capsys):
    """A TRC row missing its last cell, an NPZ with one NaN coordinate: every command failed
    with scipy's 'data must be finite, check for nan or inf values' (the duplicate-column check
    took a sample's visibility from X alone). One NaN coordinate makes the sample missing."""
    t = np.arange(60)[:, None, None] / 100.0
    pos = rng.normal(scale=300.0, size=(1, 5, 3)) + np.array([200.0, 0.0, 0.0]) * t
    pos[3:7, 2, 2] = np.nan
    pos[9, 4, 1] = np.nan
    path = tmp_path / "part.npz"
    np.savez(path, positions=pos, labels=np.array([f"S:m{i}" for i in range(5)]), rate=100.0)
    cap = read_capture(path)
    gone = np.isnan(cap.positions).any(axis=2)
    expected = np.zeros((60, 5), dtype=bool)
    expected[3:7, 2] = expected[9, 4] = True
    np.testing.assert_array_equal(gone, expected)
    assert np.isnan(cap.positions[gone]).all()
    assert any("5 samples with some coordinates missing" in n for n in cap.notes), cap.notes
    assert main(["info", str(path)]) == 0
    assert (
        "5 samples with some coordinates missing (NaN) mapped to missing" in capsys.readouterr().out
    )
