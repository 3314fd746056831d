"""The Mahalanobis gate as behaviour, not as a kernel twin: a point that fits a body's structure
perfectly but lies far outside the marker's predicted position must not take the label.

The ghost is the hidden marker mirrored through the plane of its three segment neighbours:
every distance to them -- all the structure model ``D``/``A`` knows -- is exactly the true
one, so only the motion model (the chi-square gate around the Kalman prediction) can tell the
ghost is ~10 cm away from where the marker can be.
"""

from __future__ import annotations

import numpy as np
from labeling.scene import articulated, frame_points

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.labeler import Labeler

INIT = 40
HIDDEN = (100, 140)


def _mirror(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    return p - 2.0 * np.dot(p - a, n) * n


def _farthest_mirror(pos: np.ndarray, names: tuple[str, ...]) -> tuple[int, list[int]]:
    """The marker whose mirror image (through its three segment neighbours) is farthest."""
    best = (-1.0, -1, [])
    for name in names:
        subject, seg = name.split(":")[0], name.split(":")[1][0]
        group = [i for i, n in enumerate(names) if n.startswith(f"{subject}:{seg}")]
        m = names.index(name)
        others = [i for i in group if i != m]
        p = pos[0].astype(np.float64)
        d = float(np.linalg.norm(_mirror(p[m], *p[others]) - p[m]))
        if d > best[0]:
            best = (d, m, others)
    return best[1], best[2]


def test_a_structure_perfect_ghost_outside_the_gate_stays_unlabeled(rng):
    pos, names = articulated(rng, frames=200)
    m, others = _farthest_mirror(pos, names)
    lab = Labeler(names, 120.0)
    floor = LabelerConfig().min_gate_mm
    ghost_labels, states = [], []
    for f in range(pos.shape[0]):
        hide = HIDDEN[0] <= f < HIDDEN[1]
        hidden = np.zeros(pos.shape[1], dtype=bool)
        hidden[m] = hide
        pts, truth = frame_points(rng, pos[f], hidden)
        if hide:
            p = pos[f].astype(np.float64)
            ghost = _mirror(p[m], *p[others])
            # structure-perfect, yet far outside the gate (whose floor radius is 30 mm)
            np.testing.assert_allclose(
                np.linalg.norm(ghost - p[others], axis=1),
                np.linalg.norm(p[m] - p[others], axis=1),
                rtol=1e-9,
            )
            assert np.linalg.norm(ghost - p[m]) > 3 * floor
            pts = np.concatenate([pts, ghost[None].astype(np.float32)])
            truth = np.concatenate([truth, [-1]]).astype(np.int32)
        out = lab.process(pts, f / 120.0, truth if f < INIT else None)
        if f >= INIT:
            known = truth >= 0
            np.testing.assert_array_equal(out.point_labels[known], truth[known])
        if hide:
            ghost_labels.append(int(out.point_labels[-1]))
            states.append(int(out.state[m]))
    assert ghost_labels == [-1] * (HIDDEN[1] - HIDDEN[0])
    assert MarkerState.OBSERVED not in states
