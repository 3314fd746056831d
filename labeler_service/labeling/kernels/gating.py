"""Mahalanobis gating (seed 003 Sec. 3.1): legitimate candidates of each marker.

With the factorised filter the innovation covariance is ``S = (p_pp + r) I``, so the squared
Mahalanobis distance of point ``j`` to marker ``m`` is ``|y_j - H x_m|^2 / S_m``. Points under the
chi-square gate are kept, at most ``K`` of them, best first (ties: lower point index first).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.spatial import _SLACK, _key_ordered, _lower, _span, _upper


@njit
def _before(d2, j, d2_other, j_other):
    """Candidate order: smaller distance first, ties by point index."""
    return d2 < d2_other or (d2 == d2_other and j < j_other)


@njit
def _insert(i, j, d2, K, cand, cand_d2, ncand):
    """Puts point ``j`` at distance ``d2`` into marker ``i``'s sorted list of at most ``K``
    candidates (ties: the lower point index first, in whatever order points arrive)."""
    c = ncand[i]
    if c == K and not _before(d2, j, cand_d2[i, K - 1], cand[i, K - 1]):
        return
    k = c if c < K else K - 1
    while k > 0 and _before(d2, j, cand_d2[i, k - 1], cand[i, k - 1]):
        if k < K:
            cand[i, k] = cand[i, k - 1]
            cand_d2[i, k] = cand_d2[i, k - 1]
        k -= 1
    cand[i, k] = j
    cand_d2[i, k] = d2
    if c < K:
        ncand[i] = c + 1


@njit
def _candidates(
    i, centre, scale, radius, points, index, owner, free_only, gate, K, cand, cand_d2, ncand
):
    """Marker ``i``'s candidates: the ``K`` points (free ones only with ``free_only``) whose
    ``|y - centre|^2 * scale`` is under ``gate``, i.e. within ``radius`` mm, best first."""
    ncand[i] = 0
    order = index.order
    px, py, pz = centre[0], centre[1], centre[2]
    lo, hi = _span(index, centre, radius)
    for k in range(lo, hi):
        j = order[k]
        if free_only and owner[j] >= 0:
            continue
        dx = points[j, 0] - px
        dy = points[j, 1] - py
        dz = points[j, 2] - pz
        d2 = (dx * dx + dy * dy + dz * dz) * scale
        if d2 < gate:  # also rejects NaN
            _insert(i, j, d2, K, cand, cand_d2, ncand)


@njit
def _gate(pred, s, active, points, index, gate, K, cand, cand_d2, ncand):
    """Fills ``cand (M, K)``, ``cand_d2 (M, K)`` and ``ncand (M,)`` in place (``index``: the
    sweep index of ``points``, :func:`.spatial._index`)."""
    order, axis = index.order, index.axis
    sp = _key_ordered(points, index)  # a slab is contiguous
    for i in range(pred.shape[0]):
        ncand[i] = 0
        if not active[i]:
            continue
        # _candidates(..., free_only=False) written out over ``sp``: the same slab, the same
        # sums in the same order of visit, so the same candidates, distances and ties
        radius = np.sqrt(gate * s[i])
        sc = 1.0 / s[i]
        px, py, pz = pred[i, 0], pred[i, 1], pred[i, 2]
        ca = px if axis == 0 else py
        if not (np.isfinite(ca) and radius >= 0.0):
            continue  # (_span: empty)
        rs = radius + _SLACK
        lo = _lower(index, ca - rs)
        hi = _upper(index, ca + rs)
        for k in range(lo, hi):
            dx = sp[k, 0] - px
            dy = sp[k, 1] - py
            dz = sp[k, 2] - pz
            d2 = (dx * dx + dy * dy + dz * dz) * sc
            if d2 < gate:  # also rejects NaN
                _insert(i, order[k], d2, K, cand, cand_d2, ncand)


# the common mode's first search radius (mm) for a marker with no point yet: a point within it
# is the nearest within the full radius too; none -> the full radius is searched
_CM_FIRST_MM = 40.0


@njit
def _select(v, lo, hi, k):
    """Partially sorts ``v[lo:hi+1]`` in place so that ``v[k]`` is its ``k``-th smallest value
    (quickselect, middle pivot); returns it."""
    while hi > lo:
        pivot = v[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return v[k]


@njit(inline="always")
def _row_d2(sp, k, cx, cy, cz):
    """Squared distance from row ``k`` of ``sp`` to ``(cx, cy, cz)``, summed x, y, z as
    :func:`.spatial._nearest` sums it (the same float result)."""
    d2 = 0.0
    d = sp[k, 0] - cx
    d2 += d * d
    d = sp[k, 1] - cy
    d2 += d * d
    d = sp[k, 2] - cz
    d2 += d * d
    return d2


@njit
def _median_inplace(v, n):
    """``np.median(v[:n])`` (``n >= 1``, no NaN) without its copy: ``v[:n]`` is reordered.
    The same value: the middle order statistic, or ``(a + b) / 2`` of the two middle ones."""
    h = n >> 1
    if n & 1:
        return _select(v, 0, n - 1, h)
    b = _select(v, 0, n - 1, h)
    a = v[0]  # the largest of v[:h], all <= b after the partition
    for t in range(1, h):
        if v[t] > a:
            a = v[t]
    return (a + b) / 2


@njit
def _common_mode(x, active, subj_ptr, subj_idx, points, index, radius, iters, buf, shift):
    """Per-subject common-mode correction of the predictions, in place.

    For every subject the offset from each tracked marker's prediction to its nearest point
    (within ``radius`` mm) is collected; the per-axis median of these offsets (at least 3) is
    added to the subject's predicted positions, ``iters`` times. Whole-body jumps that no
    per-marker motion model foresees (a capture's per-frame re-centring, a sudden step at a low
    rate) are thereby absorbed before the Mahalanobis gate. ``shift (S, 3)`` receives the
    total correction per subject.

    The nearest point is :func:`.spatial._nearest`'s (``ANY``, same sums, same ties) written out
    here, over a copy of the points in key order (a slab is contiguous), and from the second
    pass on within the distance of the last pass's point (the nearest is no farther: a slab of
    a few points instead of ~30). The median is taken in place in
    ``buf`` (:func:`_median_inplace`: ``np.median``'s value without its copy).
    """
    r2 = radius * radius
    order, axis = index.order, index.axis
    sp = _key_ordered(points, index)  # a slab is contiguous
    near = np.empty(subj_idx.shape[0], np.int64)  # each entry's nearest (key position), last pass
    for s in range(subj_ptr.shape[0] - 1):
        for a in range(3):
            shift[s, a] = 0.0
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            near[e] = -1
        for _it in range(iters):
            c = 0
            for e in range(subj_ptr[s], subj_ptr[s + 1]):
                i = subj_idx[e]
                if not active[i] or x[i, 0] != x[i, 0]:  # noqa: PLR0124 (NaN test)
                    continue
                cx, cy, cz = x[i, 0], x[i, 1], x[i, 2]
                ca = cx if axis == 0 else cy
                if not np.isfinite(ca):
                    near[e] = -1
                    continue  # (_span: empty)
                lim = r2
                h = near[e]
                if h >= 0:  # the last pass's point bounds the nearest: d2 <= d0
                    d0 = _row_d2(sp, h, cx, cy, cz)
                    if d0 < r2:
                        lim = d0 * (1.0 + 1e-12) + 1e-12  # just above d0: keeps its ties
                        if lim > r2:
                            lim = r2
                if lim == r2 and r2 > _CM_FIRST_MM * _CM_FIRST_MM:
                    lim = _CM_FIRST_MM * _CM_FIRST_MM  # a point within it is the nearest
                for _try in range(2):
                    rs = np.sqrt(lim) + _SLACK
                    lo = _lower(index, ca - rs)
                    hi = _upper(index, ca + rs)
                    best = lim
                    bk = -1
                    bj = -1
                    for k in range(lo, hi):
                        d2 = _row_d2(sp, k, cx, cy, cz)
                        if d2 < best or (d2 == best and bj >= 0 and order[k] < bj):
                            best = d2
                            bj = order[k]
                            bk = k
                    if bk >= 0 or lim == r2:
                        break
                    lim = r2  # none that near: the whole radius
                near[e] = bk
                if bk >= 0:
                    buf[0, c] = sp[bk, 0] - cx
                    buf[1, c] = sp[bk, 1] - cy
                    buf[2, c] = sp[bk, 2] - cz
                    c += 1
            if c < 3:
                break
            for a in range(3):
                d = _median_inplace(buf[a], c)
                shift[s, a] += d
                for e in range(subj_ptr[s], subj_ptr[s + 1]):
                    i = subj_idx[e]
                    if active[i]:
                        x[i, a] += d


@njit
def _regate(centre, lost, points, index, owner, radius, gate, K, cand, cand_d2, ncand):
    """Re-acquisition gate for ``lost`` markers: the ``K`` nearest points not yet owned within
    ``radius[i]`` mm of ``centre[i]`` (the rigid-body estimate, else the Kalman prediction);
    ``cand_d2`` is scaled so that the radius maps to ``gate``."""
    for i in range(centre.shape[0]):
        if lost[i]:
            sc = gate / (radius[i] * radius[i])
            r = radius[i]
            _candidates(
                i, centre[i], sc, r, points, index, owner, True, gate, K, cand, cand_d2, ncand
            )
