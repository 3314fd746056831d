"""Frames thinned for everyone (a system dropout), for the vanish check's test and benchmark
(``tests/labeling/test_presence.py``, ``benchmarks/thinned_frames.py``)."""

from __future__ import annotations

import numpy as np

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.labeler import Labeler
from labeler_service.scenes.simulate import simulate_scene


def thinned_errors(config: LabelerConfig, rate: float, keep: float, length: int = 1,
                   performers: int = 2, scenario: str = "walk", seed: int = 1) -> int:  # fmt: skip
    """Errors (samples whose point carries another label or none) of a simulated scene of 4 s
    labeled with its labels for the first 0.5 s, whose frame at 2 s, and the ``length - 1``
    after it, keep only ``keep`` of their points, drawn at random over the volume."""
    frames, init, at = int(4 * rate), int(0.5 * rate), int(2 * rate)
    cap = simulate_scene(performers, frames / rate, scenario, seed=seed, rate=rate, ghosts=0.0)
    pos = cap.positions.astype(np.float32)
    lab = Labeler(tuple(cap.labels), rate, config)
    order_rng = np.random.default_rng(seed)
    thin_rng = np.random.default_rng(100 + seed)
    wrong = 0
    for f in range(frames):
        frame = pos[f].copy()
        if at <= f < at + length:
            vis = np.flatnonzero(np.isfinite(frame[:, 0]))
            hide = thin_rng.choice(vis, vis.size - round(keep * vis.size), replace=False)
            frame[hide] = np.nan
        vis = np.flatnonzero(np.isfinite(frame[:, 0]))
        order = order_rng.permutation(vis.size)
        pts, truth = np.ascontiguousarray(frame[vis][order]), vis[order].astype(np.int32)
        out = lab.process(pts, f / rate, truth if f < init else None)
        if f >= init:
            wrong += int(np.count_nonzero(out.point_labels != truth))
    return wrong
