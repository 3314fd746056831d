"""3D template check, swap repair and joint re-acquisition of rigid bodies (ours, issue 10).

Eq. 5 scores only pair distances, so a permutation of a body's labels whose distances are about
right (a cluster plate, a dense shoulder set) or its mirror image (same distances, opposite
chirality) fits as well as the truth, and a body whose markers were all hidden is re-acquired
one marker at a time from stale per-marker predictions. Here every rigid body keeps a reference
*shape*: ``bodies.ref (B, 8, 3)``, its members' positions the last time all were observed for
``snapshot_age`` frames and the body fitted its previous shape (a wrong assignment never
becomes the reference). A body is checked when it is suspect - a member missing or observed
for fewer than ``repair_age`` frames, a repair pending, or its turn in a round robin over
``verify_every`` frames:

1. the current assignment's shape residual: RMS after the best *proper* rotation and
   translation (Kabsch, no reflection) of the reference onto the current points - this sees
   chirality, which distances cannot;
2. if that residual exceeds ``repair_check_mm``, or a member is missing while free points lie
   near the body, :func:`_fit_template` searches every injective map of the body's members onto
   its current points and the free points near it (or "missing"), pruned by the reference pair
   distances (``repair_tol_mm`` + 3 trained deviations), for the one with the most members whose
   RMS is within ``repair_check_mm``, then the smallest RMS (an interpretation tree);
3. held points are relabeled only in a body with a member observed for fewer than
   ``repair_age`` frames: a body whose markers were all tracked for long keeps its points
   (swaps start when markers are re-acquired, and a deforming body must not be "repaired"
   against a stale reference). Every change needs a map of 4+ points: a triangle has no
   chirality, and a near-isosceles one fits its own permutations (Eq. 5 already sees what
   three points show) - except, for a body whose reference is a model's, a map of three points
   that name themselves (:func:`_unique3`) when the body held at most one of them and it keeps
   a held point that was alone in its marker's gate (:func:`_keeps_held`). A map for a body that had
   fewer than three points (joint re-acquisition: all returning points are assigned together
   by the body's shape) is taken at once; one that only adds free points to a body seen with
   three or more is left to the per-marker 3D check (:func:`.rigid._verify`, which refuses
   ghosts off the rigid estimate); a map that relabels points already held is taken when it
   fits clearly better (RMS below a third of the current, or more members) for ``repair_frames``
   consecutive checks (swap repair). "Clearly better" is an RMS below a third of the current
   one: real repairs on the matrix went from 8-45 mm to 0.5-3.3 mm (ratio <= 0.25, or more
   points); the one false repair seen, a wrist/hand body flexed against a stale reference in
   the simulated 10-person hug, from 10.1 to 4.4 mm (0.44). A map of *fewer* members than the
   body holds (its best map within ``repair_check_mm`` leaves a member out: a skin marker that
   slid while the body was hidden) is taken the same way when it has 4+ points, fits clearly
   better than the current assignment *of the same members*, and moves no point of a member
   tracked for ``repair_age`` frames; a member it leaves out keeps its point.

A body whose current assignment no map beats (it deformed, or is not rigid) keeps it, and
when fully observed by markers tracked for ``repair_age`` frames its points become the new
reference (the reference follows slow soft-tissue drift) - but only when their pair distances
differ from the trained ones (``D0``, beyond 3 trained deviations) by at most ``repair_tol_mm``
more than the current reference's do (:func:`_refresh_ok`). A swap changes
the distances at once and drift does not, so a swap that survives ``repair_age`` frames no
longer becomes the reference it is checked against (issue 10: tennis alone 90.0 -> 93.8 %,
longest swap 350 -> 57 frames).

*Pair check* (:func:`_pair_check`, ``repair_pairs``): the template fit needs a body of four
points and relabels inside one body; a marker in triangles only (a dancer's radius and ulna)
or whose wrong point only its other bodies can refute stays swapped. For every marker
re-acquired less than ``repair_age`` frames ago, the trained pair distances (``D0`` beyond 3
floored deviations ``A0``) to the long-tracked members of all its bodies, over the links that
do not bend now (window ``A`` within 3 floored ``A0``; a body trained across a joint held still
keeps its rigid links as evidence), decide whether its point belongs to a body partner
(missing: the point moves; holding a point and re-acquired recently too: the two exchange)
when the summed mean excess exceeds ``repair_check_mm`` and the change cuts it to a third,
unless it makes a 4+-point body with a reference fail its proper-rotation template
(:func:`_mirrors`: distances cannot see a mirror).

``bodies.ok[b]`` records whether the body's assignment passed the check (the guard of the
sliding-window update, :mod:`.window`).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.rigid import _kabsch
from labeler_service.labeling.kernels.spatial import _free_in
from labeler_service.labeling.kernels.state import MAX_CAND, NONE


@njit
def _shape_rms(ref, pts, choice, n, src, dst, R, t):
    """``(count, rms)``: how many of the ``n`` members have a point (``choice[k]`` a row of
    ``pts`` or -1) and the RMS (mm) of their reference positions ``ref (n, 3)`` after the best
    proper rigid motion onto those points; ``rms = inf`` with fewer than 3."""
    c = 0
    for k in range(n):
        p = choice[k]
        if p < 0:
            continue
        for a in range(3):
            src[c, a] = ref[k, a]
            dst[c, a] = pts[p, a]
        c += 1
    if c < 3:
        return c, np.inf
    _kabsch(src, dst, c, R, t)
    e2 = 0.0
    for i in range(c):
        for a in range(3):
            d = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a] - dst[i, a]
            e2 += d * d
    return c, np.sqrt(e2 / c)


@njit
def _fit_template(n, ref, tol, pts, nc, accept_mm, max_nodes, pos, used, choice, best, kab):
    """Best map of ``n`` body members (reference positions ``ref (n, 3)``) onto the candidate
    points ``pts[:nc]`` (rows of a ``(nc, 3)`` array) or "missing": every member pair that both
    have a point keeps its reference distance within ``tol[i, j]``; among maps whose shape RMS
    (:func:`_shape_rms`) is at most ``accept_mm``, the one with the most points, then the
    smallest RMS. Depth-first with a count bound, at most ``max_nodes`` nodes. ``best[k]`` gets
    the candidate row of member ``k`` (-1 = missing); returns ``(count, rms)`` (``(0, inf)``
    when no map of 3+ points qualifies). ``pos``, ``choice (8,)``, ``used (nc,)``: work space;
    ``kab``: :class:`.state.KabschScratch`."""
    best_cnt = 0
    best_rms = np.inf
    for k in range(n):
        best[k] = -1
    if n == 0:
        return 0, np.inf
    for p in range(nc):
        used[p] = False
    nodes = 0
    k = 0
    cnt = 0
    pos[0] = -1
    while k >= 0:
        if 0 <= pos[k] < nc:
            used[pos[k]] = False
            cnt -= 1
        pos[k] += 1
        while pos[k] < nc:
            p = pos[k]
            ok = not used[p]
            j = 0
            while ok and j < k:
                q = pos[j]
                if q < nc:
                    d2 = 0.0
                    r2 = 0.0
                    for a in range(3):
                        d = pts[p, a] - pts[q, a]
                        d2 += d * d
                        d = ref[k, a] - ref[j, a]
                        r2 += d * d
                    ok = abs(np.sqrt(d2) - np.sqrt(r2)) <= tol[k, j]
                j += 1
            if ok:
                break
            pos[k] += 1
        if pos[k] > nc:  # every option of member k tried
            k -= 1
            continue
        if pos[k] < nc:
            used[pos[k]] = True
            cnt += 1
        if cnt + (n - 1 - k) < best_cnt:
            continue  # cannot reach the best count any more
        nodes += 1
        if nodes > max_nodes:
            if 0 <= pos[k] < nc:
                used[pos[k]] = False
            break
        if k < n - 1:
            k += 1
            pos[k] = -1
            continue
        # a complete map
        if cnt < 3 or cnt < best_cnt:
            continue
        for i in range(n):
            choice[i] = pos[i] if pos[i] < nc else -1
        c, rms = _shape_rms(ref, pts, choice, n, kab.src, kab.dst, kab.R, kab.t)
        if rms > accept_mm:
            continue
        if c > best_cnt or rms < best_rms:
            best_cnt = c
            best_rms = rms
            for i in range(n):
                best[i] = choice[i]
    return best_cnt, best_rms


@njit
def _d0_excess(b, bodies, points, sel, n):
    """The largest amount (mm, at least 0) by which a pair distance of the points ``sel[k]``
    (rows of ``points`` or -1) differs from the trained ``D0`` beyond 3 trained deviations
    ``A0``, over the member pairs with both points and a known ``D0``."""
    worst = 0.0
    for i in range(n):
        if sel[i] < 0:
            continue
        for j in range(i + 1, n):
            if sel[j] < 0:
                continue
            d0 = bodies.D0[b, i, j]
            if d0 != d0:
                continue
            d2 = 0.0
            for a in range(3):
                d = points[sel[i], a] - points[sel[j], a]
                d2 += d * d
            a0 = bodies.A0[b, i, j]
            x = abs(np.sqrt(d2) - d0) - (3.0 * a0 if a0 == a0 else 0.0)
            if x > worst:
                worst = x
    return worst


@njit
def _refresh_ok(b, bodies, points, cur, n, idx, tol):
    """Whether the current points (``cur[k]`` of member ``k``) may replace the body's reference:
    their pair distances differ from the trained ones (:func:`_d0_excess`) by at most ``tol``
    more than the reference's do. A swap changes the distances at once, slow drift does not.
    ``idx (>= n,)``: work space."""
    for k in range(n):
        idx[k] = k
    new = _d0_excess(b, bodies, points, cur, n)
    old = _d0_excess(b, bodies, bodies.ref[b], idx, n)
    return new <= old + tol


@njit
def _snapshot_body(b, bodies, points, cur, n):
    """``bodies.ref[b]`` = the body's current points (``cur[k]`` the point of member ``k``)."""
    for k in range(n):
        for a in range(3):
            bodies.ref[b, k, a] = points[cur[k], a]
    bodies.ref_ok[b] = True
    bodies.ref_model[b] = False


@njit
def _unique3(ref, pts, best, n, rms, check_mm, kab):
    """Whether a 3-point map ``best`` (member -> row of ``pts``, -1 missing) of a body with
    reference ``ref`` is the only reading of its three points: every other assignment of the
    same points to the same members fits worse than ``check_mm`` and than 3 ``rms`` (a scalene
    triangle names its corners by its side lengths; a near-isosceles one does not)."""
    ks = np.empty(3, dtype=np.int64)
    c = 0
    for k in range(n):
        if best[k] >= 0:
            ks[c] = best[k]
            c += 1
    if c != 3:
        return False
    choice = np.empty(n, dtype=np.int64)
    perms = ((0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
    for perm in perms:
        c = 0
        for k in range(n):
            if best[k] >= 0:
                choice[k] = ks[perm[c]]
                c += 1
            else:
                choice[k] = -1
        _, r = _shape_rms(ref, pts, choice, n, kab.src, kab.dst, kab.R, kab.t)
        if r <= check_mm or r <= 3.0 * rms:
            return False
    return True


@njit
def _bends(a, a0, d0, a_floor, a_rel):
    """A body link bends now: its window deviation ``a`` exceeds 3 trained deviations ``a0``
    floored as in Eq. 5 (``a_floor``, ``a_rel`` times its distance ``d0``) - a link trained
    across a joint held still."""
    return a > 3.0 * max(a0, a_floor, a_rel * d0)


@njit
def _link_excess(m, p, skip, points, bodies, assigned, age, min_age, a_floor, a_rel):
    """``(sum, count)`` over the trained links of marker ``m`` (every body that contains it) to
    *anchors* - members observed now and for at least ``min_age`` frames before, other than
    ``m`` and ``skip`` - of how far (mm) point ``p``'s distance to the anchor's point differs
    from the trained ``D0`` beyond 3 trained deviations ``A0`` (0 within them). A link that
    bends now (window ``A`` beyond 3 floored ``A0``: trained across a joint held still) is no
    evidence and is left out; the body's other links still count."""
    members, size, D0, A0, A = bodies.members, bodies.size, bodies.D0, bodies.A0, bodies.A
    mb_ptr, mb_idx = bodies.mb_ptr, bodies.mb_idx
    tot = 0.0
    cnt = 0
    for e in range(mb_ptr[m], mb_ptr[m + 1]):
        b = mb_idx[e]
        n = size[b]
        i = 0
        while i < n and members[b, i] != m:
            i += 1
        for j in range(n):
            k = members[b, j]
            if j == i or k == skip or assigned[k] < 0 or age[k] < min_age:
                continue
            d0 = D0[b, i, j]
            a0 = A0[b, i, j]
            if d0 != d0 or a0 != a0:
                continue
            if _bends(A[b, i, j], a0, d0, a_floor, a_rel):
                continue  # a link that bends now (trained across a joint held still)
            a0 = max(a0, a_floor, a_rel * d0)  # the floor of Eq. 5
            q = assigned[k]
            d2 = 0.0
            for a in range(3):
                d = points[p, a] - points[q, a]
                d2 += d * d
            x = abs(np.sqrt(d2) - d0) - 3.0 * a0
            if x > 0.0:
                tot += x
            cnt += 1
    return tot, cnt


@njit
def _link_mean(m, p, skip, points, bodies, assigned, age, params, min_links, min_age):
    """Mean of :func:`_link_excess` per link (anchors observed ``min_age`` frames); ``nan`` with
    fewer than ``min_links`` links."""
    tot, cnt = _link_excess(
        m,
        p,
        skip,
        points,
        bodies,
        assigned,
        age,
        min_age,
        params.a_floor_mm,
        params.a_relative,
    )
    if cnt < min_links:
        return np.nan
    return tot / cnt


@njit
def _keeps_held(b, cur, best, cand, n, members, gate_cand, gate_n):
    """Whether a map (``best``: rows of ``cand`` per member, -1 none) of body ``b`` keeps every
    point the body holds (``cur``) that names its member - for the same member or another.
    Three points that name themselves are a reading of the points the body holds, the held one
    among them; a map that leaves a held point for others overturns it, which only a doubtful
    track allows: a held point names its member when it was the only point in the member's
    gate this frame (``gate_n[m] == 1`` and ``gate_cand[m, 0]`` that point: ``scratch.ncand``,
    ``scratch.cand``). A booted jumper's shoulder, tracked on its own point, was read 476 mm
    away onto a neighbour's neck marker that fitted with two free points (holdout21 ``rate``
    from a model: the upper body read wrong for the whole scene); at 12.5 Hz a gate holds
    several points, and the labeled start's reading of them is the better one."""
    for k in range(n):
        if cur[k] < 0:
            continue
        m = members[b, k]
        if gate_n[m] != 1 or gate_cand[m, 0] != cur[k]:
            continue  # not alone in its gate (or held from outside it): a doubtful track
        kept = False
        for j in range(n):
            if best[j] >= 0 and cand[best[j]] == cur[k]:
                kept = True
        if not kept:
            return False
    return True


@njit
def _rms_with(b, bodies, points, assigned, m, pm, m2, pm2, kab):
    """``(count, rms)`` of :func:`_shape_rms` for body ``b`` against its reference when marker
    ``m`` holds point ``pm`` and ``m2`` holds ``pm2`` (-1: none), the others what they hold."""
    n = bodies.size[b]
    pts, choice = bodies.work_pts, bodies.work_choice
    for k in range(n):
        mk = bodies.members[b, k]
        p = pm if mk == m else (pm2 if mk == m2 else assigned[mk])
        choice[k] = k if p >= 0 else -1
        if p >= 0:
            for a in range(3):
                pts[k, a] = points[p, a]
    return _shape_rms(bodies.ref[b], pts, choice, n, kab.src, kab.dst, kab.R, kab.t)


@njit
def _mirrors(bodies, points, assigned, m, pm, m2, pm2, check_mm, kab):
    """Whether giving ``m`` point ``pm`` and ``m2`` point ``pm2`` makes a body of either with a
    reference and 4+ points fail the template check (RMS over ``check_mm``) and fit worse than
    now: distances cannot tell a mirrored pair, the proper-rotation fit can."""
    for side in range(2):
        mk = m if side == 0 else m2
        for e in range(bodies.mb_ptr[mk], bodies.mb_ptr[mk + 1]):
            b = bodies.mb_idx[e]
            if not bodies.ref_ok[b] or bodies.size[b] < 4:
                continue
            c1, r1 = _rms_with(b, bodies, points, assigned, m, pm, m2, pm2, kab)
            if c1 < 4 or r1 <= check_mm:
                continue
            _, r0 = _rms_with(b, bodies, points, assigned, m, assigned[m], m2, assigned[m2], kab)
            if r1 > r0:
                return True
    return False


@njit
def _best_partner(m, a, points, bodies, assigned, age, active, params, anchor_age, scratch):
    """The body partner of marker ``m`` (holding point ``a``) that :func:`_pair_check` gives
    ``a`` to, judged on anchors observed ``anchor_age`` frames, or -1."""
    members, size, mb_ptr, mb_idx = bodies.members, bodies.size, bodies.mb_ptr, bodies.mb_idx
    min_age = params.repair_age
    floor = params.repair_check_mm
    now_m = _link_mean(m, a, -1, points, bodies, assigned, age, params, 2, anchor_age)
    if not now_m > 0.0:
        return -1
    best_gain = 0.0
    best_m2 = -1
    for e in range(mb_ptr[m], mb_ptr[m + 1]):
        b = mb_idx[e]
        for j in range(size[b]):
            m2 = members[b, j]
            if m2 == m or not active[m2]:
                continue
            p2 = assigned[m2]
            if p2 >= 0 and age[m2] >= min_age:
                continue  # a marker tracked for long keeps its point (its track says so)
            after = _link_mean(m2, a, m, points, bodies, assigned, age, params, 2, anchor_age)
            if after != after:
                continue
            before = _link_mean(m, a, m2, points, bodies, assigned, age, params, 2, anchor_age)
            if before != before:
                continue
            if p2 >= 0:
                b2 = _link_mean(m2, p2, m, points, bodies, assigned, age, params, 2, anchor_age)
                a2 = _link_mean(m, p2, m2, points, bodies, assigned, age, params, 2, anchor_age)
                if b2 != b2 or a2 != a2:
                    continue
                before += b2
                after += a2
            if before > floor and 3.0 * after <= before and before - after > best_gain:
                if _mirrors(bodies, points, assigned, m, p2, m2, a, floor, scratch.kab):
                    continue
                best_gain = before - after
                best_m2 = m2
    return best_m2


@njit
def _pair_check(points, tracks, bodies, scratch, params):
    """Relabels a freshly re-acquired marker's point when a body partner fits it by the trained
    pair distances and the long-tracked anchors (the module docstring, "pair check"): for every
    marker ``m`` holding point ``a`` and observed for fewer than ``repair_age`` frames, and every
    partner ``m2`` sharing a body with it, the mean excess of :func:`_link_excess` (per marker,
    over its links to anchors) before and after giving ``a`` to ``m2`` (``m2`` missing: ``m``
    loses the point) or exchanging the two points (``m2`` holds one and was also observed for
    fewer than ``repair_age`` frames). The change with the largest gain is made when the excess
    after is at most a third of the excess before, the excess before exceeds
    ``repair_check_mm``, and :func:`_mirrors` does not refuse it.

    *Senior anchors* (``repair_senior_frames`` = S > 0): when the long-tracked anchors ask for
    no change, anchors observed S frames longer than ``m`` (not yet ``repair_age``) are asked:
    a whole limb re-acquired after a fast move has no long-tracked member, and its links to the
    trunk bend. Such a change is made only when the same partner is asked for in two
    consecutive frames (``tracks.pair_wait``): young anchors can be wrong themselves. Returns
    the number of changes."""
    assigned, owner, obs = scratch.assigned, scratch.owner, scratch.obs
    active, age, wait = tracks.active, tracks.age, tracks.pair_wait
    min_age = params.repair_age
    changes = 0
    for m in range(assigned.shape[0]):
        a = assigned[m]
        if a < 0 or not active[m] or age[m] >= min_age:
            wait[m] = -1
            continue
        m2 = _best_partner(m, a, points, bodies, assigned, age, active, params, min_age, scratch)
        senior = min(min_age, age[m] + params.repair_senior_frames)
        if m2 < 0 and params.repair_senior_frames > 0 and senior < min_age:
            m2 = _best_partner(m, a, points, bodies, assigned, age, active, params, senior, scratch)
            if m2 >= 0 and wait[m] != m2:
                wait[m] = m2  # asked for once: made if asked for again in the next frame
                continue
        wait[m] = -1
        if m2 < 0:
            continue
        p2 = assigned[m2]
        owner[a] = m2
        assigned[m2] = a
        if p2 >= 0:
            owner[p2] = m
            assigned[m] = p2
        else:
            assigned[m] = NONE
        for c in range(3):
            obs[m2, c] = points[a, c]
            obs[m, c] = points[p2, c] if p2 >= 0 else np.nan
        changes += 1
    return changes


@njit
def _extent(ref, n):
    """The largest distance (mm) of a reference position ``ref[:n]`` from their centroid."""
    cx = cy = cz = 0.0
    for k in range(n):
        cx += ref[k, 0]
        cy += ref[k, 1]
        cz += ref[k, 2]
    cx, cy, cz = cx / n, cy / n, cz / n
    e2 = 0.0
    for k in range(n):
        d2 = (ref[k, 0] - cx) ** 2 + (ref[k, 1] - cy) ** 2 + (ref[k, 2] - cz) ** 2
        e2 = max(e2, d2)
    return np.sqrt(e2)


@njit
def _near_free(b, cur, n, ref, points, index, owner, x, members, margin, centre, cand, nc):
    """Appends to ``cand[nc:]`` (up to ``MAX_CAND``) the free points within reach of body
    ``b``: within twice its reference extent (:func:`_extent`) plus ``margin`` (mm) of the
    mean of its members' points ``cur`` (rows, -1 none), or of their Kalman estimates when no
    member has a point; ``centre`` receives that mean. Returns the new count, -1 when the body
    has neither."""
    cx = cy = cz = 0.0
    nx = 0
    for k in range(n):
        if cur[k] >= 0:
            cx += points[cur[k], 0]
            cy += points[cur[k], 1]
            cz += points[cur[k], 2]
            nx += 1
    if nx == 0:
        for k in range(n):
            m = members[b, k]
            if x[m, 0] == x[m, 0]:
                cx += x[m, 0]
                cy += x[m, 1]
                cz += x[m, 2]
                nx += 1
    if nx == 0:
        return -1
    centre[0] = cx / nx
    centre[1] = cy / nx
    centre[2] = cz / nx
    radius = 2.0 * _extent(ref, n) + margin
    return _free_in(points, index, centre, radius, owner, cand, nc, MAX_CAND)


@njit
def _repair(points, index, frame_no, tracks, bodies, scratch, params):
    """The 3D template check, swap repair and joint re-acquisition of the module docstring,
    after Algorithm 1 and the per-marker 3D check. Changes ``scratch.assigned``, ``owner`` and
    keeps ``scratch.obs`` in sync; updates ``bodies.ref``, ``ref_ok``, ``ok``, ``pending``.
    ``tracks.age`` is the previous frame's. Returns the number of bodies relabeled."""
    assigned, owner, obs, kab = scratch.assigned, scratch.owner, scratch.obs, scratch.kab
    active, age, x = tracks.active, tracks.age, tracks.x
    members, size, A0 = bodies.members, bodies.size, bodies.A0
    ref_all, ref_ok, ok, pending = bodies.ref, bodies.ref_ok, bodies.ok, bodies.pending
    check_mm, tol_mm = params.repair_check_mm, params.repair_tol_mm
    rep_age, rep_frames, every = params.repair_age, params.repair_frames, params.verify_every
    margin = params.repair_radius_mm
    nb = members.shape[0]
    cur = bodies.work_cur
    pts = bodies.work_pts
    cand = bodies.work_cand
    best = bodies.work_best
    pos = bodies.work_pos
    choice = bodies.work_choice
    used = bodies.work_used
    tol = bodies.work_tol
    centre = bodies.work_centre
    changes = 0
    for b in range(nb):
        n = size[b]
        if n < 3:
            continue
        n_obs = 0
        young = False
        lost = False
        for k in range(n):
            m = members[b, k]
            cur[k] = assigned[m]
            if assigned[m] >= 0:
                n_obs += 1
                if age[m] < rep_age:
                    young = True
            elif active[m]:
                lost = True
        if not ref_ok[b]:
            # first reference: every member observed long enough
            if n_obs == n:
                full = True
                for k in range(n):
                    if age[members[b, k]] < params.snapshot_age:
                        full = False
                if full:
                    _snapshot_body(b, bodies, points, cur, n)
            continue
        turn = every > 0 and (b + frame_no) % every == 0
        if not (young or lost or turn or pending[b] > 0):
            continue
        ref = ref_all[b]
        for k in range(n):
            choice[k] = k if cur[k] >= 0 else -1
            if cur[k] >= 0:
                for a in range(3):
                    pts[k, a] = points[cur[k], a]
        c_cur, rms_cur = _shape_rms(ref, pts, choice, n, kab.src, kab.dst, kab.R, kab.t)
        bad = c_cur >= 3 and rms_cur > check_mm
        ok[b] = not bad
        if not bad and not lost:
            pending[b] = 0
            if c_cur == n and not young and _refresh_ok(b, bodies, points, cur, n, choice, tol_mm):
                _snapshot_body(b, bodies, points, cur, n)  # follow slow soft-tissue drift
            continue
        # candidates: the body's own points, then free points near it
        nc = 0
        for k in range(n):
            if cur[k] >= 0:
                cand[nc] = cur[k]
                nc += 1
        nc2 = _near_free(b, cur, n, ref, points, index, owner, x, members, margin, centre, cand, nc)
        if nc2 < 0:
            continue
        n_free = nc2 - nc
        nc = nc2
        if not bad and n_free == 0:
            pending[b] = 0
            continue
        for i in range(nc):
            for a in range(3):
                pts[i, a] = points[cand[i], a]
        for i in range(n):
            for j in range(n):
                a0 = A0[b, i, j]
                tol[i, j] = tol_mm + (3.0 * a0 if a0 == a0 else 0.0)
        c_b, rms_b = _fit_template(
            n, ref, tol, pts, nc, check_mm, params.repair_max_nodes, pos, used, choice, best, kab
        )
        fewer_fits = False
        if c_b >= 4 and c_b < c_cur and bad and rms_b < rms_cur / 3.0:
            # a map of fewer points: clearly better than the current assignment of the same
            # members (a member the map leaves out may be the one that deformed)
            r = 0  # pts[:nc] starts with the body's current points, in member order
            for k in range(n):
                choice[k] = r if cur[k] >= 0 and best[k] >= 0 else -1
                if cur[k] >= 0:
                    r += 1
            c_sub, rms_sub = _shape_rms(ref, pts, choice, n, kab.src, kab.dst, kab.R, kab.t)
            fewer_fits = c_sub >= 4 and rms_b < rms_sub / 3.0
            for k in range(n):
                # a member tracked for long keeps its point, and no other member takes it
                if not fewer_fits or cur[k] < 0 or age[members[b, k]] < rep_age:
                    continue
                for j in range(n):
                    p = cand[best[j]] if best[j] >= 0 else -1
                    if (j == k and p >= 0 and p != cur[k]) or (j != k and p == cur[k]):
                        fewer_fits = False
        if c_b < 3 or (c_b < c_cur and not fewer_fits):
            # no map of the body's shape holds as many points: the body deformed (or is not
            # rigid); its current assignment is the best explanation, and becomes the reference
            pending[b] = 0
            ok[b] = True
            if c_cur == n and not young and _refresh_ok(b, bodies, points, cur, n, choice, tol_mm):
                _snapshot_body(b, bodies, points, cur, n)
            continue
        same = True  # the best map keeps every point the body holds now
        moved = False  # the best map relabels a point the body holds now
        for k in range(n):
            p = cand[best[k]] if best[k] >= 0 else -1
            if p != cur[k]:
                same = False
                if cur[k] >= 0:
                    moved = True
        if same:
            pending[b] = 0
            ok[b] = True
            if c_cur == n and not young and _refresh_ok(b, bodies, points, cur, n, choice, tol_mm):
                _snapshot_body(b, bodies, points, cur, n)
            continue
        if moved and not young:
            # a body tracked for long keeps its points (and its reference: a better permutation
            # exists, so the current shape does not replace it)
            pending[b] = 0
            ok[b] = True
            continue
        named = (
            c_b == 3
            and c_cur <= 1
            and bodies.ref_model[b]
            and _keeps_held(b, cur, best, cand, n, members, scratch.cand, scratch.ncand)
        )
        if c_b < 4 and not (named and _unique3(ref, pts, best, n, rms_b, check_mm, kab)):
            pending[b] = 0  # three points have no chirality: Eq. 5 already saw what they show
            continue
        if c_cur >= 3 and not moved:
            pending[b] = 0  # single re-acquisitions of a seen body: the per-marker 3D check's
            continue
        if c_cur >= 3 and moved:
            better = c_b > c_cur or rms_b < rms_cur / 3.0
            if not better:
                pending[b] = 0
                ok[b] = True
                continue
            pending[b] += 1
            if pending[b] < rep_frames:
                continue
        pending[b] = 0
        # relabel: release the body's points, then assign the best map
        for k in range(n):
            m = members[b, k]
            if cur[k] >= 0 and owner[cur[k]] == m:
                owner[cur[k]] = NONE
            assigned[m] = NONE
            for a in range(3):
                obs[m, a] = np.nan
        for k in range(n):
            if best[k] < 0:
                continue
            m = members[b, k]
            p = cand[best[k]]
            owner[p] = m
            assigned[m] = p
            for a in range(3):
                obs[m, a] = points[p, a]
        for k in range(n):
            # a map of fewer members: a member it leaves out keeps its point when no member
            # took it
            p = cur[k]
            if not fewer_fits or best[k] >= 0 or p < 0 or owner[p] >= 0:
                continue
            m = members[b, k]
            owner[p] = m
            assigned[m] = p
            for a in range(3):
                obs[m, a] = points[p, a]
        ok[b] = True
        changes += 1
    if params.repair_pairs:
        changes += _pair_check(points, tracks, bodies, scratch, params)
    return changes
