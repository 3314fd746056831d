"""Small synthetic captures for tests that need no simulator and no real data."""

from __future__ import annotations

import numpy as np

from labeler_service.capture import Capture


def moving_clusters(
    rng: np.random.Generator,
    subjects: int = 2,
    markers: int = 6,
    frames: int = 120,
    rate: float = 120.0,
    spacing_mm: float = 400.0,
    speed_mm_s: float = 300.0,
) -> Capture:
    """Rigid marker clusters, one per subject, translating and turning smoothly."""
    t = np.arange(frames) / rate
    pos = np.empty((frames, subjects * markers, 3), dtype=np.float32)
    labels = []
    for s in range(subjects):
        shape = rng.normal(scale=80.0, size=(markers, 3))
        centre = np.stack(
            [
                s * spacing_mm + speed_mm_s * t,
                100 * np.sin(2 * np.pi * 0.5 * t + s),
                1000 + 50 * np.cos(2 * np.pi * 0.3 * t),
            ],
            axis=1,
        )
        ang = 0.8 * np.sin(2 * np.pi * 0.2 * t + s)
        c, sn = np.cos(ang), np.sin(ang)
        rot = np.zeros((frames, 3, 3))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -sn, sn, c, 1
        pos[:, s * markers : (s + 1) * markers] = centre[:, None, :] + np.einsum(
            "fij,mj->fmi", rot, shape
        )
        labels += [f"S{s}:m{i}" for i in range(markers)]
    return Capture(pos, tuple(labels), rate, source="synthetic")
