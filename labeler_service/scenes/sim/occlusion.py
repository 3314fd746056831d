"""Measurement effects of the simulator: soft tissue, jitter, occlusion gaps, ghost points.

* **Soft-tissue wobble**: each marker moves on the skin by a smooth, time-correlated offset of a
  few millimetres (low-pass noise, about 3 Hz), so marker-pair distances on one segment vary by
  a few mm, as in real captures; seed 003's structure model ``A`` (s.d. of pair distances) sees
  exactly this.
* **Jitter**: white reconstruction noise (default 0.5 mm s.d. per axis).
* **Occlusion**: a marker starts a gap with hazard
  ``lambda = base + per_neighbour * min(c, 10) + contact * [d_min < contact_mm]`` per second,
  where ``c`` counts *other* performers' markers within ``near_mm`` and ``d_min`` is the distance
  to the closest one: cameras lose markers that are surrounded by other bodies. Gap lengths are
  log-uniform between ``gap_s`` bounds, so gaps are contiguous runs of several frames, never
  salt noise. Missing = NaN.
* **Ghosts**: short-lived spurious points (reflections, merged blobs) near a random marker,
  offset 2-10 cm, living a few frames and moving with that marker; packed greedily into as few
  ``*N`` columns as possible.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from labeler_service._numba import njit
from labeler_service.scenes.sim.motion import smooth_noise


@dataclass(frozen=True)
class OcclusionModel:
    """Parameters of the gap hazard (rates per second, distances in mm)."""

    base: float = 0.05
    per_neighbour: float = 0.18
    contact: float = 4.0
    near_mm: float = 150.0
    contact_mm: float = 30.0
    gap_s: tuple[float, float] = (0.025, 0.3)


def wobble(
    rng: np.random.Generator, n: int, rate: float, amplitude: np.ndarray, hz: float = 3.0
) -> np.ndarray:
    """``(n, M, 3)`` smooth soft-tissue offsets with per-marker s.d. ``amplitude`` (mm)."""
    return smooth_noise(rng, n, rate, (amplitude.shape[0], 3), hz) * amplitude[None, :, None]


def neighbour_stats(
    positions: np.ndarray, owner: np.ndarray, near_mm: float, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """For every frame and marker: how many markers of *other* performers are within
    ``near_mm``, and the distance to the closest one. Evaluated every ``stride`` frames and held.

    ``positions`` ``(F, M, 3)`` (complete, no NaN), ``owner`` ``(M,)`` performer index.
    Returns ``count`` ``(F, M)`` int32 and ``closest`` ``(F, M)`` float64 (inf with one
    performer). Validates, then runs the numba kernel :func:`_neighbour_kernel`.
    """
    pos = np.asarray(positions)
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"positions must be (F, M, 3), got {pos.shape}")
    own = np.ascontiguousarray(owner, dtype=np.int64)
    if own.shape != (pos.shape[1],):
        raise ValueError(f"owner must be ({pos.shape[1]},), got {own.shape}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if np.isnan(pos).any():
        raise ValueError("positions must be complete (no NaN): pass the noise-free poses")
    if not near_mm > 0:
        raise ValueError(f"near_mm must be > 0, got {near_mm}")
    f = pos.shape[0]
    idx = np.arange(0, f, stride)
    sub = np.ascontiguousarray(pos[idx], dtype=np.float64)
    count = np.zeros((idx.size, pos.shape[1]), dtype=np.int32)
    closest = np.full((idx.size, pos.shape[1]), np.inf)
    if idx.size:
        _neighbour_kernel(sub, own, float(near_mm) ** 2, count, closest)
    hold = np.minimum(np.arange(f) // stride, max(idx.size - 1, 0))
    return count[hold], closest[hold]


@njit
def _neighbour_kernel(pos, owner, near2, count, closest):  # pragma: no cover - compiled
    """Pairwise pass per frame over markers of different owners (see neighbour_stats)."""
    n_frames, n_markers = pos.shape[0], pos.shape[1]
    for f in range(n_frames):
        for i in range(n_markers):
            xi, yi, zi = pos[f, i, 0], pos[f, i, 1], pos[f, i, 2]
            for j in range(i + 1, n_markers):
                if owner[i] == owner[j]:
                    continue
                dx = pos[f, j, 0] - xi
                dy = pos[f, j, 1] - yi
                dz = pos[f, j, 2] - zi
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < near2:
                    count[f, i] += 1
                    count[f, j] += 1
                if d2 < closest[f, i]:
                    closest[f, i] = d2
                if d2 < closest[f, j]:
                    closest[f, j] = d2
        for i in range(n_markers):
            closest[f, i] = np.sqrt(closest[f, i])


def occlusion_mask(
    rng: np.random.Generator,
    count: np.ndarray,
    closest: np.ndarray,
    rate: float,
    model: OcclusionModel = OcclusionModel(),
) -> np.ndarray:
    """``(F, M)`` bool, True where a marker is occluded (see the module docstring)."""
    f, m = count.shape
    lam = (
        model.base
        + model.per_neighbour * np.minimum(count, 10)
        + model.contact * (closest < model.contact_mm)
    )
    p = -np.expm1(-lam / rate)
    fr, mk = np.nonzero(rng.random((f, m)) < p)
    lo, hi = (math.log(x) for x in model.gap_s)
    seconds = np.exp(rng.uniform(lo, hi, size=fr.size))
    length = np.maximum(2, np.rint(seconds * rate)).astype(np.intp)
    edges = np.zeros((f + 1, m), dtype=np.int32)
    np.add.at(edges, (fr, mk), 1)
    np.add.at(edges, (np.minimum(fr + length, f), mk), -1)
    return np.cumsum(edges[:f], axis=0) > 0


def ghost_points(
    rng: np.random.Generator,
    anchors: np.ndarray,
    rate: float,
    mean_per_frame: float,
    life_s: tuple[float, float] = (1.5 / 120.0, 8.5 / 120.0),
    offset_mm: tuple[float, float] = (20.0, 100.0),
) -> np.ndarray:
    """``(F, G, 3)`` ghost tracks (NaN outside their short lives) near random anchor markers.

    Births are Poisson with rate ``mean_per_frame / mean_life`` per frame so that on average
    ``mean_per_frame`` ghosts are present; each follows its anchor marker at a fixed random
    offset (2-10 cm) plus 1 mm jitter. Ghosts are packed greedily into reusable columns.
    """
    f, m, _ = anchors.shape
    if mean_per_frame <= 0 or f == 0 or m == 0:
        return np.full((f, 0, 3), np.nan, dtype=np.float64)
    lo = max(1, round(life_s[0] * rate))
    hi = max(lo, round(life_s[1] * rate))
    births = rng.poisson(mean_per_frame * f / ((lo + hi) / 2.0))
    start = np.sort(rng.integers(0, f, size=births))
    life = rng.integers(lo, hi + 1, size=births)
    anchor = rng.integers(0, m, size=births)
    direction = rng.standard_normal((births, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    offset = direction * rng.uniform(*offset_mm, size=(births, 1))

    column = np.empty(births, dtype=np.intp)
    free: list[tuple[int, int]] = []  # (frame the column frees up, column)
    n_cols = 0
    for i in range(births):
        if free and free[0][0] <= start[i]:
            _, c = heapq.heappop(free)
        else:
            c = n_cols
            n_cols += 1
        column[i] = c
        heapq.heappush(free, (int(start[i] + life[i]) + 1, c))  # one empty frame between ghosts

    out = np.full((f, n_cols, 3), np.nan)
    for i in range(births):
        s, e = start[i], min(f, start[i] + life[i])
        out[s:e, column[i]] = anchors[s:e, anchor[i]] + offset[i]
    out += rng.normal(0.0, 1.0, out.shape)
    return out
