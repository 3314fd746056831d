"""Trilateration of a subject's missing markers (``boot_match._grow``) in one numba loop.

Every hypothesis and every completion of a boot ends with it: a marker with no node yet takes
the free point that keeps its rigid distances to the markers placed (three or more; with two,
the point must be the only one that also keeps its articulated pairs in range), when a marker
it may take its evidence from (``own``: its trained body's) is among them. In numpy it
was a KD-tree ball query and a dozen small array operations per missing marker and round:
~1 ms per call, ~130 calls per 10-performer attempt (a tenth of its CPU). Same rules, same
order (markers by index, three rounds, each placement seen by the next marker); the ball query
is a scan of the points (a few hundred). No fastmath: comparisons with NaN (pairs never seen
together) must stay false, as in numpy. The plain twin is ``tests/reference.py:grow``.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit(fastmath=False)
def _grow(assign, taken, pts, D, tol, bound, rigid, strict, link, own):
    """In place on ``assign (m,)`` (point per marker, -1) and ``taken (N,)``; see the module
    docstring and ``boot_match._grow``. ``own (m, m)``: a marker ``m`` joins only when a
    marker ``b`` with ``own[m, b]`` is among those placed (its own trained body's; ``rigid``
    lets every rigid partner count)."""
    m_all = assign.shape[0]
    n = pts.shape[0]
    have = np.empty(m_all, dtype=np.int64)
    near = np.empty(n, dtype=np.int64)
    todo = np.empty(m_all, dtype=np.int64)
    for _ in range(3):
        changed = False
        nh = 0
        nt = 0
        for k in range(m_all):
            if assign[k] >= 0:
                have[nh] = k
                nh += 1
            else:
                todo[nt] = k
                nt += 1
        for t in range(nt):
            m = todo[t]
            # rigid partners placed; the one nearest in D (the first minimum, NaN first)
            n_part = 0
            n_own = 0
            j = -1
            for h in range(nh):
                b = have[h]
                if own[m, b]:
                    n_own += 1
                if not rigid[m, b]:
                    continue
                n_part += 1
                if j < 0:
                    j = b
                elif np.isnan(D[m, b]):
                    if not np.isnan(D[m, j]):
                        j = b
                elif not np.isnan(D[m, j]) and D[m, b] < D[m, j]:
                    j = b
            if n_part < 2 or n_own == 0:
                continue
            r = D[m, j] + tol[m, j]
            c = pts[assign[j]]
            nn = 0
            for q in range(n):
                dx = pts[q, 0] - c[0]
                dy = pts[q, 1] - c[1]
                dz = pts[q, 2] - c[2]
                if dx * dx + dy * dy + dz * dz <= r * r and not taken[q]:
                    near[nn] = q
                    nn += 1
            if nn == 0:
                continue
            n_ok = 0
            n_ok3 = 0
            ok = np.zeros(nn, dtype=np.bool_)
            nfit = np.zeros(nn, dtype=np.int64)
            art_bad = np.zeros(nn, dtype=np.bool_)
            devs = np.empty((nn, nh))  # distance deviations, read again by the ranking below
            for i in range(nn):
                p = pts[near[i]]
                bad = False
                nf = 0
                ab = False
                for h in range(nh):
                    b = have[h]
                    pb = pts[assign[b]]
                    ex = p[0] - pb[0]
                    ey = p[1] - pb[1]
                    ez = p[2] - pb[2]
                    dev = np.sqrt(ex * ex + ey * ey + ez * ez) - D[m, b]
                    devs[i, h] = dev
                    adev = abs(dev)
                    if rigid[m, b] and adev <= tol[m, b]:
                        nf += 1
                    if strict[m, b]:
                        if adev > tol[m, b]:
                            bad = True
                    elif dev > bound[m, b]:
                        bad = True
                    lt = link[m, b]
                    if not rigid[m, b] and lt > 0 and adev > lt:
                        ab = True
                nfit[i] = nf
                art_bad[i] = ab
                ok[i] = (not bad) and nf >= 2 and 2 * nf >= n_part
                if ok[i]:
                    n_ok += 1
                    if nf >= 3:
                        n_ok3 += 1
            if n_ok3 == 0:
                # two rigid partners only: the point must be unique and keep its articulated
                # pairs in their trained range
                cnt = 0
                for i in range(nn):
                    if ok[i] and art_bad[i]:
                        ok[i] = False
                    if ok[i]:
                        cnt += 1
                if cnt != 1:
                    continue
            else:
                for i in range(nn):
                    if nfit[i] < 3:
                        ok[i] = False
            best = -1
            best_err = np.inf
            for i in range(nn):
                if not ok[i]:
                    continue
                s = 0.0
                for h in range(nh):
                    b = have[h]
                    dev = devs[i, h]
                    if rigid[m, b] and abs(dev) <= tol[m, b]:
                        e = dev / tol[m, b]
                        s += e * e
                err = s / max(nfit[i], 1)
                if best < 0 or err < best_err:
                    best, best_err = near[i], err
            if best >= 0:
                assign[m] = best
                taken[best] = True
                changed = True
                # the placement counts for the next markers of this round
                nh = 0
                for k in range(m_all):
                    if assign[k] >= 0:
                        have[nh] = k
                        nh += 1
        if not changed:
            return
