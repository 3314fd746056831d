"""Missing samples in C3D, as other tools read them: residual < 0 means "not captured".

Tools such as Vicon Nexus, Mokka or btk read a sample's residual, not NaN coordinates, so the
writer must store residual -1 for every missing sample (checked on the raw residuals ezc3d
reads back), and the reader must treat a negative residual as missing whatever coordinates the
sample carries (checked with a file whose invalid samples keep finite coordinates).
"""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture, read_capture, write_capture

ezc3d = pytest.importorskip("ezc3d")


def test_writer_stores_residual_minus_one_for_missing_samples(tmp_path, rng):
    pos = rng.normal(scale=300.0, size=(20, 5, 3)).astype(np.float32)
    missing = rng.random((20, 5)) < 0.3
    missing[0, 0] = missing[19, 4] = True
    pos[missing] = np.nan
    path = write_capture(
        Capture(pos, tuple(f"S:m{i}" for i in range(5)), 100.0), tmp_path / "a.c3d"
    )
    raw = ezc3d.c3d(str(path))
    res = np.asarray(raw["data"]["meta_points"]["residuals"])[0].T  # (F, M)
    assert res.shape == missing.shape
    np.testing.assert_array_equal(res[missing], -1.0)
    assert (res[~missing] >= 0).all()
    # and the coordinates of captured samples survive
    xyz = np.transpose(np.asarray(raw["data"]["points"])[:3], (2, 1, 0))
    np.testing.assert_allclose(xyz[~missing], pos[~missing], atol=1e-3)


class _FakeC3d(dict):
    """What a reader gets from a C3D whose invalid samples keep finite coordinates (a writer
    that leaves them in place; ezc3d itself may or may not blank them, depending on version)."""

    def __init__(self, points: np.ndarray, residuals: np.ndarray, labels: list[str]) -> None:
        super().__init__(
            parameters={"POINT": {"RATE": {"value": [100.0]}, "LABELS": {"value": labels},
                                  "UNITS": {"value": ["mm"]}}},
            data={"points": points, "meta_points": {"residuals": residuals}},
        )  # fmt: skip


def test_reader_treats_negative_residuals_as_missing(tmp_path, monkeypatch):
    f, m = 6, 3
    pts = np.ones((4, m, f))
    pts[:3] = np.arange(3 * m * f, dtype=float).reshape(3, m, f) + 10.0  # finite everywhere
    residuals = np.zeros((1, m, f))
    residuals[0, 1, 2] = -1.0
    residuals[0, 2, 4] = -0.5
    residuals[0, 0, 3] = 0.7  # a positive residual is a captured sample
    fake = _FakeC3d(pts, residuals, ["S:a", "S:b", "S:c"])
    path = tmp_path / "fake.c3d"
    path.write_bytes(b"")  # read_capture checks the file exists; ezc3d is replaced below
    monkeypatch.setattr(ezc3d, "c3d", lambda _path: fake)
    cap = read_capture(path)
    gone = np.isnan(cap.positions).any(axis=2)
    expected = np.zeros((f, m), dtype=bool)
    expected[2, 1] = expected[4, 2] = True
    np.testing.assert_array_equal(gone, expected)
    assert np.isnan(cap.positions[gone]).all()  # all three coordinates, not one
    np.testing.assert_allclose(cap.positions[~gone], np.transpose(pts[:3], (2, 1, 0))[~gone])
    assert any("2 samples with coordinates but a negative residual" in n for n in cap.notes)


def test_missing_samples_written_as_such_need_no_note(tmp_path, rng):
    """The writer's own missing samples (residual -1 on NaN coordinates) are the usual
    convention: read back missing, with no note that would say data was discarded."""
    pos = rng.normal(scale=300.0, size=(10, 3, 3)).astype(np.float32)
    pos[2:5, 1] = np.nan
    path = write_capture(Capture(pos, ("S:a", "S:b", "S:c"), 100.0), tmp_path / "m.c3d")
    cap = read_capture(path)
    assert np.isnan(cap.positions[2:5, 1]).all()
    assert not any("residual" in n for n in cap.notes)


def test_negative_residuals_round_trip_through_ezc3d(tmp_path):
    """A file written by ezc3d with residual -1 on finite coordinates reads back missing."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["S:a", "S:b"]
    pts = np.ones((4, 2, 5))
    pts[:3] = np.arange(30, dtype=float).reshape(3, 2, 5) + 1.0
    c["data"]["points"] = pts
    res = np.zeros((1, 2, 5))
    res[0, 1, 3] = -1.0
    c["data"]["meta_points"]["residuals"] = res
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, 2, 5), dtype=bool)
    c.write(str(tmp_path / "e.c3d"))
    cap = read_capture(tmp_path / "e.c3d")
    gone = np.isnan(cap.positions).any(axis=2)
    assert gone.sum() == 1 and gone[3, 1]
