"""Anchored coasting of lost markers (ours, docs/algorithm.md "Anchored coasting").

A marker that loses its point and has no rigid estimate (fewer than 3 observed neighbours in
its recovery set, Sec. 3.3) used to coast on its own constant-velocity Kalman state (Eq. 3),
pulled only weakly by a displacement estimate from one or two recovery-set neighbours. At
50 Hz a tennis wrist is lost at 3-5 m/s; the filter carries that velocity on, the prediction
drifts 150 mm a frame and ends 1-2 m from the arm (median 0.78 m on the tennis take alone),
so the markers are never searched where they reappear although they stay visible, and their
forearm and elbow neighbours are labeled all along. The recovery sets do not help: they are
chosen on the quiet training window and hold a wrist with the thigh and the pelvis (a hand
resting there), whose snapshot is from that window.

Here every observed marker keeps, per frame, two *anchors*: its body co-members observed in
the same frame with the most rigid links over the sliding window (lowest ``A + w D``, the
body-formation cost, with the window's ``D``, ``A`` of Eq. 1-2; the cost is kept as
``tracks.anc_cost``), and the positions of the marker and the anchors in that frame. A lost
marker's state is *broken* when its distance to an observed anchor differs from the recorded
one by more than ``anchor_slack_mm + 3 cost`` of that link (:func:`_anchor_broken`). For a lost
marker without a rigid estimate whose state is broken:

- the wide re-acquisition pass (:func:`.step._reacquire`) searches around the *anchored
  estimate* instead of the prediction, and keeps only the free points that keep the anchor
  links within the same slack (:func:`_anchor_filter`);
- with ``anchor_state`` (off by default) the Kalman state itself is also re-anchored
  (:func:`_anchor_lost`): position = the anchored estimate, velocity = the anchor's.

The anchored estimate (:func:`_anchor_estimate`): with two anchors seen, the recorded offset
from the first anchor turned by the smallest rotation that takes the recorded anchor-to-anchor
direction onto the current one (a forearm turning about the elbow carries the wrist with it;
the twist about that axis is not seen); with one, the offset translated onto it. With no
anchor observed the old behaviour stays.

A marker *with* a rigid estimate is searched for the same way when that estimate is loose (its
recovery neighbours disagree beyond ``robust_fit_mm``), breaks an anchor link
(:func:`_anchor_broken` applied to the estimate) and its residual exceeds the first anchor
link's tolerance (``anchor_slack_mm + 3 cost``): ``anchor_loose``, in
:func:`.step._reacquire`. A recovery set trained on a quiet window can hold a thigh with the
hand; once they move apart its estimate lies far off, and the more precise evidence is the
anchor link (tennis take: the thigh marker unlabeled for 340 frames while visible).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _anchor_snapshot(obs, tracks, bodies, w):
    """For every marker observed this frame (finite ``obs`` row): its two anchors (observed
    co-members of its bodies with the lowest window ``A + w D``) into ``tracks.anc (M, 2)`` and
    the positions of the marker and its anchors into ``tracks.anc_ref (M, 3, 3)``. A marker
    missing this frame keeps the snapshot of its last observation."""
    members, size, D, A = bodies.members, bodies.size, bodies.D, bodies.A
    mb_ptr, mb_idx = bodies.mb_ptr, bodies.mb_idx
    anc, ref = tracks.anc, tracks.anc_ref
    for m in range(obs.shape[0]):
        if obs[m, 0] != obs[m, 0]:  # noqa: PLR0124 (NaN: not observed)
            continue
        k0 = -1
        k1 = -1
        c0 = np.inf
        c1 = np.inf
        for e in range(mb_ptr[m], mb_ptr[m + 1]):
            b = mb_idx[e]
            i = 0
            while members[b, i] != m:
                i += 1
            for j in range(size[b]):
                k = members[b, j]
                if k == m or k == k0 or k == k1:  # noqa: SIM109 (numba: plain compares)
                    continue
                if obs[k, 0] != obs[k, 0] or D[b, i, j] != D[b, i, j]:  # noqa: PLR0124
                    continue
                c = A[b, i, j] + w * D[b, i, j]
                if c < c0:
                    k1, c1 = k0, c0
                    k0, c0 = k, c
                elif c < c1:
                    k1, c1 = k, c
        anc[m, 0] = k0
        anc[m, 1] = k1
        tracks.anc_cost[m, 0] = c0
        tracks.anc_cost[m, 1] = c1
        for a in range(3):
            ref[m, 0, a] = obs[m, a]
            ref[m, 1, a] = obs[k0, a] if k0 >= 0 else np.nan
            ref[m, 2, a] = obs[k1, a] if k1 >= 0 else np.nan


@njit
def _anchor_estimate(m, obs, anc, ref, x):
    """The anchored estimate of marker ``m`` from its anchors observed now (module docstring),
    written into ``x[m, :3]``; returns the anchor whose velocity it takes, or -1 (no anchor
    observed: ``x`` untouched)."""
    k0, k1 = anc[m, 0], anc[m, 1]
    h0 = k0 >= 0 and obs[k0, 0] == obs[k0, 0]  # noqa: PLR0124
    h1 = k1 >= 0 and obs[k1, 0] == obs[k1, 0]  # noqa: PLR0124
    if not h0 and not h1:
        return -1
    if not (h0 and h1):
        k = k0 if h0 else k1
        r = 1 if h0 else 2
        for a in range(3):
            x[m, a] = obs[k, a] + ref[m, 0, a] - ref[m, r, a]
        return k
    # offset p from anchor 0, rotated by the smallest rotation taking the snapshot direction
    # u (anchor 0 -> anchor 1) onto the current one v
    p0 = ref[m, 0, 0] - ref[m, 1, 0]
    p1 = ref[m, 0, 1] - ref[m, 1, 1]
    p2 = ref[m, 0, 2] - ref[m, 1, 2]
    u0 = ref[m, 2, 0] - ref[m, 1, 0]
    u1 = ref[m, 2, 1] - ref[m, 1, 1]
    u2 = ref[m, 2, 2] - ref[m, 1, 2]
    v0 = obs[k1, 0] - obs[k0, 0]
    v1 = obs[k1, 1] - obs[k0, 1]
    v2 = obs[k1, 2] - obs[k0, 2]
    nu = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    nv = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if nu > 1e-6 and nv > 1e-6:
        u0, u1, u2 = u0 / nu, u1 / nu, u2 / nu
        v0, v1, v2 = v0 / nv, v1 / nv, v2 / nv
        # Rodrigues: axis n = u x v (|n| = sin), c = u . v (cos)
        n0 = u1 * v2 - u2 * v1
        n1 = u2 * v0 - u0 * v2
        n2 = u0 * v1 - u1 * v0
        c = u0 * v0 + u1 * v1 + u2 * v2
        s2 = n0 * n0 + n1 * n1 + n2 * n2
        if s2 > 1e-12:
            # R p = c p + n x p + (n . p) n (1 - c) / |n|^2
            f = (n0 * p0 + n1 * p1 + n2 * p2) * (1.0 - c) / s2
            r0 = c * p0 + (n1 * p2 - n2 * p1) + f * n0
            r1 = c * p1 + (n2 * p0 - n0 * p2) + f * n1
            r2 = c * p2 + (n0 * p1 - n1 * p0) + f * n2
            p0, p1, p2 = r0, r1, r2
        elif c < 0.0:
            # opposite directions: the half turn about the axis normal to u in the plane of u
            # and p (p's component along u flips, the rest stays)
            d = p0 * u0 + p1 * u1 + p2 * u2
            p0, p1, p2 = p0 - 2.0 * d * u0, p1 - 2.0 * d * u1, p2 - 2.0 * d * u2
    x[m, 0] = obs[k0, 0] + p0
    x[m, 1] = obs[k0, 1] + p1
    x[m, 2] = obs[k0, 2] + p2
    return k0


@njit
def _breaks(p0, p1, p2, m, r, obs, anc, ref, slack, cost):
    """The position ``(p0, p1, p2)`` for marker ``m`` breaks its link to anchor ``r`` (0 or 1):
    the anchor is observed and the distance to it differs from the snapshot distance by more
    than ``slack + 3 cost`` mm (the link's window ``A + w D``: a link that slides gets more)."""
    k = anc[m, r]
    if k < 0 or obs[k, 0] != obs[k, 0]:  # noqa: PLR0124
        return False
    d0, d1, d2 = p0 - obs[k, 0], p1 - obs[k, 1], p2 - obs[k, 2]
    e0 = ref[m, 0, 0] - ref[m, 1 + r, 0]
    e1 = ref[m, 0, 1] - ref[m, 1 + r, 1]
    e2 = ref[m, 0, 2] - ref[m, 1 + r, 2]
    now = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    then = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return abs(now - then) > slack + 3.0 * cost[m, r]


@njit
def _anchor_broken(m, obs, anc, ref, x, slack, cost):
    """Marker ``m``'s position ``x[m, :3]`` breaks a link to one of its observed anchors
    (:func:`_breaks`). Such a prediction cannot be right (the anchors were chosen as the most
    rigid links); a prediction that keeps the links is left alone."""
    for r in range(2):
        if _breaks(x[m, 0], x[m, 1], x[m, 2], m, r, obs, anc, ref, slack, cost):
            return True
    return False


@njit
def _anchor_lost(obs, missing, has_rec, tracks, slack):
    """Re-anchors the Kalman state of every marker missing this frame (``missing``) that has
    no rigid estimate (``has_rec < 3``) and whose state breaks a link to an observed anchor
    (:func:`_anchor_broken`, ``slack + 3 cost`` mm): position = the anchored estimate,
    velocity = the anchor's (its Kalman state after this frame's update)."""
    x, anc, ref = tracks.x, tracks.anc, tracks.anc_ref
    for m in range(obs.shape[0]):
        if not missing[m] or has_rec[m] >= 3 or x[m, 0] != x[m, 0]:  # noqa: PLR0124
            continue
        if not _anchor_broken(m, obs, anc, ref, x, slack, tracks.anc_cost):
            continue
        k = _anchor_estimate(m, obs, anc, ref, x)
        if k >= 0:
            for a in range(3):
                x[m, 3 + a] = x[k, 3 + a]


@njit
def _anchor_filter(m, points, obs, anc, ref, slack, cost, cand, cand_d2, ncand):
    """Keeps, of marker ``m``'s candidates ``cand[m, :ncand[m]]`` (in order), only the points
    that break no link to an observed anchor (:func:`_breaks`, ``slack + 3 cost`` mm): a
    re-acquired point must keep the marker's rigid links. Ghosts and the points
    of the limb's other markers, near the anchored estimate but off those distances, drop."""
    kept = 0
    for c in range(ncand[m]):
        j = cand[m, c]
        p0, p1, p2 = np.float64(points[j, 0]), np.float64(points[j, 1]), np.float64(points[j, 2])
        ok = True
        for r in range(2):
            if _breaks(p0, p1, p2, m, r, obs, anc, ref, slack, cost):
                ok = False
                break
        if ok:
            cand[m, kept] = j
            cand_d2[m, kept] = cand_d2[m, c]
            kept += 1
    ncand[m] = kept
