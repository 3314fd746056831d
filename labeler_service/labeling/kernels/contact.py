"""Contacts between performers: both hypotheses kept until the points part (ours, issue 10).

Two markers of two performers that pass within ~15 mm of each other can leave Algorithm 1 with
their labels exchanged, and the exchange then lasts: the recovery snapshots (:mod:`.rigid`)
are re-taken every frame from the current assignment, so the 3D check's reference follows the
swap as the points part (docs/algorithm.md, "Swaps between performers that cross"). Nothing
seen *during* the contact can tell the two points apart; what can is how each point sits among
its own performer's neighbours *before* the contact, once the points are apart again.

- **Contact.** After the 3D check, swap repair and presence check, a labeled marker ``m``
  whose point lies within ``contact_mm`` of a point labeled for a marker ``m2`` of another
  subject (neither already in a contact, and the two not that close in the previous frame: a
  pair just decided must not take a reference from during its contact) registers the pair:
  ``tracks.ct_with[m] = m2`` and back, and each keeps a copy of its recovery snapshot
  (``recovery.ref``, taken at the end of the previous frame, before the contact) in
  ``tracks.ct_ref``.
- **Parting.** While both markers hold points more than ``contact_part_mm`` apart (closer,
  the two hypotheses cannot be told apart), each hypothesis is judged by the pre-contact
  references: the Kabsch estimate of ``m`` from its neighbours now and in ``ct_ref[m]`` (robust
  fit, ``robust_fit_mm``; neighbours in a contact themselves, and the partner, left out; 3+
  needed), and the same for ``m2``. The labels are exchanged when the exchange's summed
  distance to the two estimates is below ``contact_ratio`` times the kept assignment's, and the
  kept one's exceeds the points' distance (each point lies nearer the other marker's
  estimate); then the contact ends. Otherwise it is judged again the next frame, until the
  points are ``2 contact_mm`` apart: a decision that is not clear leaves things as they are.
  An exchange also exchanges the two Kalman states (they followed the points), and forgets
  the two markers' last body positions (``bodies.mpos``: no rigid motion from a point to the
  other performer's).
- A contact that has not parted within ``contact_max_s`` seconds, or whose partner was reset
  (withdrawn, dropped, a re-formed structure), is dropped without a decision. A marker whose
  track is restarted (``Labeler.seed_markers``, e.g. the booting labeler's fill labels it
  anew) keeps its open contact: the pair still touches, and ``ct_ref`` does not depend on the
  new track.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.rigid import _robust_kabsch


@njit
def _contact_estimate(m, tracks, recovery, obs, kab, out, tau):
    """Kabsch estimate of marker ``m`` from its recovery-set neighbours observed now and their
    pre-contact positions ``tracks.ct_ref[m]``; neighbours in a contact are left out. Returns
    the neighbours the robust fit kept (0: fewer than 3 usable)."""
    src, dst, R, t = kab.src, kab.dst, kab.R, kab.t
    ref, ct_with = tracks.ct_ref, tracks.ct_with
    c = 0
    for k in range(1, recovery.size[m]):
        mk = recovery.members[m, k]
        if obs[mk, 0] != obs[mk, 0] or ct_with[mk] >= 0:  # noqa: PLR0124 (NaN: not observed)
            continue
        if ref[m, k, 0] != ref[m, k, 0]:  # noqa: PLR0124
            continue
        for a in range(3):
            src[c, a] = ref[m, k, a]
            dst[c, a] = obs[mk, a]
        c += 1
    if c < 3:
        return 0
    c = _robust_kabsch(src, dst, c, R, t, tau)
    for a in range(3):
        out[a] = R[a, 0] * ref[m, 0, 0] + R[a, 1] * ref[m, 0, 1] + R[a, 2] * ref[m, 0, 2] + t[a]
    return c


@njit
def _dist(p, q):
    d2 = 0.0
    for a in range(3):
        d = np.float64(p[a]) - np.float64(q[a])
        d2 += d * d
    return np.sqrt(d2)


@njit
def _exchange(m, m2, points, tracks, bodies, scratch):
    """Exchanges the points of ``m`` and ``m2`` (both hold one) and their Kalman states."""
    assigned, owner, obs = scratch.assigned, scratch.owner, scratch.obs
    a, a2 = assigned[m], assigned[m2]
    assigned[m], assigned[m2] = a2, a
    owner[a], owner[a2] = m2, m
    for c in range(3):
        obs[m, c] = points[a2, c]
        obs[m2, c] = points[a, c]
    x, P, kx = tracks.x, tracks.P, tracks.kx
    for c in range(6):
        x[m, c], x[m2, c] = x[m2, c], x[m, c]
    for c in range(3):
        P[m, c], P[m2, c] = P[m2, c], P[m, c]
        kx[m, c], kx[m2, c] = kx[m2, c], kx[m, c]
    for mm in (m, m2):
        for q in range(bodies.mb_ptr[mm], bodies.mb_ptr[mm + 1]):
            b = bodies.mb_idx[q]
            for k in range(bodies.size[b]):
                if bodies.members[b, k] == mm:
                    for c in range(3):
                        bodies.mpos[b, k, c] = np.nan


@njit
def _contacts(points, index, dt, tracks, bodies, recovery, scratch, params):
    """Decides the contacts that parted, then registers new ones (module docstring). Reads and
    changes ``scratch.assigned``, ``owner``, ``obs`` (kept in sync); returns the exchanges."""
    assigned, owner, obs, kab = scratch.assigned, scratch.owner, scratch.obs, scratch.kab
    ct_with, ct_t, ct_ref, subj = tracks.ct_with, tracks.ct_t, tracks.ct_ref, tracks.subj
    near, part, tau = params.contact_mm, params.contact_part_mm, params.robust_fit_mm
    m_total = assigned.shape[0]
    est = np.empty(3)
    est2 = np.empty(3)
    changes = 0
    # contacts that parted (each pair once, from its lower marker)
    for m in range(m_total):
        m2 = ct_with[m]
        if m2 < 0:
            continue
        if ct_with[m2] != m or not tracks.active[m] or not tracks.active[m2]:
            ct_with[m] = -1  # the partner was reset or is in another contact
            continue
        if m2 < m:
            continue
        ct_t[m] += dt
        a, a2 = assigned[m], assigned[m2]
        if ct_t[m] > params.contact_max_s:
            ct_with[m] = -1  # no parting in time: undecided
            ct_with[m2] = -1
            continue
        if a < 0 or a2 < 0:
            continue
        d = _dist(points[a], points[a2])
        if d > 2.0 * near:
            ct_with[m] = -1  # parted without a clear exchange: the labels stay
            ct_with[m2] = -1
            continue
        if d <= part:
            continue  # too close to tell the hypotheses apart
        # judged with both markers out of the contact (a neighbour in one is left out)
        ct_with[m] = -1
        ct_with[m2] = -1
        k1 = _contact_estimate(m, tracks, recovery, obs, kab, est, tau)
        k2 = _contact_estimate(m2, tracks, recovery, obs, kab, est2, tau)
        ct_with[m] = m2
        ct_with[m2] = m
        if k1 == 0 or k2 == 0:
            continue  # no reference to judge by (yet)
        keep = _dist(points[a], est) + _dist(points[a2], est2)
        swap = _dist(points[a2], est) + _dist(points[a], est2)
        if keep > d and swap < params.contact_ratio * keep:
            _exchange(m, m2, points, tracks, bodies, scratch)
            ct_with[m] = -1
            ct_with[m2] = -1
            changes += 1
    # new contacts: a labeled point within contact_mm of another subject's labeled point (one
    # forward sweep of the sorted points: each pair once), the nearest such partner of each
    ct_near, ct_dn = scratch.ct_near, scratch.ct_dn
    for m in range(m_total):
        ct_near[m] = -1
        ct_dn[m] = near
    order, keys = index.order, index.keys
    n = keys.shape[0]
    for q in range(n):
        kq = keys[q]
        if not np.isfinite(kq):
            break  # non-finite keys sort last
        j = order[q]
        m = owner[j]
        if m < 0 or ct_with[m] >= 0 or not recovery.ok[m]:
            continue
        for q2 in range(q + 1, n):
            if keys[q2] - kq > near:
                break
            j2 = order[q2]
            m2 = owner[j2]
            if m2 < 0 or subj[m2] == subj[m] or ct_with[m2] >= 0 or not recovery.ok[m2]:
                continue
            d = _dist(points[j], points[j2])
            if d >= ct_dn[m] and d >= ct_dn[m2]:
                continue
            # only a pair coming together: a pair already this close in the previous frame
            # (a contact just decided) would take a reference from during the contact
            if _dist(tracks.pos[m], tracks.pos[m2]) < near:
                continue
            if d < ct_dn[m]:
                ct_dn[m] = d
                ct_near[m] = m2
            if d < ct_dn[m2]:
                ct_dn[m2] = d
                ct_near[m2] = m
    for m in range(m_total):
        bm = ct_near[m]
        if bm < 0 or ct_with[m] >= 0 or ct_with[bm] >= 0:
            continue
        ct_with[m] = bm
        ct_with[bm] = m
        ct_t[min(m, bm)] = 0.0
        for mm in (m, bm):
            for k in range(recovery.size[mm]):
                for c in range(3):
                    ct_ref[mm, k, c] = recovery.ref[mm, k, c]
    return changes
