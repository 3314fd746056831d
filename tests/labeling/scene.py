"""A small articulated multi-person scene for labeler tests (no simulator, no real data).

Each subject has two rigid segments of four markers joined at an elbow-like joint; subjects
walk in small circles close to each other (200 mm apart) and the joint flexes, so markers of
different people pass near each other and the segments move relative to each other.
"""

from __future__ import annotations

import numpy as np


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1], r[..., 2, 2] = c, -s, s, c, 1.0
    return r


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0], r[..., 0, 2], r[..., 2, 0], r[..., 2, 2], r[..., 1, 1] = c, s, -s, c, 1.0
    return r


def articulated(
    rng: np.random.Generator, subjects: int = 3, frames: int = 300, rate: float = 120.0
) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(F, M, 3)`` float32 positions (mm) and ``subject:marker`` names."""
    t = np.arange(frames) / rate
    out = []
    names: list[str] = []
    for s in range(subjects):
        seg_a = rng.uniform(-60, 60, (4, 3)) + [0, 0, 150]
        seg_b = rng.uniform(-50, 50, (4, 3)) + [0, 0, 150]
        phase = 2 * np.pi * s / subjects
        centre = np.stack(
            [
                200 * np.cos(phase) + 60 * np.sin(2 * np.pi * 0.4 * t + s),
                200 * np.sin(phase) + 60 * np.cos(2 * np.pi * 0.3 * t + s),
                1000 + 30 * np.sin(2 * np.pi * 0.7 * t),
            ],
            axis=1,
        )
        yaw = 0.6 * np.sin(2 * np.pi * 0.25 * t + s)
        flex = 0.7 + 0.6 * np.sin(2 * np.pi * 0.5 * t + 2 * s)
        r_a = _rot_z(yaw)
        joint = centre + np.einsum("fij,j->fi", r_a, np.array([0.0, 0.0, 300.0]))
        r_b = r_a @ _rot_y(flex)
        pa = centre[:, None] + np.einsum("fij,mj->fmi", r_a, seg_a)
        pb = joint[:, None] + np.einsum("fij,mj->fmi", r_b, seg_b)
        out.append(np.concatenate([pa, pb], axis=1))
        names += [f"P{s}:a{i}" for i in range(4)] + [f"P{s}:b{i}" for i in range(4)]
    pos = np.concatenate(out, axis=1).astype(np.float32)
    pos += rng.normal(0, 0.3, pos.shape).astype(np.float32)
    return pos, tuple(names)


def frame_points(
    rng: np.random.Generator, pos: np.ndarray, hidden: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Shuffled visible points of one frame and their true marker indices."""
    vis = np.isfinite(pos[:, 0])
    if hidden is not None:
        vis &= ~hidden
    idx = np.flatnonzero(vis)
    order = rng.permutation(idx.size)
    return np.ascontiguousarray(pos[idx[order]]), idx[order].astype(np.int32)


class GhostScore:
    """Labels frames with ghost points and scores them: ghosts given a label of a marker
    ``>= first`` (the leaver's), and accuracy over the real points, from frame ``start`` on."""

    def __init__(self, first: int, start: int) -> None:
        self.first, self.start = first, start
        self.taken = self.ghosts = self.correct = self.total = 0

    def feed(self, lab, rng, f: int, rate: float, pts, truth, init: int) -> None:
        """Shuffles the frame's points (``truth`` -1 for a ghost), labels them (with labels in
        the first ``init`` frames) and, from ``start`` on, counts."""
        order = rng.permutation(pts.shape[0])
        pts, truth = np.ascontiguousarray(pts[order], dtype=np.float32), truth[order]
        out = lab.process(pts, f / rate, truth if f < init else None)
        if f < self.start:
            return
        g = truth < 0
        self.ghosts += int(g.sum())
        self.taken += int(np.count_nonzero(out.point_labels[g] >= self.first))
        real = truth >= 0
        self.correct += int(np.count_nonzero(out.point_labels[real] == truth[real]))
        self.total += int(real.sum())

    def result(self) -> tuple[int, int, float]:
        return self.taken, self.ghosts, self.correct / self.total
