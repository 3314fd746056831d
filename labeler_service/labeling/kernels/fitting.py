"""Fitting rigid bodies (seed 003 Sec. 3.2, Eq. 5 and Algorithm 1).

Score of an assignment of a body's markers to points (Eq. 5, plus a motion term)::

    C = (sum_links exp(-(D_ij - D'_ij)^2 / (2 A_ij^2)) + w sum_markers exp(-d2_m / 2))
        / (links + w markers)

``A`` is floored at ``max(a_floor, a_rel D)`` (skin markers slide more on long links). A
marker may be "missing": each of its links then scores
``miss_term = exp(-c^2/2)``, i.e. the paper's large constant for ``D'`` expressed as a distance
off by ``c`` deviations, and its motion term is that of a point on the gate. So a candidate is
taken only when it fits its links better than ``c`` deviations on average, and ghosts or very
noisy points stay unlabeled. Links whose ``D`` or ``A`` are unknown score ``miss_term``.
``d2_m`` is the squared Mahalanobis distance of the point to the marker's prediction (Eq. 3-4):
it breaks ties between shapes that fit equally well.

The exhaustive search enumerates every option of every marker (its candidates not yet taken,
plus "missing"; two markers never share a point) depth first, best candidates first, and
prunes a branch when its partial sum plus an upper bound of what is left (1 per remaining link,
the best motion term per remaining marker) cannot beat the best complete assignment: branch and
bound returns exactly the ``itertools.product`` optimum (ties: the first in product order).

Line 12 of Algorithm 1 satisfies the best-scoring body first. In the wide re-acquisition pass
(``distrust``, ours, issue 10 class A) the order is the score times the body's *rigidity*
(:func:`_rigidity`): each link counts ``min(1, tolerance / (A + w D))`` with the sliding-window
``D``, ``A`` of Eq. 1-2 and the body-formation rule of
:mod:`labeler_service.labeling.training` (``body_tolerance_mm``, ``body_distance_weight``). A
body trained on a quiet window that the data later shows bending (a hand glued to the pelvis, an
upper arm and forearm trained straight) has window deviations far beyond that tolerance: its
links still score its own assignment, but it no longer pulls points before the bodies that the
data shows rigid. The first pass keeps the paper's order (measured: distrusting there too
lowers the matrix's worst scene again, docs/algorithm.md).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.state import MAX_BODY, NONE, UNDECIDED


@njit
def _pair_term(Db, Ab, pi, pj, a_floor, a_rel, miss_term, points, qi, qj):
    """One link of Eq. 5: markers at body positions ``pi``, ``pj`` on points ``qi``, ``qj``."""
    if qi < 0 or qj < 0:
        return miss_term
    d = Db[pi, pj]
    a = Ab[pi, pj]
    if not (d == d and a == a):
        return miss_term
    dx = np.float64(points[qi, 0]) - np.float64(points[qj, 0])
    dy = np.float64(points[qi, 1]) - np.float64(points[qj, 1])
    dz = np.float64(points[qi, 2]) - np.float64(points[qj, 2])
    dp = np.sqrt(dx * dx + dy * dy + dz * dz)
    if a < a_floor:
        a = a_floor
    if a < a_rel * d:
        a = a_rel * d
    e = (d - dp) / a
    return np.exp(-0.5 * e * e)


@njit
def _search_body(
    n,
    perm,
    opts,
    nopts,
    mot,
    Db,
    Ab,
    a_floor,
    a_rel,
    miss_term,
    w,
    points,
    choice,
    partial,
    best_choice,
):
    """Exhaustive branch-and-bound search over one body; returns the best normalised score.

    Position ``k`` of the search is body member ``perm[k]``; its options are
    ``opts[k, :nopts[k]]`` (point index or -1 = missing) with motion terms ``mot[k, o]``.
    ``best_choice[k]`` receives the chosen option index of position ``k``.
    """
    links = n * (n - 1) // 2
    norm = links + w * n
    if n == 0 or norm <= 0.0:
        return 0.0
    # rem[k]: upper bound of everything positions > k can still add
    rem = partial[n + 1 :]
    acc = 0.0
    for k in range(n - 1, -1, -1):
        rem[k] = acc
        best_m = 0.0
        for o in range(nopts[k]):
            if mot[k, o] > best_m:
                best_m = mot[k, o]
        acc += k + w * best_m
    best = -1.0
    depth = 0
    choice[0] = -1
    partial[0] = 0.0
    while depth >= 0:
        choice[depth] += 1
        o = choice[depth]
        if o >= nopts[depth]:
            depth -= 1
            continue
        q = opts[depth, o]
        dup = False
        if q >= 0:
            for l in range(depth):
                if opts[l, choice[l]] == q:
                    dup = True
                    break
        if dup:
            continue
        val = partial[depth] + w * mot[depth, o]
        pd = perm[depth]
        for l in range(depth):
            val += _pair_term(
                Db, Ab, pd, perm[l], a_floor, a_rel, miss_term, points, q, opts[l, choice[l]]
            )
        if val + rem[depth] <= best:
            continue
        if depth == n - 1:
            best = val
            for k in range(n):
                best_choice[k] = choice[k]
            continue
        depth += 1
        partial[depth] = val
        choice[depth] = -1
    return best / norm


@njit
def _point_markers(cand, ncand, n_points, pm_ptr, pm_idx):
    """CSR index point -> markers that have it as a candidate."""
    for j in range(n_points + 1):
        pm_ptr[j] = 0
    m = cand.shape[0]
    for i in range(m):
        for c in range(ncand[i]):
            pm_ptr[cand[i, c] + 1] += 1
    for j in range(n_points):
        pm_ptr[j + 1] += pm_ptr[j]
    fill = pm_ptr[:n_points].copy()
    for i in range(m):
        for c in range(ncand[i]):
            j = cand[i, c]
            pm_idx[fill[j]] = i
            fill[j] += 1


@njit
def _build_options(
    b,
    body_markers,
    body_size,
    assigned,
    owner,
    cand,
    cand_d2,
    ncand,
    miss_mot,
    perm,
    opts,
    nopts,
    mot,
):
    """Options of each member of body ``b`` in search order (fixed members first, then by
    increasing number of options). Returns the member count."""
    n = body_size[b]
    # counts per member for ordering
    cnt = np.empty(MAX_BODY, np.int64)
    for k in range(n):
        mk = body_markers[b, k]
        if assigned[mk] != UNDECIDED:
            cnt[k] = 0
        else:
            c = 1
            for o in range(ncand[mk]):
                if owner[cand[mk, o]] < 0:
                    c += 1
            cnt[k] = c
    # insertion sort of member positions by count (stable)
    for k in range(n):
        perm[k] = k
    for k in range(1, n):
        v = perm[k]
        l = k - 1
        while l >= 0 and cnt[perm[l]] > cnt[v]:
            perm[l + 1] = perm[l]
            l -= 1
        perm[l + 1] = v
    for k in range(n):
        mk = body_markers[b, perm[k]]
        a = assigned[mk]
        if a != UNDECIDED:
            opts[k, 0] = a
            mot[k, 0] = miss_mot
            if a >= 0:
                for o in range(ncand[mk]):
                    if cand[mk, o] == a:
                        mot[k, 0] = np.exp(-0.5 * cand_d2[mk, o])
                        break
            nopts[k] = 1
            continue
        c = 0
        for o in range(ncand[mk]):
            j = cand[mk, o]
            if owner[j] < 0:
                opts[k, c] = j
                mot[k, c] = np.exp(-0.5 * cand_d2[mk, o])
                c += 1
        opts[k, c] = NONE
        mot[k, c] = miss_mot
        nopts[k] = c + 1
    return n


@njit
def _flag(b, need, satisfied, queue, nq):
    """Queues body ``b`` for a re-search (once); returns the new queue length."""
    if not need[b] and not satisfied[b]:
        need[b] = True
        queue[nq] = b
        nq += 1
    return nq


@njit
def _first(score, b1, b2):
    """Line 12's order: the higher score first, ties by the lower body index."""
    return score[b1] > score[b2] or (score[b1] == score[b2] and b1 < b2)


@njit
def _heap_fix(heap, pos, size, score, i):
    """Restores the heap order around slot ``i`` after ``score[heap[i]]`` changed."""
    b = heap[i]
    while i > 0:  # up
        up = (i - 1) // 2
        if not _first(score, b, heap[up]):
            break
        heap[i] = heap[up]
        pos[heap[i]] = i
        i = up
    while True:  # down
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and _first(score, heap[c + 1], heap[c]):
            c += 1
        if not _first(score, heap[c], b):
            break
        heap[i] = heap[c]
        pos[heap[i]] = i
        i = c
    heap[i] = b
    pos[b] = i


@njit
def _still_feasible(b, body_markers, body_size, assigned, owner, best):
    """Whether body ``b``'s last best assignment survives the markers and points fixed since.

    Fixing markers and taking points only removes options, and a fixed marker scores exactly
    what the same option scored in the search, so a best assignment that is still feasible is
    still the best (an exact tie with another assignment aside: the new search order might
    list that one first). Re-searching is then wasted: with overlapping bodies most of the
    bodies flagged after each step are in this case.
    """
    for k in range(body_size[b]):
        mk = body_markers[b, k]
        q = best[b, k]
        a = assigned[mk]
        if a != UNDECIDED:
            if a != q:
                return False
        elif q >= 0 and owner[q] >= 0:
            return False
    return True


@njit
def _rigidity(b, body_size, D, A, tol, w):
    """How rigid body ``b`` has proven in the sliding window, in ``[0, 1]``: the mean over its
    links of ``min(1, tol / (A + w D))`` (1 for a link as rigid as body formation requires,
    :func:`labeler_service.labeling.training.select_bodies`). A link the window does not know
    (NaN) counts 1: no evidence against it."""
    n = body_size[b]
    acc = 0.0
    links = 0
    for i in range(n):
        for j in range(i + 1, n):
            links += 1
            d = D[b, i, j]
            a = A[b, i, j]
            c = a + w * d
            if c != c or c <= tol:
                acc += 1.0
            else:
                acc += tol / c
    return acc / links if links > 0 else 1.0


@njit
def _fit_bodies(bodies, points, miss_term, scratch, params, distrust=False):
    """Algorithm 1: satisfy the best-scoring body, fix its markers and points, recompute only
    the bodies whose candidate sets changed, until every body is satisfied.

    Reads the gate's ``scratch.cand``, ``cand_d2``, ``ncand`` and the structure model
    ``bodies`` (:class:`.state.Bodies`); ``miss_term`` is the Eq. 5 score of a missing
    marker's link (``params.miss_term``, or ``params.miss_reacq`` in the wide pass).
    In: ``scratch.assigned (M,)`` = ``UNDECIDED`` or fixed (point, ``NONE``),
    ``scratch.owner (N,)`` = ``NONE`` or fixed. Out: ``assigned[m]`` = point index or ``NONE``
    (missing), ``owner[j]`` = marker or ``NONE``, ``scratch.fit.score[b]`` = Eq. 5 score of the
    assignment each body was satisfied with.
    """
    body_markers, body_size = bodies.members, bodies.size
    Db, Ab, mb_ptr, mb_idx = bodies.D, bodies.A, bodies.mb_ptr, bodies.mb_idx
    cand, cand_d2, ncand = scratch.cand, scratch.cand_d2, scratch.ncand
    assigned, owner = scratch.assigned, scratch.owner
    fit = scratch.fit
    body_score, pm_idx, best = fit.score, fit.pm_idx, fit.best
    satisfied, need = fit.satisfied, fit.need
    perm, opts, nopts, mot = fit.perm, fit.opts, fit.nopts, fit.mot
    choice, partial, best_choice = fit.choice, fit.partial, fit.best_choice
    a_floor, a_rel = params.a_floor_mm, params.a_relative
    w, gate = params.motion_weight, params.gate_chi2
    nb = body_markers.shape[0]
    n_points = points.shape[0]
    miss_mot = np.exp(-0.5 * gate)
    pm_ptr = np.empty(n_points + 1, np.int64)
    _point_markers(cand, ncand, n_points, pm_ptr, pm_idx)
    # line 12's key per body: the score, times the rigidity with ``distrust``
    prio = np.empty(nb)
    weight = np.ones(nb)
    if distrust:
        tol, wd = params.body_tolerance_mm, params.body_distance_weight
        for b in range(nb):
            weight[b] = _rigidity(b, body_size, Db, Ab, tol, wd)
    # bodies to (re)search, each once (``need``), and an indexed max-heap of the unsatisfied
    # searched bodies by (``prio``, lower index): line 12 without a scan of every body per step
    queue = np.empty(nb, np.int64)
    nq = 0
    heap = np.empty(nb, np.int64)
    pos = np.full(nb, -1, np.int64)
    size = 0
    for b in range(nb):
        # a body with no undecided marker is satisfied already (second pass, re-acquisition)
        und = False
        for k in range(body_size[b]):
            if assigned[body_markers[b, k]] == UNDECIDED:
                und = True
                break
        satisfied[b] = not und
        need[b] = False
        body_score[b] = -1.0
        prio[b] = -1.0
        nq = _flag(b, need, satisfied, queue, nq)
    while True:
        # lines 5-11: (re)search the bodies that need it
        for e in range(nq):
            b = queue[e]
            need[b] = False
            if satisfied[b]:
                continue
            if body_score[b] >= 0.0 and _still_feasible(
                b, body_markers, body_size, assigned, owner, best
            ):
                continue
            n = _build_options(
                b,
                body_markers,
                body_size,
                assigned,
                owner,
                cand,
                cand_d2,
                ncand,
                miss_mot,
                perm,
                opts,
                nopts,
                mot,
            )
            s = _search_body(
                n,
                perm,
                opts,
                nopts,
                mot,
                Db[b],
                Ab[b],
                a_floor,
                a_rel,
                miss_term,
                w,
                points,
                choice,
                partial,
                best_choice,
            )
            for k in range(MAX_BODY):
                best[b, k] = NONE
            for k in range(n):
                best[b, perm[k]] = opts[k, best_choice[k]]
            body_score[b] = s
            prio[b] = s * weight[b]
            if pos[b] < 0:
                heap[size] = b
                pos[b] = size
                size += 1
            _heap_fix(heap, pos, size, prio, pos[b])
        nq = 0
        # line 12: the best unsatisfied body
        if size == 0:
            break
        r = heap[0]
        size -= 1
        pos[r] = -1
        if size > 0:
            heap[0] = heap[size]
            pos[heap[0]] = 0
            _heap_fix(heap, pos, size, prio, 0)
        satisfied[r] = True
        # lines 13-19: fix its markers and points; flag bodies whose candidates changed
        for k in range(body_size[r]):
            mk = body_markers[r, k]
            if assigned[mk] != UNDECIDED:
                continue
            q = best[r, k]
            assigned[mk] = q
            for e in range(mb_ptr[mk], mb_ptr[mk + 1]):
                nq = _flag(mb_idx[e], need, satisfied, queue, nq)
            if q >= 0:
                owner[q] = mk
                for e in range(pm_ptr[q], pm_ptr[q + 1]):
                    m2 = pm_idx[e]
                    for e2 in range(mb_ptr[m2], mb_ptr[m2 + 1]):
                        nq = _flag(mb_idx[e2], need, satisfied, queue, nq)
