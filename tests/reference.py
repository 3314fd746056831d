"""Plain-numpy twins of the numba kernels in ``labeler_service.labeling.kernels`` (slow, obvious).

Each twin follows the paper's formula directly (the full 6x6 Kalman filter, scipy's Mahalanobis
distance, ``itertools.product`` for the exhaustive search, Algorithm 1 recomputing every body at
every step) so the tests can compare the optimised kernels with them.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial.distance import mahalanobis

# --------------------------------------------------------------------------- Kalman (Eq. 3-4)


def kalman_full_predict(x, P6, q, dt):
    """Eq. 3 with the full matrices: ``x (6,)``, ``P6 (6, 6)``."""
    F = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    G = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    Q = q * np.kron(G, np.eye(3))
    return F @ x, F @ P6 @ F.T + Q


def kalman_full_update(x, P6, z, r):
    """Eq. 4 with the full matrices."""
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    S = H @ P6 @ H.T + r * np.eye(3)
    K = P6 @ H.T @ np.linalg.inv(S)
    x = x + K @ (z - H @ x)
    P6 = (np.eye(6) - K @ H) @ P6
    return x, P6


def p2_to_p6(p):
    """Factorised ``(p_pp, p_pv, p_vv)`` -> full ``P2 (x) I3``."""
    return np.kron(np.array([[p[0], p[1]], [p[1], p[2]]]), np.eye(3))


# --------------------------------------------------------------------------- gating


def gate(pred, s, active, points, gate_chi2, K):
    """Candidates per marker with scipy's Mahalanobis distance (``S = s I``), best K first."""
    out = []
    for i in range(pred.shape[0]):
        if not active[i]:
            out.append(([], []))
            continue
        vi = np.eye(3) / s[i]
        found = []
        for j in range(points.shape[0]):
            if not (np.isfinite(points[j]).all() and np.isfinite(pred[i, :3]).all()):
                continue
            d2 = mahalanobis(points[j].astype(float), pred[i, :3], vi) ** 2
            if d2 < gate_chi2:
                found.append((d2, j))
        found.sort()
        found = found[:K]
        out.append(([j for _, j in found], [d for d, _ in found]))
    return out


def regate(x, lost, points, owner, radius, gate_chi2, K):
    """The re-acquisition gate: free points within ``radius[i]`` of lost markers, K nearest."""
    out = {}
    for i in np.flatnonzero(lost):
        found = []
        for j in range(points.shape[0]):
            if owner[j] >= 0:
                continue
            d2 = float(np.sum((points[j] - x[i, :3]) ** 2)) * gate_chi2 / radius[i] ** 2
            if d2 < gate_chi2:
                found.append((d2, j))
        found.sort()
        out[int(i)] = [j for _, j in found[:K]]
    return out


def common_mode(x, active, groups, points, radius, iters):
    """Per-subject median nearest-point offset, applied ``iters`` times."""
    x = x.copy()
    shifts = []
    for g in groups:
        total = np.zeros(3)
        for _ in range(iters):
            offs = []
            for i in g:
                if not active[i] or not np.isfinite(x[i, 0]):
                    continue
                d = np.linalg.norm(points - x[i, :3], axis=1)
                if d.size and d.min() < radius:
                    offs.append(points[int(np.argmin(d))] - x[i, :3])
            if len(offs) < 3:
                break
            delta = np.median(np.asarray(offs), axis=0)
            total += delta
            for i in g:
                if active[i]:
                    x[i, :3] += delta
        shifts.append(total)
    return x, np.asarray(shifts)


# --------------------------------------------------------------------------- Eq. 5


def pair_term(D, A, a_floor, a_rel, miss_term, pa, pb):
    if pa is None or pb is None or not (np.isfinite(D) and np.isfinite(A)):
        return miss_term
    a = max(A, a_floor, a_rel * D)
    d = np.linalg.norm(np.asarray(pa, float) - np.asarray(pb, float))
    return float(np.exp(-((D - d) ** 2) / (2 * a * a)))


def score(assign, perm, mot_of, Db, Ab, a_floor, a_rel, miss_term, w, points):
    """Normalised Eq. 5 + motion score of one assignment (option per search position)."""
    n = len(assign)
    total = w * sum(mot_of[k] for k in range(n))
    for k in range(n):
        for l in range(k):
            pa = None if assign[k] < 0 else points[assign[k]]
            pb = None if assign[l] < 0 else points[assign[l]]
            total += pair_term(Db[perm[k], perm[l]], Ab[perm[k], perm[l]], a_floor, a_rel,
                               miss_term, pa, pb)  # fmt: skip
    return total / (n * (n - 1) / 2 + w * n)


def search_body(n, perm, opts, nopts, mot, Db, Ab, a_floor, a_rel, miss_term, w, points):
    """Exhaustive search with ``itertools.product``: best score and option indices (the first
    maximum in product order)."""
    best, arg = -1.0, None
    for combo in itertools.product(*[range(nopts[k]) for k in range(n)]):
        pts = [int(opts[k, o]) for k, o in enumerate(combo)]
        used = [p for p in pts if p >= 0]
        if len(used) != len(set(used)):
            continue
        s = score(pts, perm, [mot[k, o] for k, o in enumerate(combo)], Db, Ab, a_floor, a_rel,
                  miss_term, w, points)  # fmt: skip
        if s > best + 1e-12:
            best, arg = s, combo
    return best, arg


def rigidity(D, A, k, tol, w):
    """Mean over the ``k`` members' links of ``min(1, tol / (A + w D))`` (NaN link: 1)."""
    vals = []
    for i, j in itertools.combinations(range(k), 2):
        c = A[i, j] + w * D[i, j]
        vals.append(1.0 if not np.isfinite(c) or c <= tol else tol / c)
    return float(np.mean(vals)) if vals else 1.0


def fit_bodies(body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, a_floor, a_rel,
               miss_term, w, gate_chi2, weight=None):  # fmt: skip
    """Algorithm 1 literally: every step re-searches every unsatisfied body, satisfies the best
    (the highest score, times ``weight[b]`` when given: the distrust order).

    Returns ``assigned (M,)`` (point or -1) and ``owner (N,)``.
    """
    m_total = cand.shape[0]
    assigned = np.full(m_total, -2)
    owner = np.full(points.shape[0], -1)
    miss_mot = np.exp(-0.5 * gate_chi2)
    nb = body_markers.shape[0]
    satisfied = [body_size[b] == 0 for b in range(nb)]
    while not all(satisfied):
        results = []
        for b in range(nb):
            if satisfied[b]:
                continue
            members = list(body_markers[b, : body_size[b]])
            counts = []
            for mk in members:
                if assigned[mk] != -2:
                    counts.append(0)
                else:
                    counts.append(1 + sum(owner[cand[mk, o]] < 0 for o in range(ncand[mk])))
            perm = sorted(range(len(members)), key=lambda k: counts[k])
            K1 = cand.shape[1] + 1
            opts = np.zeros((8, K1), dtype=np.int64)
            mot = np.zeros((8, K1))
            nopts = np.zeros(8, dtype=np.int64)
            for pos, k in enumerate(perm):
                mk = members[k]
                if assigned[mk] != -2:
                    opts[pos, 0] = assigned[mk]
                    mot[pos, 0] = miss_mot
                    for o in range(ncand[mk]):
                        if cand[mk, o] == assigned[mk]:
                            mot[pos, 0] = np.exp(-0.5 * cand_d2[mk, o])
                            break
                    nopts[pos] = 1
                    continue
                c = 0
                for o in range(ncand[mk]):
                    if owner[cand[mk, o]] < 0:
                        opts[pos, c] = cand[mk, o]
                        mot[pos, c] = np.exp(-0.5 * cand_d2[mk, o])
                        c += 1
                opts[pos, c] = -1
                mot[pos, c] = miss_mot
                nopts[pos] = c + 1
            s, arg = search_body(len(members), perm, opts, nopts, mot, Db[b], Ab[b], a_floor,
                                 a_rel, miss_term, w, points)  # fmt: skip
            chosen = {members[k]: int(opts[pos, arg[pos]]) for pos, k in enumerate(perm)}
            results.append((s * (1.0 if weight is None else weight[b]), b, chosen))
        best = max(r[0] for r in results)
        s, r, chosen = next(x for x in results if x[0] == best)
        satisfied[r] = True
        for mk, p in chosen.items():
            if assigned[mk] == -2:
                assigned[mk] = p
                if p >= 0:
                    owner[p] = mk
    return assigned, owner


# --------------------------------------------------------------------------- Eq. 1-2


def window_stats(history, min_samples, D0, A0):
    """Mean and deviation of the finite values of ``history (T,)``; trained values below
    ``min_samples``."""
    h = np.asarray(history, dtype=np.float64)
    h = h[np.isfinite(h)]
    if h.size < max(1, min_samples):
        return D0, A0
    return float(h.mean()), float(h.std())


# --------------------------------------------------------------------------- recovery


def kabsch(src, dst):
    """``R, t`` minimising ``|R src + t - dst|`` (scipy-free SVD form, reflection excluded)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return R, cd - R @ cs


def robust_kabsch(src, dst, tau):
    src, dst = src.copy(), dst.copy()
    while True:
        R, t = kabsch(src, dst)
        if len(src) <= 3:
            return R, t, len(src)
        res = np.linalg.norm(src @ R.T + t - dst, axis=1)
        wi = int(np.argmax(res))
        if res[wi] <= tau:
            return R, t, len(src)
        last = len(src) - 1
        src[wi], dst[wi] = src[last].copy(), dst[last].copy()
        src, dst = src[:last], dst[:last]


def recover(m, members, ref, obs, method, tau):
    """Estimate of marker ``m`` from its recovery set (``members[0] == m``); None if impossible."""
    idx = [k for k in range(1, len(members)) if np.isfinite(obs[members[k], 0])]
    if not idx:
        return None
    src = np.array([ref[k] for k in idx], dtype=float)
    dst = np.array([obs[members[k]] for k in idx], dtype=float)
    if method == "kabsch" and len(idx) >= 3:
        R, t, _ = robust_kabsch(src, dst, tau)
        return R @ ref[0] + t
    return np.mean(dst + ref[0] - src, axis=0)


def set_estimate(m, members, ref, obs, tau):
    """Robust Kabsch estimate of ``m`` from its observed recovery-set members; None with fewer
    than 3."""
    idx = [k for k in range(1, len(members)) if np.isfinite(obs[members[k], 0])]
    if len(idx) < 3:
        return None
    src = np.array([ref[k] for k in idx], dtype=float)
    dst = np.array([obs[members[k]] for k in idx], dtype=float)
    R, t, _ = robust_kabsch(src, dst, tau)
    return R @ ref[0] + t


def contest(assigned, owner, active, prev_state, x, s, gate, points, obs, members, refs, rec_ok,
            jump, verify, tau):  # fmt: skip
    """Track continuity after Algorithm 1, marker by marker in index order (and again, up to 3
    passes, while a pass hands something over): a point held by a
    marker that jumped more than ``jump`` for it goes to the marker missing now with the smallest
    squared Mahalanobis distance ``|y - x|^2 / s`` to it, if that is below ``gate`` and a quarter
    of the holder's (a marker tracked in the previous frame must also predict it within
    ``jump``), unless the holder's rigid estimate is within ``verify`` of the point or the
    taker's estimate is farther from it than the holder's. ``members[m]`` and ``refs[m]`` are
    the recovery set and its snapshot. Returns the number of hand-overs (arrays in place)."""
    changes = 0
    for _pass in range(3):  # again while it hands something over (at most 3 passes)
        before = changes
        for m in range(len(assigned)):
            a = assigned[m]
            if a < 0:
                continue
            jump_m = np.linalg.norm(points[a] - x[m, :3])
            if jump_m <= jump:
                continue
            limit = min(gate, 0.25 * jump_m**2 / s[m])
            takers = []
            for m2 in range(len(assigned)):
                if assigned[m2] >= 0 or not active[m2]:
                    continue
                d = np.linalg.norm(points[a] - x[m2, :3])
                if prev_state[m2] == 1 and d >= jump:
                    continue
                if d**2 / s[m2] < limit:
                    takers.append((d**2 / s[m2], m2))
            if not takers:
                continue
            m2 = min(takers)[1]  # nearest (ties: lowest index)
            e_m = np.inf
            if rec_ok[m]:
                est = set_estimate(m, members[m], refs[m], obs, tau)
                if est is not None:
                    e_m = np.linalg.norm(points[a] - est)
            if e_m <= verify:
                continue
            if rec_ok[m2]:
                est = set_estimate(m2, members[m2], refs[m2], obs, tau)
                if est is not None and np.linalg.norm(points[a] - est) > e_m:
                    continue
            owner[a] = m2
            assigned[m2] = a
            assigned[m] = -1
            obs[m2] = points[a]
            obs[m] = np.nan
            changes += 1
        if changes == before:
            break
    return changes


def exchange(assigned, owner, active, prev_state, x, points, bodies, D, A, a_floor, a_rel,
             miss_term, jump, ratio):  # fmt: skip
    """Two tracked markers on each other's points, marker by marker in index order: for a marker
    observed in the previous frame more than ``jump`` from its prediction, its co-members (body
    order, member order) also observed then, the first whose exchange brings the summed
    prediction distances below ``ratio`` of the current ones while each exchanged marker keeps
    every Eq. 5 link to an assigned co-member (the partner left out) at ``miss_term`` or better.
    ``bodies``: member lists; ``D``, ``A``: per body, (k, k). Returns the exchanges (in place)."""

    def allows(m, q, partner):
        for b, mem in enumerate(bodies):
            if m not in mem:
                continue
            i = mem.index(m)
            for j, o in enumerate(mem):
                if o in (m, partner) or assigned[o] < 0:
                    continue
                t = pair_term(D[b][i, j], A[b][i, j], a_floor, a_rel, miss_term, points[q],
                              points[assigned[o]])  # fmt: skip
                if t < miss_term:
                    return False
        return True

    def partner(m, a, e11):
        """The first co-member the exchange applies to (body order, member order), or None."""
        for mem in (mem for mem in bodies if m in mem):
            for m2 in mem:
                a2 = assigned[m2]
                if m2 == m or a2 < 0 or prev_state[m2] != 1:
                    continue
                now = e11 + np.linalg.norm(points[a2] - x[m2, :3])
                after = np.linalg.norm(points[a2] - x[m, :3]) + np.linalg.norm(
                    points[a] - x[m2, :3]
                )
                if after < ratio * now and allows(m, a2, m2) and allows(m2, a, m):
                    return m2
        return None

    changes = 0
    for m in range(len(assigned)):
        a = assigned[m]
        if a < 0 or not active[m] or prev_state[m] != 1:
            continue
        e11 = np.linalg.norm(points[a] - x[m, :3])
        m2 = partner(m, a, e11) if e11 > jump else None
        if m2 is None:
            continue
        a2 = assigned[m2]
        assigned[[m, m2]] = a2, a
        owner[[a, a2]] = m2, m
        changes += 1
    return changes


def max_residual(src, dst, R, t):
    """Largest ``|R src_i + t - dst_i|``."""
    return float(np.max(np.linalg.norm(np.asarray(src) @ R.T + t - np.asarray(dst), axis=1)))


# --------------------------------------------------------------------------- rigid-body prediction


def remember(old, new, alpha):
    """Running error that rises at once (``kernels/motion.py``)."""
    if np.isnan(old):
        return new
    return max(new, (1.0 - alpha) * old + alpha * new)


def body_motion(members, mpos, obs, pred, kx, err, kerr, memory, tau):
    """Per body: ``(R, t, moving, err, kerr, mpos)`` after one frame, with the SVD Kabsch of
    the members observed in both frames (``members``: list of marker lists); with ``tau`` > 0
    a fit that leaves a member farther than ``tau`` is no motion."""
    alpha = 1.0 / memory if memory > 1.0 else 1.0
    out = []
    for b, mk in enumerate(members):
        e_b, e_k = err[b, : len(mk)].copy(), kerr[b, : len(mk)].copy()
        for k, m in enumerate(mk):
            if np.isfinite(obs[m, 0]) and np.isfinite(pred[b, k, 0]):
                e_b[k] = remember(e_b[k], np.sum((obs[m] - pred[b, k]) ** 2) / 3.0, alpha)
                e_k[k] = remember(e_k[k], np.sum((obs[m] - kx[m]) ** 2) / 3.0, alpha)
        both = [
            k for k, m in enumerate(mk) if np.isfinite(obs[m, 0]) and np.isfinite(mpos[b, k, 0])
        ]
        R = t = None
        moving = len(both) >= 3
        if moving:
            src, dst = mpos[b, both], obs[[mk[k] for k in both]]
            R, t = kabsch(src, dst)
            if tau > 0 and np.linalg.norm(src @ R.T + t - dst, axis=1).max() > tau:
                moving = False
        if not moving:
            e_b[:] = np.nan
            e_k[:] = np.nan
        out.append((R, t, moving, e_b, e_k, obs[mk].copy()))
    return out


def body_predict(members, R, t, moving, motion_dt, err, kerr, x, pos, dt):
    """Per marker: the Kalman state after the rigid-body prediction (``kernels/motion.py``):
    every body with a motion over a matching interval predicts ``R pos + t``; a marker takes
    the prediction of its body with the lowest running error below its Kalman error."""
    x = x.copy()
    best = {}
    for b, mk in enumerate(members):
        if not (moving[b] and abs(dt - motion_dt[b]) <= 0.25 * motion_dt[b]):
            continue
        for k, m in enumerate(mk):
            if np.isnan(pos[m, 0]) or not err[b, k] < kerr[b, k]:
                continue
            if m not in best or err[b, k] < best[m][0]:
                best[m] = (err[b, k], R[b] @ pos[m] + t[b])
    for m, (_, p) in best.items():
        x[m, 3:] = (p - pos[m]) / dt
        x[m, :3] = p
    return x


# --------------------------------------------------------------------------- template fit (repair)


def shape_rms(ref, pts, choice):
    """``(count, rms)`` of the members with a point (``choice[k]`` a row of ``pts`` or -1):
    RMS of ``ref`` after the best proper rigid motion onto their points (inf with < 3)."""
    idx = [k for k in range(len(choice)) if choice[k] >= 0]
    if len(idx) < 3:
        return len(idx), np.inf
    src = np.asarray(ref, dtype=float)[idx]
    dst = np.asarray(pts, dtype=float)[[choice[k] for k in idx]]
    R, t = kabsch(src, dst)
    return len(idx), float(np.sqrt(np.mean(np.sum((src @ R.T + t - dst) ** 2, axis=1))))


def fit_template(ref, tol, pts, accept_mm):
    """Every injective map of the members onto the points or "missing" (itertools.product):
    pair distances within ``tol`` of the reference's, RMS at most ``accept_mm``; the most points,
    then the smallest RMS. Returns ``(count, rms, choice)`` (``(0, inf, all -1)`` if none)."""
    n, nc = len(ref), len(pts)
    best = (0, np.inf, [-1] * n)
    for choice in itertools.product(*[list(range(nc)) + [-1]] * n):
        used = [p for p in choice if p >= 0]
        if len(set(used)) < len(used) or len(used) < 3:
            continue
        ok = all(
            abs(np.linalg.norm(pts[choice[i]] - pts[choice[j]]) - np.linalg.norm(ref[i] - ref[j]))
            <= tol[i, j]
            for i in range(n)
            for j in range(i)
            if choice[i] >= 0 and choice[j] >= 0
        )
        if not ok:
            continue
        c, rms = shape_rms(ref, pts, choice)
        if rms > accept_mm:
            continue
        if c > best[0] or (c == best[0] and rms < best[1] - 1e-9):
            best = (c, rms, list(choice))
    return best


def gone(lost, active, groups, absent_frames):
    """Per marker: every active marker of its subject (``groups``: marker lists) has been
    missing for ``absent_frames`` frames."""
    out = np.zeros(len(lost), dtype=bool)
    for g in groups:
        out[g] = all(lost[i] >= absent_frames for i in g if active[i])
    return out


def link_excess(m, p, skip, points, bodies, D0, A0, A, assigned, age, min_age, a_floor, a_rel):
    """``(sum, count)`` over marker ``m``'s trained links (``bodies``: member lists; ``D0``,
    ``A0``, ``A`` per body ``(k, k)``) to anchors (assigned, ``age >= min_age``, not ``m`` or
    ``skip``) whose window ``A`` is within 3 floored ``A0`` (a link that bends now is left
    out, not its whole body): how far point ``p``'s distance to the anchor's point is off ``D0``
    beyond 3 floored ``A0``."""
    tot, cnt = 0.0, 0
    for b, body in enumerate(bodies):
        if m not in body:
            continue
        floor = np.maximum(np.maximum(A0[b], a_floor), a_rel * D0[b])
        i = body.index(m)
        for j, other in enumerate(body):
            if other in (m, skip) or assigned[other] < 0 or age[other] < min_age:
                continue
            if np.isnan(D0[b][i, j]) or np.isnan(A0[b][i, j]):
                continue
            if A[b][i, j] > 3.0 * floor[i, j]:
                continue
            d = np.linalg.norm(points[p] - points[assigned[other]])
            tot += max(0.0, abs(d - D0[b][i, j]) - 3.0 * floor[i, j])
            cnt += 1
    return tot, cnt


def match_tracks(pts, pred, gate):
    """Twin of ``kernels/track.py``: mutual nearest neighbours by two KD-trees (unbounded
    queries), kept when within the prediction's gate; -1 for a point with no such pair."""
    from scipy.spatial import cKDTree

    n = pts.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    if n == 0 or pred.shape[0] == 0:
        return out
    d_pt, j_pt = cKDTree(pred).query(pts)
    _, i_tr = cKDTree(pts).query(pred)
    ok = (i_tr[j_pt] == np.arange(n)) & (d_pt <= gate[j_pt])
    out[ok] = j_pt[ok]
    return out


def pair_error(D, scale, logs, gauss, use, markers, points, assign, pts, sigmas):
    """Twin of ``kernels/boot_pairs.py:_pair_error`` (the numpy ``boot_match._pair_error`` it
    replaced): the pair table among ``markers`` (upper triangle) and against the rest of
    ``assign``, each pair's negative log-likelihood as in ``boot_match._nll``."""
    markers = np.asarray(markers, dtype=np.int64)
    points = np.asarray(points, dtype=np.int64)

    def nll(ma, pa, mb, pb):
        d = np.linalg.norm(pts[pa][:, None, :] - pts[pb][None, :, :], axis=2)
        r, c = ma[:, None], mb[None, :]
        e = np.abs(d - D[r, c]) / scale[r, c]
        cost = np.where(gauss[r, c], 0.5 * (sigmas * e) ** 2, np.log1p(e**2)) + logs[r, c]
        return np.where(use[r, c] & np.isfinite(cost), cost, 0.0)

    rest = np.flatnonzero(assign >= 0)
    rest = rest[~np.isin(rest, markers)]
    total = float(np.triu(nll(markers, points, markers, points), 1).sum())
    if rest.size:
        total += float(nll(markers, points, rest, assign[rest]).sum())
    return total


def grow(assign, taken, pts, D, TOL, bound, rigid, strict, link, own):
    """Twin of ``kernels/boot_grow.py:_grow`` (the numpy ``boot_match._grow`` it replaced, with
    its KD-tree ball query), in place on ``assign`` and ``taken``."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    for _ in range(3):
        changed = False
        have = np.flatnonzero(assign >= 0)
        for m in np.flatnonzero(assign < 0):
            part = have[rigid[m, have]]
            if part.size < 2 or not own[m, have].any():
                continue
            j = part[np.argmin(D[m, part])]
            near = tree.query_ball_point(pts[assign[j]], D[m, j] + TOL[m, j])
            near = np.asarray(near, dtype=np.int64)
            near = near[~taken[near]]
            if near.size == 0:
                continue
            d = np.linalg.norm(pts[near][:, None, :] - pts[assign[have]][None, :, :], axis=2)
            dev = d - D[m, have]
            rig = rigid[m, have]
            st = strict[m, have]
            tol = TOL[m, have]
            # pairs of one trained body must hold; a pair rigid by A alone counts when it fits
            fit = rig & (np.abs(dev) <= tol)
            bad = (st & (np.abs(dev) > tol)) | (~st & (dev > bound[m, have]))
            n_fit = fit.sum(axis=1)
            ok = ~bad.any(axis=1) & (n_fit >= 2) & (2 * n_fit >= part.size)
            if not np.any(ok & (n_fit >= 3)):
                # two rigid partners only: a ring of solutions, the point must be unique and
                # keep its articulated pairs in their trained range
                lt = link[m, have]
                ok &= ~np.any(~rig & (lt > 0) & (np.abs(dev) > lt), axis=1)
                if ok.sum() != 1:
                    continue
            else:
                ok &= n_fit >= 3
            best = -1
            if ok.any():
                err = (np.where(fit, dev / tol, 0.0) ** 2).sum(axis=1) / np.maximum(n_fit, 1)
                err = np.where(ok, err, np.inf)
                best = int(near[int(np.argmin(err))])
            if best >= 0:
                assign[m] = best
                taken[best] = True
                have = np.flatnonzero(assign >= 0)
                changed = True
        if not changed:
            return


def track_history(frames, ids):
    """Twin of ``boot_tracks.track_history`` (its ``kernels/track.py`` pass): per frame a sort
    of the frame's track ids and a search of ``ids`` in it."""
    out = np.full((ids.shape[0], len(frames), 3), np.nan)
    for w, (pts, fids) in enumerate(frames):
        order = np.argsort(fids, kind="stable")
        sids = fids[order]
        if sids.shape[0] == 0:
            continue
        pos = np.minimum(np.searchsorted(sids, ids), sids.shape[0] - 1)
        hit = sids[pos] == ids
        out[hit, w] = pts[order[pos[hit]]]
    return out


def window_obs(frames, mask):
    """Twin of ``frame.window_observations`` (its ``kernels/stacked.py`` pass): per frame
    ``frame_points``, ``frame_labels`` and a scatter of the labels in ``mask``."""
    from labeler_service.labeling.frame import frame_labels, frame_points

    m = mask.shape[0]
    obs = np.full((len(frames), m, 3), np.nan)
    for k, (_, pts, lab) in enumerate(frames):
        pts = frame_points(pts)
        lab = frame_labels(lab, pts.shape[0], m)
        ok = lab >= 0
        ok[ok] = mask[lab[ok]]
        obs[k, lab[ok]] = pts[ok]
    return obs


def spread_labels(window_ids, window_labels, ids, labels):
    """Twin of ``BootingLabeler._spread`` (its ``kernels/stacked.py`` pass): per frame the
    track labels by a search, and per label its first free point unless the frame has it
    (``np.unique``'s first occurrence). Returns new label arrays."""
    lab = labels >= 0
    tid, tl = ids[lab], labels[lab]
    order = np.argsort(tid)
    tid, tl = tid[order], tl[order]
    out = []
    for fids, old in zip(window_ids, window_labels, strict=True):
        old = old.copy()
        spread = np.full(fids.shape[0], -1, dtype=np.int64)
        if tid.size:
            pos = np.minimum(np.searchsorted(tid, fids), tid.size - 1)
            hit = tid[pos] == fids
            spread[hit] = tl[pos[hit]]
        cand = np.flatnonzero((old < 0) & (spread >= 0))
        if cand.size:
            taken = np.zeros(int(max(old.max(initial=-1), spread.max()) + 1), dtype=bool)
            taken[old[old >= 0]] = True
            new = spread[cand]
            _, first = np.unique(new, return_index=True)
            ok = first[~taken[new[first]]]
            old[cand[ok]] = new[ok]
        out.append(old)
    return out


# ------------------------------------------------------- chirality volumes (structure training)


def volume_stats(p, q, quantile=0.1):
    """Twin of ``kernels.chirality.volume_stats``: ``np.linalg.det`` of each frame's edge
    vectors (NaN where a marker is unseen: LAPACK returns 0 for a singular matrix holding a
    NaN row), then per column the frames seen, the fraction positive and the ``quantile`` of
    the cube root of ``|det|`` (numpy's linear interpolation; 0 where none)."""
    det = np.full((p.shape[0], q.shape[0]), np.nan)
    for f, k in itertools.product(range(p.shape[0]), range(q.shape[0])):
        e = (p[f, q[k, 1:]] - p[f, q[k, 0]]).astype(np.float64)
        if np.isfinite(e).all():
            det[f, k] = np.linalg.det(e)
    seen = np.isfinite(det)
    n = seen.sum(axis=0)
    pos_frac = np.where(seen, det > 0, False).sum(axis=0) / np.maximum(n, 1)
    thick = np.array(
        [np.percentile(np.cbrt(np.abs(col[ok])), 100 * quantile) if ok.any() else 0.0
         for col, ok in zip(det.T, seen.T, strict=True)]
    )  # fmt: skip
    return n, pos_frac, thick


def constancy_counts(hist, pts, D, tol, strict):
    """Twin of ``kernels/boot_pairs.py:_constancy_counts`` (the numpy block of
    ``boot_match._constancy`` it replaced): per placed marker, its strict pairs' distances along
    the tracks seen, and those off ``D +- tol``."""
    h = hist[np.asarray(pts, dtype=np.int64)]  # (n, W, 3)
    d = np.linalg.norm(h[:, None] - h[None, :], axis=3)  # (n, n, W)
    pair = strict[..., None] & np.isfinite(d)
    bad = pair & (np.abs(d - D[..., None]) > tol[..., None])
    return pair.sum(axis=(1, 2)), bad.sum(axis=(1, 2))


def body_scores(
    bodies, chosen, blocked, links, lerr, possible, support, against, near, M, refused,
    complete, link_fraction,
):  # fmt: skip
    """Twin of ``boot_match._body_scores`` (the numpy body step of ``boot_match._select`` it
    replaced): ``(total, rsum, count, free & beside, bb)``."""
    bb = bodies >= 0
    if complete:
        shared = (chosen[bodies] & bb).sum(axis=1)
        bb = bb & ~chosen[np.maximum(bodies, 0)]
    else:
        shared = np.zeros(bodies.shape[0], dtype=np.int64)
    free = ~np.any(blocked[bodies] & bb, axis=1) & bb.any(axis=1)
    count = (links[bodies] * bb).sum(axis=1)
    soft = count - (lerr[bodies] * bb).sum(axis=1)
    frac = count / np.maximum((possible[bodies] * bb).sum(axis=1), 1)
    placed = np.zeros(near.shape[1], dtype=bool)
    placed[M[chosen]] = True
    beside = (near & placed).sum(axis=1) >= (1 if complete else 2)
    sup = support[bodies] * bb
    differ = (against[bodies] * bb).sum(axis=1)
    ok = free & beside & (differ <= sup.sum(axis=1)) & ~refused
    total = np.where(ok & (frac >= link_fraction), soft, -1.0)
    rsum = np.where(free & ((sup > 0).sum(axis=1) >= 2), sup.sum(axis=1) + shared, 0)
    return total, rsum, count, free & beside, bb


def join_triangles(a1, b1, a2s, b2s, keys3, n):
    """Twin of ``kernels.boot_anchor._join_triangles`` (the numpy join of
    ``boot_match._triangles`` it replaced)."""
    lo = np.searchsorted(a2s, a1, side="left")
    hi = np.searchsorted(a2s, a1, side="right")
    cnt = hi - lo
    if cnt.sum() == 0 or keys3.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    rep = np.repeat(np.arange(a1.size), cnt)
    start = np.repeat(lo, cnt)
    within = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    p, q, r = a1[rep], b1[rep], b2s[start + within]
    key = q.astype(np.int64) * n + r
    pos = np.minimum(np.searchsorted(keys3, key), keys3.size - 1)
    ok = (keys3[pos] == key) & (q != r)
    return np.stack([p[ok], q[ok], r[ok]], axis=1)


def anchor_predict(tri_shape, shape, pts, trip):
    """Twin of ``kernels.boot_anchor._anchor_predict``: the batched SVD Kabsch of
    ``boot_match._body_candidates`` it replaced (``boot_match._kabsch_batch``, still the boot's
    fit of one placement), applied to every member."""
    from labeler_service.labeling.boot_match import _kabsch_batch

    R, cs, cd = _kabsch_batch(tri_shape, pts[trip])
    return np.einsum("kj,cij->cki", shape - cs, R) + cd[:, None, :]


def swap_gains(D, scale, logs, gauss, use, have, ka, kb, pts, sigmas):
    """Twin of ``kernels/boot_pairs.py:_swap_gains``: per pair ``(have[ka], have[kb])`` of
    placed markers on ``pts (k, 3)``, the negative log-likelihood (as ``boot_match._nll``) of
    the two markers' pairs with the other placed markers as they are less with their points
    exchanged; NaN where either point is untracked."""
    have = np.asarray(have, dtype=np.int64)

    def nll(rows, cols, d):
        e = np.abs(d - D[rows, cols]) / scale[rows, cols]
        cost = np.where(gauss[rows, cols], 0.5 * (sigmas * e) ** 2, np.log1p(e**2))
        cost = cost + logs[rows, cols]
        return np.where(use[rows, cols] & np.isfinite(cost), cost, 0.0)

    out = np.full(len(ka), np.nan)
    for p, (i, j) in enumerate(zip(ka, kb, strict=True)):
        if not (np.isfinite(pts[i, 0]) and np.isfinite(pts[j, 0])):
            continue
        rest = np.array([r for r in range(have.size) if r not in (i, j)], dtype=np.int64)
        di = np.linalg.norm(pts[rest] - pts[i], axis=1)
        dj = np.linalg.norm(pts[rest] - pts[j], axis=1)
        a, b, m = have[i], have[j], have[rest]
        now = nll(a, m, di) + nll(b, m, dj)
        swap = nll(a, m, dj) + nll(b, m, di)
        out[p] = float((now - swap).sum())
    return out
