"""The whole per-frame loop of the online labeler in one numba entry point.

Order (seed 003 Fig. 2 and Algorithm 1): Kalman prediction (Eq. 3), replaced by a rigid body's
prediction where that body has predicted the marker better (ours, :mod:`.motion`) -> common-mode
shift (ours) -> Mahalanobis gating with at
most K candidates (Sec. 3.1) -> greedy rigid-body fitting (Eq. 5, Algorithm 1) -> track
continuity (points back to the markers tracked onto them, ours) -> wide re-acquisition, the
exchange and kept tracks (ours) -> 3D
check (ours, see docs/algorithm.md) -> 3D template check of suspect bodies, swap repair and joint
re-acquisition (ours, :mod:`.repair`) -> lost markers take back the point they followed (ours,
:mod:`.follow`) -> markers never observed placed by their bodies' trained
shapes (ours, :mod:`.unseen`) -> Kalman update of the observed markers (Eq. 4) -> recovery
of hidden markers from their bodies (Sec. 3.3; the recovered position also updates the Kalman
state with a larger ``R``, so a marker hidden for long is predicted from its body, not from a
stale state) -> anchored coasting of lost markers without a rigid estimate (ours, :mod:`.anchor`)
-> each body's inter-frame rigid motion and prediction errors (:mod:`.motion`)
-> sliding-window structure update (Eq. 1-2) -> reference snapshots of fully observed bodies.

The state is the named structures of :mod:`.state` (``Tracks``, ``Bodies``, ``Recovery``,
``Scratch``) and the settings ``Params`` of :mod:`.params`; every step reads them by field
name and updates them in place.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.frame import MISSING, OBSERVED, RECOVERED
from labeler_service.labeling.kernels.anchor import (
    _anchor_broken,
    _anchor_estimate,
    _anchor_filter,
    _anchor_lost,
    _anchor_snapshot,
)
from labeler_service.labeling.kernels.anonymous import (
    _continue_track,
    _link_anonymous,
    _refuse_anonymous,
    _store_anonymous,
    _track_taken,
)
from labeler_service.labeling.kernels.contact import _contacts
from labeler_service.labeling.kernels.fitting import _fit_bodies
from labeler_service.labeling.kernels.follow import _acquire_followed, _follow_all
from labeler_service.labeling.kernels.gating import _common_mode, _gate, _regate
from labeler_service.labeling.kernels.kalman import _predict, _start_or_update
from labeler_service.labeling.kernels.motion import _body_motion, _body_predict, _keep_kalman
from labeler_service.labeling.kernels.params import Params
from labeler_service.labeling.kernels.repair import _repair
from labeler_service.labeling.kernels.rigid import (
    _contest,
    _exchange,
    _keep_tracks,
    _max_residual,
    _recover,
    _set_estimate,
    _snapshot,
    _verify,
)
from labeler_service.labeling.kernels.spatial import _index
from labeler_service.labeling.kernels.state import (
    NONE,
    UNDECIDED,
    Bodies,
    FitScratch,
    KabschScratch,
    Recovery,
    Scratch,
    Tracks,
)
from labeler_service.labeling.kernels.unseen import _acquire_unseen
from labeler_service.labeling.kernels.window import _window_update


@njit
def _observed(assigned, points, obs):
    """``obs[m]`` = the point marker ``m`` is assigned to, NaN when it has none."""
    for i in range(assigned.shape[0]):
        a = assigned[i]
        for c in range(3):
            obs[i, c] = points[a, c] if a >= 0 else np.nan


@njit
def _process_frame(points, dt, ptr, frame_no, tracks, bodies, recovery, scratch, params):
    """Labels one frame of ``points (N, 3)`` in place (the order of the module docstring).

    ``dt``: seconds since the previous frame; ``ptr``: this frame's slot in the sliding window
    ``bodies.ring``; ``frame_no``: frames labeled so far (the 3D check's round robin). The
    structures are those of :mod:`.state` (``params``: :mod:`.params`). Out:
    ``scratch.owner[:N]`` (point -> marker or ``NONE``), ``tracks.pos (M, 3)`` and
    ``tracks.state (M,)``.
    """
    x, P, active, state, pos = tracks.x, tracks.P, tracks.active, tracks.state, tracks.pos
    s, assigned, owner, obs = scratch.s, scratch.assigned, scratch.owner, scratch.obs
    rec, has_rec, missing = scratch.rec, scratch.has_rec, scratch.missing
    age, n_reject = tracks.age, tracks.n_reject
    r, v0 = params.r, params.v0
    if params.absent_frames > 0:
        _gone(tracks, params.absent_frames)
    if params.presence_min_markers > 0:
        _absent(tracks, params.presence_min_markers, params.absent_frames > 0)
    m_total = x.shape[0]
    n = points.shape[0]
    index = _index(points)
    # Eq. 3: predict; S = H P H^T + R
    _predict(x, P, tracks.q, active, dt, params.p_cap)
    if params.body_prediction:  # rigid-body prediction (ours, kernels/motion.py)
        _body_predict(tracks, bodies, dt)  # (keeps the Kalman predictions in tracks.kx)
    elif params.acquire_follow:
        _keep_kalman(tracks)  # where a marker that loses its point starts following
    if params.common_mode_iters > 0:
        subj_ptr, subj_idx = tracks.subj_ptr, tracks.subj_idx
        radius, iters = params.common_mode_radius_mm, params.common_mode_iters
        buf, shift = scratch.cm_buf, scratch.cm_shift
        _common_mode(x, active, subj_ptr, subj_idx, points, index, radius, iters, buf, shift)
    for i in range(m_total):
        s[i] = P[i, 0] + r
        if s[i] < params.s_min:  # gate floor: radius^2 = s_min * gate
            s[i] = params.s_min
        if tracks.gone[i]:
            s[i] = params.s_min  # the subject left: only the narrowest gate at its last place
    cand, cand_d2, ncand = scratch.cand, scratch.cand_d2, scratch.ncand
    _gate(x, s, active, points, index, params.gate_chi2, params.K, cand, cand_d2, ncand)
    # points seen unlabeled beside a tracked marker (ours, kernels/anonymous.py)
    runs = (
        _link_anonymous(points, index, dt, frame_no, scratch, params)
        if params.anonymous_tracks
        else 0
    )
    if runs > 0:
        _refuse_anonymous(cand, cand_d2, ncand, scratch.anon, tracks, frame_no)
    # Algorithm 1
    for i in range(m_total):
        assigned[i] = UNDECIDED
    for j in range(n):
        owner[j] = NONE
    _fit_bodies(bodies, points, params.miss_term, scratch, params)
    # track continuity: points the fit gave to a marker that jumped for them go back to the
    # marker tracked onto them in the previous frame
    if params.contest:
        _observed(assigned, points, obs)
        _contest(points, tracks, recovery, scratch, params)
    if params.reacquire_mm > 0.0:
        _reacquire(points, index, frame_no, runs, tracks, bodies, recovery, scratch, params)
    if params.exchange:  # two tracked markers on each other's points (ours, kernels/rigid.py)
        _exchange(points, tracks, bodies, scratch, params)
    if params.keep_tracks:  # a continuing track keeps its point (ours, kernels/rigid.py)
        _keep_tracks(points, index, dt, tracks, recovery, scratch, params)
    _observed(assigned, points, obs)
    if params.verify_mm > 0.0:
        _verify(points, index, frame_no, tracks, recovery, scratch, params)
    if params.repair:
        _repair(points, index, frame_no, tracks, bodies, scratch, params)
    if params.presence_min_markers > 0:
        _presence(points, tracks, bodies, scratch, params)
    if params.contact_mm > 0.0:  # contacts between performers (ours, kernels/contact.py)
        _contacts(points, index, dt, tracks, bodies, recovery, scratch, params)
    if params.acquire_follow:  # a lost marker takes back the point it followed (ours)
        _acquire_followed(points, index, dt, frame_no, tracks, bodies, scratch, params)
    if params.acquire_unseen or params.acquire_lost_frames > 0:  # unseen, or lost (ours)
        _acquire_unseen(points, index, frame_no, tracks, bodies, scratch, params)
    if params.acquire_follow:  # (before Eq. 4: tracks.pos and age are the last frame's)
        _follow_all(points, index, dt, tracks, scratch, params)
    # Eq. 4 for observed markers
    for i in range(m_total):
        a = assigned[i]
        if a >= 0:
            missing[i] = False  # the 3D check used it as scratch
            tracks.lost[i] = 0
            n_reject[i] = 0
            age[i] += 1
            if params.anonymous_tracks:
                _continue_track(i, a, points, frame_no, tracks, r, params.jump_mm)
            _start_or_update(x, P, i, obs[i, 0], obs[i, 1], obs[i, 2], r, v0)
            state[i] = OBSERVED
            for c in range(3):
                pos[i, c] = obs[i, c]
        else:
            if params.anonymous_tracks and state[i] == OBSERVED:
                _track_taken(i, points, index, owner, tracks, r, params.jump_mm)
            age[i] = 0
            tracks.lost[i] += 1
            for c in range(3):
                obs[i, c] = np.nan
            missing[i] = active[i]
            state[i] = MISSING
            for c in range(3):
                pos[i, c] = np.nan
    # Sec. 3.3: recovery from rigid bodies
    method, tau = params.recovery, params.robust_fit_mm
    _recover(missing, recovery, obs, method, rec, has_rec, scratch.kab, tau)
    for i in range(m_total):
        if not missing[i]:
            continue
        if has_rec[i] > 0:
            # a rigid (3+ neighbours) estimate steers the Kalman state; a weaker one barely
            rr = params.r_rec if has_rec[i] >= 3 else 25.0 * params.r_rec
            _start_or_update(x, P, i, rec[i, 0], rec[i, 1], rec[i, 2], rr, v0)
            state[i] = RECOVERED
            for c in range(3):
                pos[i, c] = rec[i, c]
        else:
            for c in range(3, 6):
                x[i, c] *= params.velocity_decay
    if params.anchor_lost:  # anchored coasting (ours, kernels/anchor.py)
        if params.anchor_state:
            _anchor_lost(obs, missing, has_rec, tracks, params.anchor_slack_mm)
        _anchor_snapshot(obs, tracks, bodies, params.body_distance_weight)
    if params.body_prediction:
        kab, memory, tau = scratch.kab, params.body_error_frames, params.body_rigid_mm
        _body_motion(bodies, obs, tracks.kx, dt, memory, tau, kab.src, kab.dst, kab.R, kab.t)
    # Eq. 1-2: sliding window
    guard = params.repair and params.window_guard
    _window_update(bodies, obs, ptr, params.min_window_samples, guard, params.window_drift_mm)
    # reference snapshots of the recovery sets
    _snapshot(age, params.snapshot_age, obs, recovery)
    if params.anonymous_tracks:
        _store_anonymous(points, index, frame_no, scratch, params)


@njit
def _process_frame_fields(points, dt, ptr, frame_no, tracks, bodies, recovery, scratch, params):
    """:func:`_process_frame` called with each structure as a plain tuple of its fields
    (:func:`.state.fields`), as the Labeler calls it.

    Numba types every argument of a call from Python; for a named tuple it spells out the class
    and every field name, which costs about 1 us per structure and frame (+5 us a frame, 1.4 %
    of a 6-performer frame). A plain tuple takes the fast path; the names come back here, at
    compile time, for free (``scratch`` ends with the nested ``fit`` and ``kab``).
    """
    fit, kab = scratch[-2], scratch[-1]
    named = scratch[:-2] + (FitScratch(*fit), KabschScratch(*kab))
    _process_frame(
        points,
        dt,
        ptr,
        frame_no,
        Tracks(*tracks),
        Bodies(*bodies),
        Recovery(*recovery),
        Scratch(*named),
        Params(*params),
    )


@njit
def _gone(tracks, absent_frames):
    """``tracks.gone[m]``: every marker of ``m``'s subject has been missing for
    ``absent_frames`` frames (``tracks.lost``, the previous frame's count) - the subject left
    the volume (class D of docs/diagnosis_issue10.md)."""
    subj_ptr, subj_idx, lost = tracks.subj_ptr, tracks.subj_idx, tracks.lost
    for s in range(subj_ptr.shape[0] - 1):
        left = True
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            if tracks.active[subj_idx[k]] and lost[subj_idx[k]] < absent_frames:
                left = False
                break
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            tracks.gone[subj_idx[k]] = left


@njit
def _absent(tracks, need, also):
    """``tracks.gone[m]`` when fewer than ``need`` markers of ``m``'s subject were observed in
    the previous frame (``tracks.age > 0``; the labeled window counts; ``also``: or when
    :func:`_gone` set it): the presence check's "absent" (:func:`_presence`). Such markers
    search only the narrowest gate at their last place and stay out of the wide
    re-acquisition, so a subject who left does not take the others' points before
    :func:`_presence` would drop them again (tune24 ``half``,
    tennis + a clinical take that ends: 85.1 % before the presence check, 68.0 % with
    :func:`_presence` alone, 91.5 % with this too)."""
    subj_ptr, subj_idx = tracks.subj_ptr, tracks.subj_idx
    for s in range(subj_ptr.shape[0] - 1):
        seen = 0
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            if tracks.age[subj_idx[k]] > 0:
                seen += 1
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            m = subj_idx[k]
            tracks.gone[m] = seen < need or (also and tracks.gone[m])


@njit
def _consistent(b, points, assigned, bodies, need, tol):
    """Body ``b`` has ``need`` labeled members, every pair of them within ``tol`` + 3 A of its
    ``D`` (a pair with no ``D`` is not counted against it)."""
    members, size, D, A = bodies.members, bodies.size, bodies.D, bodies.A
    n = size[b]
    c = 0
    for k in range(n):
        if assigned[members[b, k]] >= 0:
            c += 1
    if c < need:
        return False
    for k in range(n):
        jk = assigned[members[b, k]]
        if jk < 0:
            continue
        for e in range(k + 1, n):
            je = assigned[members[b, e]]
            if je < 0 or D[b, k, e] != D[b, k, e]:  # noqa: PLR0124 (NaN: unknown link)
                continue
            d2 = 0.0
            for a in range(3):
                d = np.float64(points[jk, a]) - np.float64(points[je, a])
                d2 += d * d
            lim = tol + 3.0 * A[b, k, e]
            if abs(np.sqrt(d2) - D[b, k, e]) > lim:
                return False
    return True


#: A subject vanishing at once is checked only while the other subjects kept at least this
#: share of the markers they showed in the previous frame (:func:`_presence`).
VANISH_OTHERS_KEPT = 0.5


@njit
def _presence(points, tracks, bodies, scratch, params):
    """The presence check (ours, class D of docs/diagnosis_issue10.md).

    A subject of whom fewer than ``presence_min_markers`` markers were observed in the previous
    frame is absent (he left the volume, or was never seen); he keeps this frame's labels only
    if one of his rigid bodies has ``presence_min_markers`` labeled members whose pair
    distances agree with the body's ``D`` (:func:`_consistent`); otherwise every label of the
    subject is dropped (its points stay unlabeled, its markers missing).

    A performer who left otherwise keeps predicting at his last place, and his markers take
    isolated points there (ghosts born near the others, a neighbour's marker) frame after frame,
    so he is never seen to leave. Isolated points cannot show a body's shape; a returning
    performer shows it with his first three markers on one body. A present subject (3+ markers
    observed in the previous frame) is not checked: a performer seen badly (half his markers
    hidden, his bodies bending at 12.5 Hz) keeps every label Algorithm 1 gave him.

    A subject labeled with fewer than ``presence_drop`` of the markers observed in the previous
    frame (all of his vanished at once: a take that ends) is checked in the same way while the
    other subjects kept at least :data:`VANISH_OTHERS_KEPT` of theirs; a frame that lost most
    points of everyone (a system dropout, a frame thinned at random) is no one leaving, and a
    lone subject is never checked so.
    """
    assigned, owner = scratch.assigned, scratch.owner
    subj_ptr, subj_idx = tracks.subj_ptr, tracks.subj_idx
    mb_ptr, mb_idx = bodies.mb_ptr, bodies.mb_idx
    need, tol, drop = params.presence_min_markers, params.presence_tol_mm, params.presence_drop
    total_labeled = 0
    total_seen = 0
    if drop > 0.0:
        for m in range(tracks.x.shape[0]):
            if assigned[m] >= 0:
                total_labeled += 1
            if tracks.age[m] > 0:
                total_seen += 1
    for s in range(subj_ptr.shape[0] - 1):
        labeled = 0
        seen = 0  # observed in the previous frame (ages change only after this)
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            if assigned[subj_idx[e]] >= 0:
                labeled += 1
            if tracks.age[subj_idx[e]] > 0:
                seen += 1
        if labeled == 0:
            continue
        # absent (:func:`_absent` counted this frame's subject), or vanishing at once while
        # the others kept at least half of theirs (a frame that lost most points of everyone,
        # a system dropout, is no one leaving: no shape can be asked of anyone there)
        vanishing = (
            labeled < drop * seen
            and total_labeled - labeled >= VANISH_OTHERS_KEPT * (total_seen - seen)
            and total_seen > seen
        )
        if not tracks.gone[subj_idx[subj_ptr[s]]] and not vanishing:
            continue
        present = False
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            m = subj_idx[e]
            if assigned[m] < 0:
                continue
            for q in range(mb_ptr[m], mb_ptr[m + 1]):
                if _consistent(mb_idx[q], points, assigned, bodies, need, tol):
                    present = True
                    break
            if present:
                break
        if present:
            continue
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            m = subj_idx[e]
            if assigned[m] >= 0:
                owner[assigned[m]] = NONE
                assigned[m] = NONE


@njit
def _reacquire(points, index, frame_no, runs, tracks, bodies, recovery, scratch, params):
    """The wide re-acquisition pass (ours, docs/algorithm.md) after Algorithm 1.

    Bodies with fewer than two observed markers are released (their markers not held by a
    better-seen body search again) and, with every missing marker when ``reacquire_all``, look
    for free points within a wide radius: ``reacquire_estimate_mm`` around the rigid estimate
    of 3+ observed neighbours (``reacquire_loose_mm`` when those disagree), else
    ``reacquire_mm`` around the prediction. Algorithm 1 then runs again on those bodies only
    (everything else stays fixed), with the stricter ``miss_reacq``. ``runs``: this frame's
    points that continue an anonymous run (:mod:`.anonymous`; 0: none to refuse).
    """
    x, active, state = tracks.x, tracks.active, tracks.state
    s, assigned, owner, obs = scratch.s, scratch.assigned, scratch.owner, scratch.obs
    rec, missing, kab, rec_ok = scratch.rec, scratch.missing, scratch.kab, recovery.ok
    src, dst, R, t = kab.src, kab.dst, kab.R, kab.t  # the last Kabsch fit of _set_estimate
    body_markers, body_size = bodies.members, bodies.size
    satisfied = scratch.fit.satisfied  # Algorithm 1's scratch, reused between its passes
    robust_mm = params.robust_fit_mm
    m_total = x.shape[0]
    est4 = np.empty(3)
    n_lost = 0
    nb = body_markers.shape[0]
    for i in range(m_total):
        missing[i] = False
    for b in range(nb):
        c = 0
        for k in range(body_size[b]):
            if assigned[body_markers[b, k]] >= 0:
                c += 1
        satisfied[b] = c >= 2  # scratch: a well-seen body
        if not satisfied[b]:
            for k in range(body_size[b]):
                missing[body_markers[b, k]] = True
    for b in range(nb):
        if satisfied[b]:
            for k in range(body_size[b]):
                missing[body_markers[b, k]] = False
    for i in range(m_total):
        if params.reacquire_all and active[i] and assigned[i] == NONE:
            missing[i] = True
        if tracks.gone[i]:
            missing[i] = False  # the subject left: no wide search from stale predictions
        if params.reacquire_keep_observed and assigned[i] >= 0 and state[i] == OBSERVED:
            missing[i] = False  # tracked through the previous frame: keep
        if missing[i] and active[i]:
            if assigned[i] >= 0:
                owner[assigned[i]] = NONE
            assigned[i] = UNDECIDED
            n_lost += 1
        else:
            missing[i] = False
    if n_lost == 0:
        return
    # centre: the rigid estimate from the neighbours seen so far, else the prediction
    _observed(assigned, points, obs)
    anchored = scratch.anchored
    anc, anc_ref = tracks.anc, tracks.anc_ref
    for i in range(m_total):
        anchored[i] = False
        if not missing[i]:
            continue
        kept = 0
        loose_broken = False
        if rec_ok[i]:
            kept = _set_estimate(i, recovery, obs, kab, est4, robust_mm)
        if kept >= 3:
            for c in range(3):
                rec[i, c] = est4[c]
            s[i] = params.reacquire_estimate_mm
            residual = _max_residual(src, dst, kept, R, t)
            if residual > robust_mm:
                # the neighbours kept still disagree (a joint moved while the marker was
                # hidden): the estimate is loose, so is the search
                s[i] = params.reacquire_loose_mm
                # a loose estimate that breaks an anchor link is searched for like a broken
                # prediction, around the anchored estimate (kernels/anchor.py)
                loose_broken = (
                    params.anchor_lost
                    and params.anchor_loose
                    and residual > params.anchor_slack_mm + 3.0 * tracks.anc_cost[i, 0]
                    and _anchor_broken(
                        i, obs, anc, anc_ref, rec, params.anchor_slack_mm, tracks.anc_cost
                    )
                )
        if kept < 3 or loose_broken:
            # anchored on the marker's observed anchors (kernels/anchor.py), else the prediction
            k = -1
            if params.anchor_lost and (
                loose_broken
                or _anchor_broken(i, obs, anc, anc_ref, x, params.anchor_slack_mm, tracks.anc_cost)
            ):
                anchored[i] = True
                k = _anchor_estimate(i, obs, anc, anc_ref, rec)
            if k < 0:
                for c in range(3):
                    rec[i, c] = x[i, c]
            s[i] = params.reacquire_mm
    cand, cand_d2, ncand = scratch.cand, scratch.cand_d2, scratch.ncand
    gate, K = params.gate_chi2, params.K
    _regate(rec, missing, points, index, owner, s, gate, K, cand, cand_d2, ncand)
    if params.anchor_lost:
        # an anchored search keeps only points that keep the marker's anchor links
        anc, anc_ref, slack = tracks.anc, tracks.anc_ref, params.anchor_slack_mm
        for i in range(m_total):
            if anchored[i]:
                _anchor_filter(
                    i, points, obs, anc, anc_ref, slack, tracks.anc_cost, cand, cand_d2, ncand
                )
    if params.anonymous_tracks and runs > 0:
        _refuse_anonymous(cand, cand_d2, ncand, scratch.anon, tracks, frame_no)
    _fit_bodies(bodies, points, params.miss_reacq, scratch, params, params.distrust)
    for i in range(m_total):
        if assigned[i] == UNDECIDED:
            assigned[i] = NONE
