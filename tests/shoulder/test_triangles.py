"""Marker surface: automatic faces, faces files, rest pose, near-rigid filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from labeler_service.errors import ModelError
from offline.shoulder.triangles import (
    auto_faces,
    edge_strain,
    marker_neighbors,
    read_faces,
    rest_pose,
    rigid_faces,
    write_faces,
)


def _cylinder(n_around=10, n_rows=6, r=45.0, step=27.0):
    pts = []
    for i in range(n_rows):
        for j in range(n_around):
            a = 2 * np.pi * (j + 0.5 * (i % 2)) / n_around
            pts.append([r * np.cos(a), r * np.sin(a), i * step])
    return np.asarray(pts)


def test_auto_faces_mesh_a_cylinder_surface():
    pts = _cylinder()
    faces = auto_faces(pts)
    # the staggered grid has 2 triangles per marker per band: 2 * 10 * 5 = 100
    assert 80 <= len(faces) <= 110
    edges = np.linalg.norm(pts[faces] - pts[np.roll(faces, 1, axis=1)], axis=2)
    assert edges.max() < 60.0  # no face across the limb (diameter 90 mm)
    assert np.unique(faces).size == len(pts)
    nb = marker_neighbors(faces, len(pts))
    assert all(4 <= len(x) <= 8 for x in nb[10:-10])


def test_auto_faces_errors():
    with pytest.raises(ModelError, match="at least 4"):
        auto_faces(np.zeros((3, 3)))
    with pytest.raises(ModelError, match="NaN"):
        auto_faces(np.full((5, 3), np.nan))


def test_faces_file_round_trip_and_errors(tmp_path):
    labels = ("s:A", "s:B", "s:C", "s:D")
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    p = write_faces(tmp_path / "f.txt", faces, labels)
    np.testing.assert_array_equal(read_faces(p, labels), faces)
    alt = tmp_path / "g.txt"
    alt.write_text("# comment\nA, B, 3\n\n0 1 2  # indices\n")
    np.testing.assert_array_equal(read_faces(alt, labels), [[0, 1, 3], [0, 1, 2]])
    bad = tmp_path / "bad.txt"
    bad.write_text("A B X\n")
    with pytest.raises(ModelError, match="unknown marker 'X'"):
        read_faces(bad, labels)
    bad.write_text("A B\n")
    with pytest.raises(ModelError, match="needs 3"):
        read_faces(bad, labels)
    bad.write_text("A A B\n")
    with pytest.raises(ModelError, match="repeats"):
        read_faces(bad, labels)
    with pytest.raises(ModelError, match="no such"):
        read_faces(tmp_path / "missing.txt", labels)


def test_rest_pose_picks_most_visible_frame_and_fills():
    pos = np.arange(4 * 3 * 3, dtype=float).reshape(4, 3, 3)
    pos[0, 1] = np.nan
    pos[2, 0] = np.nan
    pos[1, 2] = np.nan
    pos[3, 2] = np.nan
    frame, rest = rest_pose(pos)
    assert frame in (0, 1, 2)  # tied: each misses one marker
    assert np.isfinite(rest).all()


def test_rest_pose_takes_the_unique_best_frame_and_carries_the_missing_marker(rng):
    """Visible counts 5, 7, 9, 8, 6, 4 over six frames: frame 2 is the only best one (neither
    the first, the last nor the least visible). A marker missing there is carried from the
    nearest frame with its neighbours' rigid motion, so it lands on its true position."""
    shape = rng.normal(scale=50.0, size=(10, 3))
    R = Rotation.from_rotvec(rng.normal(scale=0.4, size=(6, 3))).as_matrix()
    t = rng.normal(scale=100.0, size=(6, 3))
    truth = np.einsum("fij,mj->fmi", R, shape) + t[:, None]
    pos = truth.copy()
    hidden = {0: [1, 3, 5, 7, 9], 1: [0, 4, 8], 2: [6], 3: [2, 6], 4: [0, 2, 4, 6], 5: range(6)}
    for f, ms in hidden.items():
        pos[f, list(ms)] = np.nan
    frame, rest = rest_pose(pos)
    assert frame == 2
    np.testing.assert_allclose(rest[np.arange(10) != 6], pos[2, np.arange(10) != 6])
    np.testing.assert_allclose(rest[6], truth[2, 6], atol=1e-9)  # from frame 1 (or 3), rigidly
    pos[:, 0] = np.nan
    with pytest.raises(Exception, match="never visible"):
        rest_pose(pos)


def test_edge_strain_separates_rigid_from_folding(rng):
    rest = np.array([[0, 0, 0], [30, 0, 0], [0, 30, 0], [60, 0, 0]], dtype=float)
    pos = np.repeat(rest[None], 100, axis=0) + rng.normal(scale=0.3, size=(100, 4, 3))
    pos[:, 3, 0] = 30 + np.linspace(5, 60, 100)  # marker 3 slides: its face stretches
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    s = edge_strain(pos, faces)
    assert s[0] < 1.1 and s[1] > 3
    np.testing.assert_array_equal(rigid_faces(pos, faces), [0])
    np.testing.assert_array_equal(rigid_faces(pos, faces, max_strain=1.0, min_keep=1), [0])
