"""Markers the stream has not shown yet, placed by their bodies' trained shapes (ours).

A labeler started from a model and a few labeled frames (``Labeler.from_model``) has no
Kalman state for a marker those frames never showed (``tracks.x`` NaN) and no recovery
snapshot: it is never predicted, gated or re-acquired, so it never got a label, and in a crowd
its point went to another marker. The model knows where it sits on its bodies. Only members on
points this frame that continue their tracks (observed in the previous frame too, or in the
last labeled frame) are used:

- *shape*: each body of the marker with a reference shape (``bodies.ref``; the trained shape
  until the stream shows the body whole) and 3+ such members fits that shape onto them (Horn,
  proper rotations only); a tight fit (RMS within ``repair_check_mm``) places the marker. It
  takes the free point nearest the place, within ``reacquire_near_mm``, when no other free point
  lies within twice that and every body that places it points at the same point;
- *distances*, when no body has 3 such members (a triangle's third corner): the only free
  point whose distances to the members of all the marker's bodies keep the trained ``D``
  (within 3 floored trained deviations + ``PAIR_SLACK_MM``), ``MIN_PAIRS`` pairs or more. Two
  pairs leave a circle of places: a real point on it that the model does not know can be
  taken (measured in docs/algorithm.md, step 7). Asking 3 pairs did worse: a marker of a
  triangle placed alone left the triangle holding two points, so the repair's joint
  re-acquisition of the other two (three points that name themselves) no longer fired.

Its track then starts at the update (Eq. 4), as a first observation does.

*Markers lost for long* (``acquire_lost_frames`` > 0): a marker observed before and missing
that many frames in a row is placed the same way, except that the pair rule counts only links
that do not bend now (:func:`.repair._bends`), needs ``LOST_PAIRS`` of them, and the point
must not continue an anonymous run that began while the marker was still on a track of its own
(:func:`.anonymous._refused`). Its prediction coasted away and its recovery set may hold
markers across a joint held still in training (the tennis wrist after the serve).

*Lost together* (``acquire_together``): before those per-marker rules, the members of one body
that are lost now (observed before, no point this frame), ``TOGETHER_MIN`` or more of them and
one lost for ``acquire_lost_frames``, are placed as one: the template fit of the swap repair
(:func:`.repair._fit_template`) maps their reference shape alone onto the free points within
reach of the body (the repair's own search, :func:`.repair._near_free`); the map must place
every lost member (one left out leaves open which members the points are), and of the
readings of those points that keep the shape (3 points: every permutation) exactly one must
keep the trained distances to their *anchors* (members of their bodies on points that
continue their tracks, over links that do not bend now; beyond 3 floored deviations by
``PAIR_SLACK_MM`` at most in all, per marker; one link at least) and take no point an
anonymous run saw beside its marker. A hand lost whole in a swing has only one link per
marker that holds (the elbow), so each per-marker rule refuses it; its triangle and the elbow
name it.

*A new track* (``acquire_restart``): a lost marker placed by these rules starts a new Kalman
track on its point, moving with the mean velocity of its anchors (kept as it was when it has
none). Its coasted velocity says nothing of a limb that swung on while it was lost, and the
next frame's fit of its body trusted it (the tennis arm read along the chain one frame after
its hand was placed mid-swing).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.anonymous import _refused
from labeler_service.labeling.kernels.repair import (
    _bends,
    _fit_template,
    _link_excess,
    _near_free,
    _shape_rms,
)
from labeler_service.labeling.kernels.rigid import _take
from labeler_service.labeling.kernels.spatial import FREE, _free_within, _nearest, _span
from labeler_service.labeling.kernels.state import MAX_BODY

PAIR_SLACK_MM = 3.0  # distance slack of the pair rule beyond 3 trained deviations, mm
MAX_PAIRS = 16  # pairs kept per marker for the pair rule
MIN_PAIRS = 2  # pairs the pair rule needs
LOST_PAIRS = 3  # pairs it needs for a marker observed before and lost (its links that hold)
TOGETHER_MIN = 3  # members of one body lost together that the together rule places as one


@njit
def _acquire_unseen(points, index, frame_no, tracks, bodies, scratch, params):
    """Assigns free points to active markers that were never observed, or observed and lost
    for ``acquire_lost_frames`` frames (see the module doc); ``frame_no`` as the anonymous point
    runs count it.

    Reads ``tracks.age`` as the previous frame's; changes ``scratch.assigned``, ``owner`` and
    ``obs`` (in sync). Returns the number of markers placed. Allocates its work space (five
    small arrays) only in a frame with such a marker: none in most frames of a labeler started
    on labeled frames, every frame while a marker stays lost (measured: no cost,
    BENCHMARKS.md)."""
    m_total = tracks.x.shape[0]
    want = _want(tracks, scratch, params)
    first = 0
    while first < m_total and not _wanted(first, *want):
        first += 1
    if first == m_total:
        return 0
    est = np.empty(3)
    choice = np.empty(MAX_BODY, dtype=np.int64)  # the shape rule: each member's point or -1
    pa = np.empty(MAX_PAIRS, dtype=np.int64)  # the pair rule: member's point, D, tolerance
    pd = np.empty(MAX_PAIRS)
    pt = np.empty(MAX_PAIRS)
    placed = 0
    if params.acquire_together and params.acquire_lost_frames > 0:
        placed += _acquire_together(points, index, frame_no, tracks, bodies, scratch, params)
    runs = tracks.seen_at, tracks.track_from
    for m in range(first, m_total):
        if not _wanted(m, *want):
            continue
        lost = not _never_observed(m, tracks.x)
        pick, shaped = _by_shape(m, points, index, tracks, bodies, scratch, params, est, choice)
        if pick < 0 and not shaped:
            pick = _by_pairs(m, points, index, tracks, bodies, scratch, params, pa, pd, pt, lost)
        if pick < 0:
            continue
        if lost and params.anonymous_tracks and _refused(m, pick, scratch.anon, *runs, frame_no):
            continue  # the point was there, unlabeled, while the marker was on its own
        _take(m, pick, points, scratch.assigned, scratch.owner, scratch.obs)
        if lost and params.acquire_restart:
            _restart(m, pick, points, tracks, bodies, scratch, params)
        placed += 1
    return placed


@njit
def _want(tracks, scratch, params):
    """What :func:`_wanted` reads, as a plain tuple of arrays and numbers.

    Helpers called per marker take arrays, never a whole state structure: numba passes a
    structure as every one of its fields, ~100-400 ns a call (measured with ``_wanted`` itself:
    402 ns with ``tracks``, ``scratch`` and ``params``, 19 ns with these; at 10 performers it
    runs ~500 times a frame)."""
    return (tracks.active, tracks.gone, tracks.lost, tracks.x, scratch.assigned,
            params.acquire_unseen, params.acquire_lost_frames)  # fmt: skip


@njit
def _wanted(m, active, gone, lost, x, assigned, unseen, lost_frames):
    """Marker ``m`` is placed here: active, its subject present (not ``gone``), no point this
    frame (``assigned``), and either never observed (``unseen``: ``acquire_unseen``) or
    observed before and ``lost`` for ``lost_frames`` (``acquire_lost_frames``) frames or more.
    The arguments are :func:`_want`'s."""
    if not active[m] or gone[m] or assigned[m] >= 0:
        return False
    if _never_observed(m, x):
        return unseen
    return 0 < lost_frames <= lost[m]


@njit
def _never_observed(m, x):
    """Marker ``m`` has no Kalman state ``x``: the stream never showed it."""
    return x[m, 0] != x[m, 0]  # noqa: PLR0124 (NaN test)


@njit
def _continuing(i, assigned, age):
    """Marker ``i`` is on a point this frame (``assigned``) and was observed in the previous one
    (``age``, ``tracks.age``: frames observed in a row up to the previous frame; the labeled
    frames' warm start sets it, where ``state`` stays as it was)."""
    return assigned[i] >= 0 and age[i] > 0


@njit
def _by_shape(m, points, index, tracks, bodies, scratch, params, est, choice):
    """The shape rule: ``(point, shaped)``; point -1 when no agreed unambiguous point;
    ``shaped``: some body had 3+ continuing members and a tight fit (then the pair rule is not
    asked). ``choice (MAX_BODY,)``: work space (each member's point, -1 none)."""
    kab = scratch.kab
    near = params.reacquire_near_mm
    owner, assigned, age = scratch.owner, scratch.assigned, tracks.age
    pick = -1
    shaped = False
    for e in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
        b = bodies.mb_idx[e]
        if not bodies.ref_ok[b]:
            continue
        k = bodies.size[b]
        me = -1
        for q in range(k):
            i = bodies.members[b, q]
            choice[q] = -1
            if i == m:
                me = q
            elif _continuing(i, assigned, age) and bodies.ref[b, q, 0] == bodies.ref[b, q, 0]:
                choice[q] = assigned[i]
        if me < 0 or bodies.ref[b, me, 0] != bodies.ref[b, me, 0]:  # noqa: PLR0124 (NaN test)
            continue
        c, rms = _shape_rms(bodies.ref[b], points, choice, k, kab.src, kab.dst, kab.R, kab.t)
        if c < 3 or rms > params.repair_check_mm:
            continue  # too few members, or the body does not hold its shape now
        shaped = True
        R, t = kab.R, kab.t
        for d in range(3):
            est[d] = (
                R[d, 0] * bodies.ref[b, me, 0]
                + R[d, 1] * bodies.ref[b, me, 1]
                + R[d, 2] * bodies.ref[b, me, 2]
                + t[d]
            )
        j, _ = _nearest(points, index, est, near * near, owner, FREE, -1)
        if j < 0:
            return -1, True  # this body sees no point at the marker's place
        if _free_within(points, index, est, 2.0 * near, owner, j) or (pick >= 0 and j != pick):
            return -1, True  # two free points at the place, or two bodies disagree
        pick = j
    return pick, shaped


@njit
def _by_pairs(m, points, index, tracks, bodies, scratch, params, pa, pd, pt, lost):
    """The pair rule: the only free point that keeps ``MIN_PAIRS`` or more trained distances to
    continuing members of the marker's bodies, or -1. A pair without a trained distance (NaN
    ``D0``: a model may hold one) is no evidence and is not counted; a trained distance without
    a deviation gets the floor. ``lost``: a marker observed before - only links that do not bend
    now count, ``LOST_PAIRS`` or more."""
    n = 0
    floor = params.a_floor_mm
    assigned, age, links = scratch.assigned, tracks.age, _links(bodies, params)
    for e in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
        b = bodies.mb_idx[e]
        me = _slot(bodies.members, b, m)
        for q in range(bodies.size[b]):
            i = bodies.members[b, q]
            if i == m or not _continuing(i, assigned, age) or n >= MAX_PAIRS:
                continue
            # a link that bends now is no evidence of where a lost marker is
            d0, a0 = _link(b, me, q, lost, *links)
            if d0 != d0:  # noqa: PLR0124 (NaN: no trained distance, or it bends)
                continue
            dup = False
            for k in range(n):
                dup = dup or pa[k] == assigned[i]
            if dup:
                continue
            pa[n] = assigned[i]
            pd[n] = d0
            pt[n] = 3.0 * max(a0, floor) + PAIR_SLACK_MM
            n += 1
    if n < (LOST_PAIRS if lost else MIN_PAIRS):
        return -1
    lo, hi = _span(index, points[pa[0]], pd[0] + pt[0])
    pick = -1
    for k in range(lo, hi):
        j = index.order[k]
        if scratch.owner[j] >= 0:
            continue
        fits = True
        for p in range(n):
            d2 = 0.0
            for d in range(3):
                v = points[j, d] - points[pa[p], d]
                d2 += v * v
            if abs(np.sqrt(d2) - pd[p]) > pt[p]:
                fits = False
                break
        if not fits:
            continue
        if pick >= 0:
            return -1  # two free points keep the distances
        pick = j
    return pick


@njit
def _slot(members, b, m):
    """Marker ``m``'s row in body ``b`` (a member of it; ``members``: ``bodies.members``)."""
    me = 0
    while members[b, me] != m:
        me += 1
    return me


@njit
def _links(bodies, params):
    """What :func:`_link` reads after its first four arguments (arrays, not the structures:
    :func:`_want`)."""
    return bodies.D0, bodies.A0, bodies.A, params.a_floor_mm, params.a_relative


@njit
def _link(b, me, q, held, D0, A0, A, a_floor, a_rel):
    """``(D0, A0)`` of body ``b``'s trained link between rows ``me`` and ``q`` (``A0`` 0 when
    it has no trained deviation: the floor applies); ``D0`` NaN when the link has no trained
    distance, or with ``held`` when it bends now (:func:`.repair._bends`: window ``A`` beyond 3
    floored ``A0``, a link trained across a joint held still). The rest: :func:`_links`."""
    d0 = D0[b, me, q]
    if not np.isfinite(d0):
        return np.nan, 0.0
    a0 = A0[b, me, q]
    a0 = a0 if np.isfinite(a0) else 0.0
    if held and _bends(A[b, me, q], a0, d0, a_floor, a_rel):
        return np.nan, a0
    return d0, a0


@njit
def _acquire_together(points, index, frame_no, tracks, bodies, scratch, params):
    """Members of one body lost together, placed together (*lost together* in the module
    doc): per body with a reference, its members observed before and without a point now
    (``TOGETHER_MIN`` or more, one lost ``acquire_lost_frames`` frames); the template fit over
    the free points within reach of the body (:func:`.repair._near_free`, the swap repair's
    search), placing every lost member; the one reading of those points, within
    ``repair_check_mm`` of their shape, that :func:`_anchored` accepts. Uses the repair's work
    space (``bodies.work_*``). Returns the number of markers placed."""
    members, size, ref_all = bodies.members, bodies.size, bodies.ref
    assigned, owner, kab = scratch.assigned, scratch.owner, scratch.kab
    pts, cand, best, pos = bodies.work_pts, bodies.work_cand, bodies.work_best, bodies.work_pos
    choice, used, tol = bodies.work_choice, bodies.work_used, bodies.work_tol
    centre, cur = bodies.work_centre, bodies.work_cur
    want = _want(tracks, scratch, params)
    lost = np.empty(MAX_BODY, dtype=np.int64)  # the body slots of the lost members
    ref = np.empty((MAX_BODY, 3))
    placed = 0
    for b in range(members.shape[0]):
        if not bodies.ref_ok[b]:
            continue
        n = size[b]
        nl = 0
        long_lost = False
        for q in range(n):
            m = members[b, q]
            if ref_all[b, q, 0] != ref_all[b, q, 0] or _never_observed(m, tracks.x):  # noqa: PLR0124
                continue
            if not tracks.active[m] or tracks.gone[m] or assigned[m] >= 0:
                continue
            lost[nl] = q
            nl += 1
            long_lost = long_lost or _wanted(m, *want)  # lost for long
        if nl < TOGETHER_MIN or not long_lost:
            continue
        for i in range(nl):
            for a in range(3):
                ref[i, a] = ref_all[b, lost[i], a]
            for k in range(nl):
                a0 = bodies.A0[b, lost[i], lost[k]]
                tol[i, k] = params.repair_tol_mm + (3.0 * a0 if a0 == a0 else 0.0)
        # the free points within reach of the body (the swap repair's search: around its
        # members on points, else around its members' estimates)
        for q in range(n):
            cur[q] = assigned[members[b, q]]
        nc = _near_free(b, cur, n, ref_all[b], points, index, owner, tracks.x, members,
                        params.repair_radius_mm, centre, cand, 0)  # fmt: skip
        if nc < 3:
            continue
        for i in range(nc):
            for a in range(3):
                pts[i, a] = points[cand[i], a]
        check = params.repair_check_mm
        c, _ = _fit_template(nl, ref, tol, pts, nc, check, params.repair_max_nodes, pos, used,
                             choice, best, kab)  # fmt: skip
        if c < 3:
            continue
        mapped = 0
        for i in range(nl):
            mapped += best[i] >= 0
        if mapped < nl:
            continue  # a lost member the map leaves out: which members the points are is open
        # every reading of the same points that keeps the shape: the anchors must name one
        take = -1
        for r in range(_N_READINGS if nl == 3 else 1):
            _reading(best, r, nl, choice)
            _, rms_r = _shape_rms(ref, pts, choice, nl, kab.src, kab.dst, kab.R, kab.t)
            if rms_r > check:
                continue
            if not _anchored(b, lost, choice, nl, cand, points, tracks, bodies, scratch, params,
                             frame_no):  # fmt: skip
                continue
            if take >= 0:
                take = -2  # two readings hold: the anchors do not name the points
                break
            take = r
        if take < 0:
            continue
        _reading(best, take, nl, choice)
        for i in range(nl):
            _take(members[b, lost[i]], cand[choice[i]], points, assigned, owner, scratch.obs)
            placed += 1
        for i in range(nl):  # after every placement: a member lost only now anchors the others
            if params.acquire_restart:
                m, p = members[b, lost[i]], cand[choice[i]]
                _restart(m, p, points, tracks, bodies, scratch, params)
    return placed


@njit
def _reading(best, r, nl, choice):
    """``choice[:nl]`` = reading ``r`` of the map ``best`` (candidate row per lost member):
    with 3 members, permutation ``r`` of its three points; otherwise the map itself."""
    for i in range(nl):
        choice[i] = best[_READINGS[r, i]] if nl == 3 else best[i]


@njit
def _restart(m, p, points, tracks, bodies, scratch, params):
    """Lost marker ``m``, placed on point ``p``, starts a new Kalman track there (``P`` of a
    first observation) with the mean velocity of the members on points that continue their
    tracks over its links that do not bend now; without such a member its state is kept. Its
    coasted velocity says nothing of a limb that moved on while it was lost."""
    x, P = tracks.x, tracks.P
    assigned, age, links = scratch.assigned, tracks.age, _links(bodies, params)
    v0 = v1 = v2 = 0.0
    c = 0
    for e in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
        b = bodies.mb_idx[e]
        me = _slot(bodies.members, b, m)
        for q in range(bodies.size[b]):
            k = bodies.members[b, q]
            if k == m or not _continuing(k, assigned, age):
                continue
            d0, _ = _link(b, me, q, True, *links)
            if d0 != d0:  # noqa: PLR0124 (NaN: no trained distance, or it bends now)
                continue
            v0 += x[k, 3]
            v1 += x[k, 4]
            v2 += x[k, 5]
            c += 1
    if c == 0:
        return
    for a in range(3):
        x[m, a] = points[p, a]
    x[m, 3], x[m, 4], x[m, 5] = v0 / c, v1 / c, v2 / c
    P[m, 0], P[m, 1], P[m, 2] = params.r, 0.0, params.v0


#: the six readings of three points (the together rule's permutations)
_READINGS = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])
_N_READINGS = 6


@njit
def _anchored(b, lost, choice, nl, cand, points, tracks, bodies, scratch, params, frame_no):
    """Whether the reading ``choice`` (row of ``cand`` per lost member of body ``b``, -1 none)
    keeps every trained distance to the members on points that continue their tracks, over the
    links that do not bend now (:func:`.repair._link_excess`, at most ``PAIR_SLACK_MM`` in all
    per marker), with one such link at least, and no point continues an anonymous run seen
    beside its marker."""
    links = 0
    runs = tracks.seen_at, tracks.track_from
    for i in range(nl):
        if choice[i] < 0:
            continue
        m, p = bodies.members[b, lost[i]], cand[choice[i]]
        tot, cnt = _link_excess(m, p, -1, points, bodies, scratch.assigned, tracks.age, 1,
                                params.a_floor_mm, params.a_relative)  # fmt: skip
        if tot > PAIR_SLACK_MM:
            return False
        if params.anonymous_tracks and _refused(m, p, scratch.anon, *runs, frame_no):
            return False
        links += cnt
    return links > 0
