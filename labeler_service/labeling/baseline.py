"""The closest-point baseline of Yu, Li and Deng (2007): each label takes the point nearest its
last position.

Yu et al. (Sec. 4) compare against a tracker that "assumes the correct correspondence is the
closest point in the next frame". Our implementation makes the two choices the paper leaves
open explicit:

- **Collisions** (two labels nearest to one point): resolved globally, nearest pair first. All
  (label, point) pairs within the gate are sorted by distance and taken greedily; a label or a
  point already taken is skipped, so every point carries at most one label and vice versa.
- **Misses** (a label with no free point inside its gate): the label stays missing for this frame
  and keeps its last known position and time. The gate grows with the time since the label was
  last seen: ``max_speed_mm_s * (t - t_last)``, at least ``min_gate_mm``. A point no label takes
  stays unlabeled (ghost or unknown).

During the supervised training window the caller passes the true labels, which simply reset each
label's last position. There is no motion model, no structure model and no recovery.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from labeler_service.labeling.frame import LabeledFrame, MarkerState, frame_labels

if TYPE_CHECKING:
    from labeler_service.labeling.templates import LabelerModel


class ClosestPointLabeler:
    """Closest-point tracker with the :class:`~labeler_service.labeling.frame.FrameLabeler`
    interface."""

    model: LabelerModel | None = (
        None  # no structure, no motion model: nothing to boot or recover from
    )

    def __init__(
        self,
        marker_names: tuple[str, ...] | list[str],
        rate: float,
        max_speed_mm_s: float = 4000.0,
        min_gate_mm: float = 30.0,
    ) -> None:
        if not marker_names:
            raise ValueError("marker_names is empty")
        if not rate > 0:
            raise ValueError(f"rate must be > 0, got {rate}")
        self._names = tuple(marker_names)
        self.rate = float(rate)
        self.max_speed_mm_s = float(max_speed_mm_s)
        self.min_gate_mm = float(min_gate_mm)
        m = len(self._names)
        self._last = np.full((m, 3), np.nan, dtype=np.float64)
        self._t_last = np.full(m, -np.inf, dtype=np.float64)

    @property
    def marker_names(self) -> tuple[str, ...]:
        return self._names

    def warmup(self) -> None:
        """Nothing to compile: the baseline is numpy and scipy only."""

    def body_extent(self) -> np.ndarray:
        """All NaN: the baseline has no rigid bodies (and recovers nothing)."""
        return np.full(len(self._names), np.nan)

    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame:
        t0 = time.perf_counter_ns()
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        n, m = pts.shape[0], len(self._names)
        point_labels = np.full(n, -1, dtype=np.int32)
        if labels is not None:
            lab = frame_labels(labels, n, m)
            ok = lab >= 0
            point_labels[ok] = lab[ok]
        else:
            point_labels = self._assign(pts, float(t))
        hit = point_labels >= 0
        self._last[point_labels[hit]] = pts[hit]
        self._t_last[point_labels[hit]] = t
        positions = np.full((m, 3), np.nan, dtype=np.float32)
        positions[point_labels[hit]] = pts[hit]
        state = np.zeros(m, dtype=np.uint8)
        state[point_labels[hit]] = MarkerState.OBSERVED
        return LabeledFrame(
            t=float(t),
            point_labels=point_labels,
            positions=positions,
            state=state,
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    def _assign(self, pts: np.ndarray, t: float) -> np.ndarray:
        n = pts.shape[0]
        out = np.full(n, -1, dtype=np.int32)
        known = np.flatnonzero(~np.isnan(self._last[:, 0]))
        if n == 0 or known.size == 0:
            return out
        gates = np.maximum(self.min_gate_mm, self.max_speed_mm_s * (t - self._t_last[known]))
        tree = cKDTree(pts)
        # Candidate pairs inside each label's gate (query_ball_point accepts per-query radii).
        hits = tree.query_ball_point(self._last[known], r=gates)
        rows = np.repeat(np.arange(known.size), [len(h) for h in hits])
        if rows.size == 0:
            return out
        cols = np.fromiter((j for h in hits for j in h), dtype=np.int64, count=rows.size)
        d = np.linalg.norm(pts[cols] - self._last[known[rows]], axis=1)
        order = np.argsort(d, kind="stable")
        label_used = np.zeros(known.size, dtype=bool)
        for k in order:
            r, c = rows[k], cols[k]
            if label_used[r] or out[c] >= 0:
                continue
            label_used[r] = True
            out[c] = known[r]
        return out
