"""The whole per-frame loop of the online labeler in one numba entry point.

Order (seed 003 Fig. 2 and Algorithm 1): Kalman prediction (Eq. 3) -> Mahalanobis gating with at
most K candidates (Sec. 3.1) -> greedy rigid-body fitting (Eq. 5, Algorithm 1) -> track
continuity (points back to the markers tracked onto them, ours) -> wide re-acquisition and 3D
check (ours, see docs/algorithm.md) -> Kalman update of the observed markers (Eq. 4) -> recovery
of hidden markers from their bodies (Sec. 3.3; the recovered position also updates the Kalman
state with a larger ``R``, so a marker hidden for long is predicted from its body, not from a
stale state) -> sliding-window structure update (Eq. 1-2) -> reference snapshots of fully
observed bodies.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.fitting import _fit_bodies
from labeler_service.labeling.kernels.gating import _common_mode, _gate, _regate
from labeler_service.labeling.kernels.kalman import _predict, _start_or_update
from labeler_service.labeling.kernels.rigid import (
    _contest,
    _max_residual,
    _recover,
    _set_estimate,
    _snapshot,
    _verify,
)
from labeler_service.labeling.kernels.spatial import _index
from labeler_service.labeling.kernels.window import _window_update

OBSERVED = 1
RECOVERED = 2


@njit
def _observed(assigned, points, obs):
    """``obs[m]`` = the point marker ``m`` is assigned to, NaN when it has none."""
    for i in range(assigned.shape[0]):
        a = assigned[i]
        for c in range(3):
            obs[i, c] = points[a, c] if a >= 0 else np.nan


@njit
def _process_frame(
    points,
    dt,
    x,
    P,
    q,
    active,
    r,
    r_rec,
    s_min,
    v0,
    p_cap,
    vel_decay,
    gate,
    K,
    s,
    cand,
    cand_d2,
    ncand,
    bodies,
    D0,
    A0,
    ring,
    ptr,
    s1,
    s2,
    cnt,
    min_samples,
    a_floor,
    a_rel,
    miss_term,
    w,
    rset,
    method,
    assigned,
    owner,
    fit,
    obs,
    rec,
    has_rec,
    missing,
    kab,
    point_labels,
    out_pos,
    out_state,
    subj_ptr,
    subj_idx,
    cm_radius,
    cm_iters,
    cm_buf,
    cm_shift,
    reacq_radius,
    verify_mm,
    reacq_near_mm,
    miss_reacq,
    reacq_all,
    robust_mm,
    reject_mm,
    jump_mm,
    suspect_mm,
    n_reject,
    reject_limit,
    age,
    snap_age,
    reacq_est_mm,
    reacq_keep,
    verify_every,
    frame_no,
    swap_check,
    contest,
    reacq_loose_mm,
):
    """Labels one frame in place: ``point_labels (N,)``, ``out_pos (M, 3)``, ``out_state (M,)``."""
    m_total = x.shape[0]
    n = points.shape[0]
    est4 = np.empty(3)
    index = _index(points)
    body_markers, body_size, D, A = bodies[:4]
    satisfied = fit[2]  # Algorithm 1's scratch, reused between its passes
    # Eq. 3: predict; S = H P H^T + R
    _predict(x, P, q, active, dt, p_cap)
    if cm_iters > 0:
        _common_mode(
            x, active, subj_ptr, subj_idx, points, index, cm_radius, cm_iters, cm_buf, cm_shift
        )
    for i in range(m_total):
        s[i] = P[i, 0] + r
        if s[i] < s_min:  # gate floor: radius^2 = s_min * gate
            s[i] = s_min
    _gate(x, s, active, points, index, gate, K, cand, cand_d2, ncand)
    # Algorithm 1
    for i in range(m_total):
        assigned[i] = -2
    for j in range(n):
        owner[j] = -1
    _fit_bodies(
        bodies, cand, cand_d2, ncand, points, a_floor, a_rel, miss_term, w, gate, assigned, owner,
        fit,
    )  # fmt: skip
    # track continuity: points the fit gave to a marker that jumped for them go back to the
    # marker tracked onto them in the previous frame
    if contest:
        _observed(assigned, points, obs)
        _contest(
            assigned, owner, active, out_state, x, s, gate, points, obs, rset, jump_mm, verify_mm,
            kab, robust_mm,
        )  # fmt: skip
    # re-acquisition: bodies with fewer than two observed markers are released (their markers
    # not held by a better-seen body search again) and, with every missing marker when
    # ``reacq_all``, look for free points within a wide radius; Algorithm 1 then runs again on
    # those bodies only (everything else stays fixed)
    if reacq_radius > 0.0:
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
            if reacq_all and active[i] and assigned[i] == -1:
                missing[i] = True
            if reacq_keep and assigned[i] >= 0 and out_state[i] == OBSERVED:
                missing[i] = False  # tracked through the previous frame: keep
            if missing[i] and active[i]:
                if assigned[i] >= 0:
                    owner[assigned[i]] = -1
                assigned[i] = -2
                n_lost += 1
            else:
                missing[i] = False
        if n_lost > 0:
            # centre: the rigid estimate from the neighbours seen so far, else the prediction
            _observed(assigned, points, obs)
            for i in range(m_total):
                if not missing[i]:
                    continue
                kept = 0
                if rset[3][i]:
                    kept = _set_estimate(i, rset, obs, kab, est4, robust_mm)
                if kept >= 3:
                    for c in range(3):
                        rec[i, c] = est4[c]
                    s[i] = reacq_est_mm
                    if _max_residual(kab[0], kab[1], kept, kab[2], kab[3]) > robust_mm:
                        # the neighbours kept still disagree (a joint moved while the marker
                        # was hidden): the estimate is loose, so is the search
                        s[i] = reacq_loose_mm
                else:
                    for c in range(3):
                        rec[i, c] = x[i, c]
                    s[i] = reacq_radius
            _regate(rec, missing, points, index, owner, s, gate, K, cand, cand_d2, ncand)
            _fit_bodies(
                bodies, cand, cand_d2, ncand, points, a_floor, a_rel, miss_reacq, w, gate,
                assigned, owner, fit,
            )  # fmt: skip
            for i in range(m_total):
                if assigned[i] == -2:
                    assigned[i] = -1
    _observed(assigned, points, obs)
    if verify_mm > 0.0:
        _verify(
            assigned, owner, ncand, active, out_state, x, points, index, obs, rset, verify_mm,
            reacq_near_mm, reject_mm, jump_mm, suspect_mm, missing, kab, robust_mm, n_reject,
            reject_limit, verify_every, frame_no, swap_check,
        )  # fmt: skip
    for j in range(n):
        point_labels[j] = owner[j]
    # Eq. 4 for observed markers
    for i in range(m_total):
        a = assigned[i]
        if a >= 0:
            missing[i] = False  # the 3D check used it as scratch
            n_reject[i] = 0
            age[i] += 1
            _start_or_update(x, P, i, obs[i, 0], obs[i, 1], obs[i, 2], r, v0)
            out_state[i] = OBSERVED
            for c in range(3):
                out_pos[i, c] = obs[i, c]
        else:
            age[i] = 0
            for c in range(3):
                obs[i, c] = np.nan
            missing[i] = active[i]
            out_state[i] = 0
            for c in range(3):
                out_pos[i, c] = np.nan
    # Sec. 3.3: recovery from rigid bodies
    _recover(missing, rset, obs, method, rec, has_rec, kab, robust_mm)
    for i in range(m_total):
        if not missing[i]:
            continue
        if has_rec[i] > 0:
            # a rigid (3+ neighbours) estimate steers the Kalman state; a weaker one barely
            rr = r_rec if has_rec[i] >= 3 else 25.0 * r_rec
            _start_or_update(x, P, i, rec[i, 0], rec[i, 1], rec[i, 2], rr, v0)
            out_state[i] = RECOVERED
            for c in range(3):
                out_pos[i, c] = rec[i, c]
        else:
            for c in range(3, 6):
                x[i, c] *= vel_decay
    # Eq. 1-2: sliding window
    _window_update(body_markers, body_size, obs, ring, ptr, s1, s2, cnt, D0, A0, min_samples, D, A)
    # reference snapshots of the recovery sets
    _snapshot(age, snap_age, obs, rset)
