"""A lost marker follows its own point (ours, issue 10).

A marker whose point leaves its gate in a sudden deceleration (a toe landing at 50 Hz: 41 mm a
frame, then 16) is lost although its point goes on, alone, where it was. Its prediction then
coasts away, and the lost rules (:mod:`.unseen`) need three links that hold: a foot marker
whose third link crosses the ankle is never placed again (tune18 ``rate``, ``RTOE``, 44
frames). Two links leave a circle of places, and a wrong point on it was taken (a 389-frame
swap, BENCHMARKS.md). Continuity names the point on that circle:

- *start* (end of the frame the marker lost its point): the free point nearest its
  constant-velocity prediction (``tracks.kx``) within twice the gate floor, with no other point
  within that of the prediction, is the point it went on as;
- *follow* (each frame after, while the marker stays lost): the followed point moved by its
  own velocity; the nearest point within the gate floor, no other within twice that, free;
- *take back* (:func:`_acquire_followed`, before the lost rules): the followed point, when two
  or more distinct anchors (members of the marker's bodies on points that continue their
  tracks), over links that do not bend now, keep their trained distances
  (:func:`_anchors_held`: the worst link per anchor, at most ``FOLLOW_SLACK_MM`` beyond 3
  floored deviations in all) and no anonymous run refuses it. The marker starts a new track
  there, moving with the velocity the point was followed with.

Following stops when the point is ambiguous, taken by another marker, followed by another
lost marker, or gone, and for a marker whose subject left.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.anonymous import _refused
from labeler_service.labeling.kernels.repair import _bends
from labeler_service.labeling.kernels.rigid import _take
from labeler_service.labeling.kernels.spatial import ANY, _alone, _nearest
from labeler_service.labeling.kernels.unseen import _slot

FOLLOW_ANCHORS = 2  # distinct anchors a followed point needs
FOLLOW_SLACK_MM = 3.0  # as the pair rule's PAIR_SLACK_MM


@njit
def _floor(params):
    """The gate floor's radius (mm): ``min_gate_mm``."""
    return np.sqrt(params.s_min * params.gate_chi2)


@njit
def _followed(i, points, index, dt, owner, tracks, params):
    """This frame's point that marker ``i``'s followed point went on as, -1 none."""
    if tracks.fol[i, 6] <= 0 or not dt > 0.0:
        return -1
    r = _floor(params)
    c = np.empty(3)
    for a in range(3):
        c[a] = tracks.fol[i, a] + tracks.fol[i, 3 + a] * dt
    return _sole_free(points, index, c, r, 2.0 * r, owner)


@njit
def _sole_free(points, index, c, near, alone, owner):
    """The point nearest ``c`` within ``near`` when it is free and no other point lies within
    ``alone`` of ``c``; -1 otherwise."""
    j, _ = _nearest(points, index, c, near * near, owner, ANY, -1)
    if j < 0 or owner[j] >= 0 or not _alone(points, index, c, alone, j):
        return -1
    return j


@njit
def _follow_all(points, index, dt, tracks, scratch, params):
    """End of a frame's labeling, before the Kalman update (``tracks.pos`` and ``age`` still
    the last frame's): markers on a point stop following, active markers without one start
    or go on (:func:`_follow_update`). Its own pass, called only with the rule on: the
    update loop stays as it was."""
    assigned, owner = scratch.assigned, scratch.owner
    for i in range(assigned.shape[0]):
        if assigned[i] >= 0:
            tracks.fol[i, 6] = 0.0
        elif tracks.active[i]:
            _follow_update(i, points, index, dt, owner, tracks, params)


@njit
def _follow_update(i, points, index, dt, owner, tracks, params):
    """End of a frame in which marker ``i`` has no point: start or go on following."""
    j = -1
    if tracks.gone[i]:
        pass  # the subject left: nothing to follow for its return
    elif tracks.fol[i, 6] > 0:
        j = _followed(i, points, index, dt, owner, tracks, params)
    elif tracks.age[i] > 0 and dt > 0.0:  # observed in the previous frame: start
        r = 2.0 * _floor(params)
        c = tracks.kx[i]
        if c[0] == c[0]:  # noqa: PLR0124 (NaN: no prediction)
            j = _sole_free(points, index, c, r, r, owner)
    if j >= 0 and _followed_by_another(i, points[j], tracks):
        j = -1  # (the marker followed first this frame keeps it; the link check judges it)
    if j < 0:
        tracks.fol[i, 6] = 0.0
        return
    for a in range(3):
        last = np.float64(tracks.pos[i, a]) if tracks.fol[i, 6] == 0 else tracks.fol[i, a]
        v = (np.float64(points[j, a]) - last) / dt
        tracks.fol[i, 3 + a] = v if v == v else 0.0  # noqa: PLR0124
        tracks.fol[i, a] = points[j, a]
    tracks.fol[i, 6] += 1.0


@njit
def _followed_by_another(i, q, tracks):
    """Another marker follows point ``q`` this frame (two neighbours that lost their points in
    one frame, one point left): the first to follow it keeps following, the other stops."""
    for k in range(tracks.fol.shape[0]):
        if k == i or tracks.fol[k, 6] <= 0:
            continue
        if tracks.fol[k, 0] == q[0] and tracks.fol[k, 1] == q[1] and tracks.fol[k, 2] == q[2]:
            return True
    return False


@njit
def _acquire_followed(points, index, dt, frame_no, tracks, bodies, scratch, params):
    """Lost markers take back the point they followed (module doc). Returns how many."""
    assigned, owner = scratch.assigned, scratch.owner
    runs = tracks.seen_at, tracks.track_from  # (arrays for the per-marker call)
    placed = 0
    for m in range(tracks.x.shape[0]):
        if tracks.fol[m, 6] <= 0 or assigned[m] >= 0 or not tracks.active[m] or tracks.gone[m]:
            continue
        j = _followed(m, points, index, dt, owner, tracks, params)
        if j < 0:
            continue
        tot, cnt = _anchors_held(m, j, points, tracks, bodies, assigned, params)
        if cnt < FOLLOW_ANCHORS or tot > FOLLOW_SLACK_MM:
            continue
        if params.anonymous_tracks and _refused(m, j, scratch.anon, *runs, frame_no):
            continue
        _take(m, j, points, assigned, owner, scratch.obs)
        # a new track on the point, moving with the velocity it was followed with (the last
        # frame's step instead, (point - fol) / dt, measured identical on the labeled matrix and
        # worse on the boot matrix's tune04 `half`: boot 1.04 -> 1.28 s, a 13-frame swap)
        for a in range(3):
            tracks.x[m, a] = points[j, a]
            tracks.x[m, 3 + a] = tracks.fol[m, 3 + a]
        tracks.P[m, 0], tracks.P[m, 1], tracks.P[m, 2] = params.r, 0.0, params.v0
        placed += 1
    return placed


@njit
def _anchors_held(m, p, points, tracks, bodies, assigned, params):
    """``(sum, anchors)``: the distinct *anchors* of marker ``m`` (members of its bodies on
    points that continue their tracks) over whose links that do not bend now point ``p`` is
    judged, and the sum over them of the worst excess of the distance beyond 3 floored trained
    deviations (as :func:`.repair._link_excess` has it, per link). An anchor in two of ``m``'s
    bodies is one anchor: its places are a sphere, whatever the number of bodies that hold the
    pair. (The per-link arithmetic is written out here: split out of ``_link_excess`` into a
    helper both call, it made the pair check's frame 10-15 % slower at 10 performers.)"""
    members, size, mb_ptr, mb_idx = bodies.members, bodies.size, bodies.mb_ptr, bodies.mb_idx
    cap = 0
    for e in range(mb_ptr[m], mb_ptr[m + 1]):
        cap += size[mb_idx[e]]
    seen = np.empty(cap, dtype=np.int64)
    worst = np.empty(cap)
    n = 0
    for e in range(mb_ptr[m], mb_ptr[m + 1]):
        b = mb_idx[e]
        i = _slot(members, b, m)
        for j in range(size[b]):
            k = members[b, j]
            if j == i or assigned[k] < 0 or tracks.age[k] < 1:
                continue
            d0 = bodies.D0[b, i, j]
            a0 = bodies.A0[b, i, j]
            if d0 != d0 or a0 != a0:  # noqa: PLR0124 (NaN: no trained distance)
                continue
            if _bends(bodies.A[b, i, j], a0, d0, params.a_floor_mm, params.a_relative):
                continue  # a link that bends now
            a0 = max(a0, params.a_floor_mm, params.a_relative * d0)
            q = assigned[k]
            d2 = 0.0
            for a in range(3):
                d = points[p, a] - points[q, a]
                d2 += d * d
            x = max(abs(np.sqrt(d2) - d0) - 3.0 * a0, 0.0)
            t = 0
            while t < n and seen[t] != k:
                t += 1
            if t == n:
                seen[n] = k
                worst[n] = x
                n += 1
            elif x > worst[t]:
                worst[t] = x
    tot = 0.0
    for t in range(n):
        tot += worst[t]
    return tot, n
