"""A sweep index of one frame's points: every "points near here" query of the labeler.

The gate (Sec. 3.1), the common-mode shift, the re-acquisition gate and the 3D check each ask,
for hundreds of markers, which points lie within some radius of a position. Scanning all ``N``
points for each of ``M`` markers costs ``M x N``: 260,000 distances per pass at 10 performers,
and it was most of the frame. The index sorts the points once per frame along the horizontal
axis with the wider spread (performers stand side by side, never on top of each other); a query
binary-searches the slab ``|key - centre| <= radius`` and computes distances only inside it.

Results are those of the full scan: candidates are ordered by distance, ties by point index,
whatever order the slab is visited in. Points with a non-finite key sort last and are never
visited (they fail every distance test of the full scan too).

An index is a :class:`SweepIndex` ``(order, keys, axis)``: ``keys`` the sorted coordinates
(``inf`` for non-finite), ``order`` the point index of each key, ``axis`` the coordinate sorted.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from labeler_service._numba import njit

# slab bound slack (mm): a point exactly on the radius must not be lost to float rounding
_SLACK = 1e-6
# which points :func:`_nearest` considers
ANY = 0
FREE = 1  # not owned by a marker
OWNED = 2  # owned by a marker


class SweepIndex(NamedTuple):
    """The points of one frame sorted along ``axis`` (0 = x, 1 = y): ``keys (N,)`` the sorted
    coordinates, ``order (N,)`` the point of each key."""

    order: np.ndarray
    keys: np.ndarray
    axis: int


@njit
def _index(points):
    """Builds the sweep index of ``points (N, 3)``."""
    n = points.shape[0]
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for j in range(n):
        for a in range(2):
            v = points[j, a]
            if not np.isfinite(v):
                continue
            if v < lo[a]:
                lo[a] = v
            if v > hi[a]:
                hi[a] = v
    axis = 1 if hi[1] - lo[1] > hi[0] - lo[0] else 0
    raw = np.empty(n)
    for j in range(n):
        v = np.float64(points[j, axis])
        raw[j] = v if np.isfinite(v) else np.inf
    order = np.argsort(raw, kind="mergesort")
    keys = np.empty(n)
    for k in range(n):
        keys[k] = raw[order[k]]
    return SweepIndex(order, keys, axis)


@njit
def _span(index, centre, radius):
    """``[lo, hi)``: the positions in ``index`` whose key is within ``radius`` of ``centre``'s
    (``centre`` a 3-vector; empty when it is not finite)."""
    keys = index.keys
    c = centre[index.axis]
    if not (np.isfinite(c) and radius >= 0.0):
        return 0, 0
    r = radius + _SLACK
    lo = np.searchsorted(keys, c - r, side="left")
    hi = np.searchsorted(keys, c + r, side="right")
    return lo, hi


@njit
def _key_ordered(points, index):
    """A float64 copy of ``points`` in ``index``'s key order (row ``k`` is point
    ``index.order[k]``): a slab is then contiguous. For the kernels that search many slabs of
    one frame (the common-mode shift, the gate); the same coordinates, so the same sums."""
    order = index.order
    n = order.shape[0]
    sp = np.empty((n, 3))
    for k in range(n):
        for a in range(3):
            sp[k, a] = points[order[k], a]
    return sp


@njit
def _nearest(points, index, centre, lim2, owner, which, skip):
    """The point nearest ``centre`` with squared distance below ``lim2`` (ties: lower index);
    ``which`` = ``ANY``, ``FREE`` (``owner < 0``) or ``OWNED`` (``owner >= 0``, not ``skip``).
    Returns ``(j, d2)``, ``j = -1`` when there is none."""
    lo, hi = _span(index, centre, np.sqrt(lim2) if lim2 > 0.0 else 0.0)
    order = index.order
    best = lim2
    bj = -1
    for k in range(lo, hi):
        j = order[k]
        if which == FREE and owner[j] >= 0:
            continue
        if which == OWNED and (owner[j] < 0 or j == skip):
            continue
        d2 = 0.0
        for c in range(3):
            d = points[j, c] - centre[c]
            d2 += d * d
        if d2 < best or (d2 == best and bj >= 0 and j < bj):
            best = d2
            bj = j
    return bj, best
