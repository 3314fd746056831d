"""The boot's reading score in one kernel: the negative log-likelihood of a few markers placed
on points, against each other and against the rest of their subject (``boot_match._pair_error``).

The readings of symmetric bodies, mirror segments, pairs and single markers, the fill and the
reclaim of limbs between subjects all compare such sums (``boot_match._readings``,
``_symmetries``, ``_relocate``, ``_complete_weak``, ``Booter._reclaim``): a boot attempt on 10
hugging performers at 360 Hz asks for ~3,600 of them. Each was a few small numpy calls (two
distance tables, fancy indexing into five template tables, ``isin``): ~0.1 ms, about a sixth of
the attempt. Here one loop over the pairs, with the formula of ``boot_match._nll``:

    e = |d - D| / scale;  cost = 0.5 (s e)^2 (pairs of one trained body)  or  log(1 + e^2)
    cost += log(scale);   0 where the pair carries no evidence or the cost is not finite

Its plain twin is ``boot_match._pair_error_numpy`` (the numpy version it replaced).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _pair_cost(D, scale, logs, gauss, use, a, b, pa, pb, pts, sigmas):
    """:func:`boot_match._nll` of marker ``a`` on point ``pa`` against ``b`` on ``pb``."""
    if not use[a, b]:
        return 0.0
    return _distance_cost(D, scale, logs, gauss, use, a, b, _dist(pts[pa], pts[pb]), sigmas)


@njit
def _dist(p, q):
    dx = p[0] - q[0]
    dy = p[1] - q[1]
    dz = p[2] - q[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@njit
def _distance_cost(D, scale, logs, gauss, use, a, b, d, sigmas):
    """:func:`boot_match._nll` of markers ``a`` and ``b`` at distance ``d``."""
    if not use[a, b]:
        return 0.0
    dab = D[a, b]
    # the inputs are checked, not the cost: with the project's fastmath set (reassoc, ...)
    # LLVM folded ``isfinite(cost)`` to true here and a NaN pair returned NaN (scale and its
    # log are finite by construction, and no distance in mm overflows e^2)
    if not (np.isfinite(d) and np.isfinite(dab)):
        return 0.0
    e = abs(d - dab) / scale[a, b]
    if gauss[a, b]:
        se = sigmas * e
        cost = 0.5 * se * se
    else:
        cost = np.log1p(e * e)
    return cost + logs[a, b]


@njit
def _pair_error(D, scale, logs, gauss, use, markers, points, assign, pts, sigmas):
    """Sum of :func:`_pair_cost` over the pairs among ``markers`` (placed on ``points``) and
    between them and every other marker placed by ``assign`` (-1: not placed)."""
    k = markers.shape[0]
    m = assign.shape[0]
    mine = np.zeros(m, dtype=np.bool_)
    for i in range(k):
        mine[markers[i]] = True
    total = 0.0
    for i in range(k):
        a, pa = markers[i], points[i]
        for j in range(i + 1, k):
            total += _pair_cost(D, scale, logs, gauss, use, a, markers[j], pa, points[j], pts,
                                sigmas)  # fmt: skip
        for b in range(m):
            pb = assign[b]
            if pb < 0 or mine[b]:
                continue
            total += _pair_cost(D, scale, logs, gauss, use, a, b, pa, pb, pts, sigmas)
    return total


@njit(fastmath=False)
def _constancy_counts(hist, pts, D, tol, strict):
    """Per placed marker ``i`` (on point ``pts[i]`` of ``hist (N, W, 3)``, the window's tracks):
    how many of its ``strict`` pair distances along the tracks were seen (both points tracked in
    that frame) and how many of those were off ``D +- tol`` (``boot_match._constancy``, which
    drops the markers off in most; ``D``, ``tol``, ``strict``: the ``(n, n)`` tables of the
    placed markers). The numpy version built the ``(n, n, W)`` distance block of each of its
    three rounds: ~2.7 ms a call, 72 calls in one extension of 10 hugging performers. No
    fastmath: the same distances to the bit as ``np.linalg.norm`` (``x0 + x1 + x2`` of the
    squares in that order), so a count at a tolerance's edge does not change."""
    n = pts.shape[0]
    W = hist.shape[1]
    seen = np.zeros(n, dtype=np.int64)
    bad = np.zeros(n, dtype=np.int64)
    for i in range(n):
        pi = pts[i]
        for j in range(n):
            if not strict[i, j]:
                continue
            pj = pts[j]
            dm = D[i, j]
            tl = tol[i, j]
            ns = 0
            nb = 0
            for w in range(W):
                dx = hist[pi, w, 0] - hist[pj, w, 0]
                dy = hist[pi, w, 1] - hist[pj, w, 1]
                dz = hist[pi, w, 2] - hist[pj, w, 2]
                d = np.sqrt(dx * dx + dy * dy + dz * dz)
                if np.isfinite(d):
                    ns += 1
                    if abs(d - dm) > tl:
                        nb += 1
            seen[i] += ns
            bad[i] += nb
    return seen, bad


@njit
def _swap_gains(D, scale, logs, gauss, use, have, ka, kb, pts, sigmas):
    """``(P,)``: per pair ``(have[ka[p]], have[kb[p]])`` of placed markers, how much lower the
    :func:`_distance_cost` sum of the two markers' pairs with every other placed marker is
    with their points exchanged (``pts (k, 3)``: the points of the placed markers ``have
    (k,)``; NaN where either point is untracked; an untracked third point's pairs count 0).
    ``boot_match._ledger_exchange``'s evidence; its numpy twin is
    ``tests/reference.py:swap_gains``."""
    P = ka.shape[0]
    k = have.shape[0]
    d = np.full((k, k), np.nan)
    now = np.zeros((k, k))  # marker i on its point against marker r on its point
    for i in range(k):
        for r in range(k):
            if r != i:
                d[i, r] = _dist(pts[i], pts[r])
                now[i, r] = _distance_cost(D, scale, logs, gauss, use, have[i], have[r],
                                           d[i, r], sigmas)  # fmt: skip
    out = np.full(P, np.nan)
    for p in range(P):
        i, j = ka[p], kb[p]
        if not (np.isfinite(pts[i, 0]) and np.isfinite(pts[j, 0])):
            continue
        a, b = have[i], have[j]
        g = 0.0
        for r in range(k):
            if r == i or r == j or not np.isfinite(pts[r, 0]):  # noqa: SIM109 (numba)
                continue
            m = have[r]
            if not (use[a, m] or use[b, m]):
                continue
            g += now[i, r] + now[j, r]
            g -= _distance_cost(D, scale, logs, gauss, use, a, m, d[j, r], sigmas)
            g -= _distance_cost(D, scale, logs, gauss, use, b, m, d[i, r], sigmas)
        out[p] = g
    return out
