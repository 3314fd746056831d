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

An index is a :class:`SweepIndex` ``(order, keys, axis, lo, inv_w, start)``: ``keys`` the sorted
coordinates (``inf`` for non-finite), ``order`` the point index of each key, ``axis`` the
coordinate sorted, and a bucket table over the keys' range: bucket ``b`` holds the keys ``v``
with ``floor((v - lo) * inv_w) = b`` and starts at position ``start[b]``.

The buckets (as many as points, ~4 mm each for a 2 m crowd) make both steps cheap where a
frame's data defeats the branch predictor: the sort is a counting sort by bucket then an
insertion sort inside each (stable, so the same order as a stable argsort: ties by point
index), and a slab's bounds are its bucket's start plus a step or two, not a binary search
(:func:`_lower`, :func:`_upper`: ``np.searchsorted``'s results). 10 performers at 360 Hz build
three indexes and search ~6,000 slabs a frame. A bucket that gets more than ``_BUCKET_MAX``
keys (a far outlier squeezes the others into a few buckets) falls back to ``np.argsort`` and
binary searches (``start`` empty).
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


# most keys a bucket may hold before the index falls back to a sort and binary searches
_BUCKET_MAX = 24


class SweepIndex(NamedTuple):
    """The points of one frame sorted along ``axis`` (0 = x, 1 = y): ``keys (N,)`` the sorted
    coordinates, ``order (N,)`` the point of each key; the bucket table ``lo``, ``inv_w``,
    ``start (B + 1,)`` (empty: none, binary searches; see the module docstring)."""

    order: np.ndarray
    keys: np.ndarray
    axis: int
    lo: float
    inv_w: float
    start: np.ndarray


@njit(inline="always")
def _bucket(v, lo, inv_w, nb):
    """The bucket of key ``v`` (clipped to ``[0, nb)``; NaN: 0)."""
    x = (v - lo) * inv_w
    if not x >= 1.0:  # (NaN too)
        return 0
    if x >= nb - 1:
        return nb - 1
    return int(x)


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
    n_fin = 0
    for j in range(n):
        v = np.float64(points[j, axis])
        if np.isfinite(v):
            raw[j] = v
            n_fin += 1
        else:
            raw[j] = np.inf
    a0, a1 = lo[axis], hi[axis]
    nb = max(n_fin, 1)
    inv_w = nb / (a1 - a0) if n_fin > 0 and a1 > a0 else 0.0
    if n_fin == 0:
        a0 = 0.0
    # counting sort by bucket (point order kept inside a bucket), non-finite keys last
    count = np.zeros(nb + 1, dtype=np.int64)
    bk = np.empty(n, dtype=np.int64)
    for j in range(n):
        b = _bucket(raw[j], a0, inv_w, nb) if raw[j] != np.inf else nb
        bk[j] = b
        count[b] += 1
    start = np.empty(nb + 1, dtype=np.int64)
    c = 0
    big = False
    for b in range(nb + 1):
        start[b] = c
        c += count[b]
        if b < nb and count[b] > _BUCKET_MAX:
            big = True
    if big:  # a few crowded buckets: sort, and search by halves
        order = np.argsort(raw, kind="mergesort")
        keys = np.empty(n)
        for k in range(n):
            keys[k] = raw[order[k]]
        return SweepIndex(order, keys, axis, a0, inv_w, np.empty(0, dtype=np.int64))
    order = np.empty(n, dtype=np.int64)
    keys = np.empty(n)
    fill = start.copy()
    for j in range(n):
        k = fill[bk[j]]
        fill[bk[j]] += 1
        order[k] = j
        keys[k] = raw[j]
    for b in range(nb):  # insertion sort inside each bucket: stable (ties keep point order)
        for k in range(start[b] + 1, start[b + 1]):
            v = keys[k]
            o = order[k]
            q = k
            while q > start[b] and keys[q - 1] > v:
                keys[q] = keys[q - 1]
                order[q] = order[q - 1]
                q -= 1
            keys[q] = v
            order[q] = o
    return SweepIndex(order, keys, axis, a0, inv_w, start)


@njit(inline="always")
def _bound(index, v, right):
    """``np.searchsorted(index.keys, v, side="right" if right else "left")`` (``v`` not NaN):
    the first position whose key is above ``v`` (``right``), else not below it."""
    keys, start = index.keys, index.start
    if start.shape[0] == 0:
        if right:
            return np.searchsorted(keys, v, side="right")
        return np.searchsorted(keys, v, side="left")
    # every key of an earlier bucket is below v (the bucket is monotone in the key); the step
    # back guards a bucket computed one off (the same formula, compiled in another function)
    k = start[_bucket(v, index.lo, index.inv_w, start.shape[0] - 1)]
    n = keys.shape[0]
    while k > 0 and (keys[k - 1] > v or (keys[k - 1] == v and not right)):
        k -= 1
    while k < n and (keys[k] < v or (keys[k] == v and right)):
        k += 1
    return k


@njit(inline="always")
def _lower(index, v):
    """``np.searchsorted(index.keys, v, side="left")`` (:func:`_bound`)."""
    return _bound(index, v, False)


@njit(inline="always")
def _upper(index, v):
    """``np.searchsorted(index.keys, v, side="right")`` (:func:`_bound`)."""
    return _bound(index, v, True)


@njit
def _span(index, centre, radius):
    """``[lo, hi)``: the positions in ``index`` whose key is within ``radius`` of ``centre``'s
    (``centre`` a 3-vector; empty when it is not finite)."""
    c = centre[index.axis]
    if not (np.isfinite(c) and radius >= 0.0):
        return 0, 0
    r = radius + _SLACK
    return _lower(index, c - r), _upper(index, c + r)


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


@njit
def _alone(points, index, c, radius, skip):
    """No point but ``skip`` lies within ``radius`` of ``c`` (strictly: one at ``radius`` does
    not count)."""
    r2 = radius * radius
    lo, hi = _span(index, c, radius)
    for k in range(lo, hi):
        j = index.order[k]
        if j == skip:
            continue
        d2 = 0.0
        for a in range(3):
            d = points[j, a] - c[a]
            d2 += d * d
        if d2 < r2:
            return False
    return True


@njit
def _free_within(points, index, centre, radius, owner, skip):
    """Some free point other than ``skip`` lies within ``radius`` of ``centre``."""
    lo, hi = _span(index, centre, radius)
    for k in range(lo, hi):
        j = index.order[k]
        if j == skip or owner[j] >= 0:
            continue
        d2 = 0.0
        for d in range(3):
            v = points[j, d] - centre[d]
            d2 += v * v
        if d2 <= radius * radius:
            return True
    return False


@njit
def _free_in(points, index, centre, radius, owner, cand, nc, cap):
    """Appends to ``cand[nc:]`` the free points (``owner < 0``) within ``radius`` of ``centre``,
    in index order, ``cap`` in all at most. Returns the new count."""
    lo, hi = _span(index, centre, radius)
    for k in range(lo, hi):
        j = index.order[k]
        if owner[j] >= 0:
            continue
        if nc >= cap:
            break
        d2 = 0.0
        for a in range(3):
            d = points[j, a] - centre[a]
            d2 += d * d
        if d2 <= radius * radius:
            cand[nc] = j
            nc += 1
    return nc
