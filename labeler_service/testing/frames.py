"""A capture's frames as a live source sends them to a labeler of a model (tests, benchmarks)."""

from __future__ import annotations

import numpy as np

from labeler_service.capture import Capture


class ModelFrames:
    """Frames of ``capture`` for a labeler of the markers ``names``: in each, the points of those
    markers the capture shows, then its ghosts, shuffled (``seed``); ``truth`` per point is the
    marker's index in ``names``, -1 for a ghost. A marker of ``names`` the capture lacks is
    never shown; with ``hide``, that share of the markers (drawn first from the seeded
    generator) is hidden throughout too (``hidden``)."""

    def __init__(self, capture: Capture, names, seed: int, hide: float | None = None) -> None:
        col = {lab: i for i, lab in enumerate(capture.labels)}
        self.gidx = np.array([col.get(n, -1) for n in names], dtype=np.int64)
        self.ghosts = np.flatnonzero(capture.ghost_mask)
        self.positions = capture.positions
        self.rng = np.random.default_rng(seed)
        self.hidden = np.zeros(len(self.gidx), dtype=bool)
        if hide is not None:
            self.hidden = self.rng.random(len(self.gidx)) < hide

    def frame(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """``(points (N, 3) float32, truth (N,))`` of capture frame ``f``."""
        mk = self.positions[f, np.maximum(self.gidx, 0)]
        vis = np.isfinite(mk[:, 0]) & (self.gidx >= 0) & ~self.hidden
        g = self.positions[f, self.ghosts]
        g = g[np.isfinite(g[:, 0])]
        pts = np.concatenate([mk[vis], g]).astype(np.float32)
        truth = np.concatenate([np.flatnonzero(vis), np.full(len(g), -1)])
        order = self.rng.permutation(len(pts))
        return pts[order], truth[order]
