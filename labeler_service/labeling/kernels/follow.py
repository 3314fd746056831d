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
  or more of the marker's links that do not bend now, to members on points that continue their
  tracks, keep their trained distances (:func:`.repair._link_excess`, at most
  ``PAIR_SLACK_MM`` beyond 3 floored deviations in all) and no anonymous run refuses it.

Following stops when the point is ambiguous, taken by another marker, or gone.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.anonymous import _refused
from labeler_service.labeling.kernels.repair import _link_excess
from labeler_service.labeling.kernels.rigid import _take
from labeler_service.labeling.kernels.spatial import ANY, _alone, _nearest

FOLLOW_PAIRS = 2  # links that hold a followed point needs
FOLLOW_SLACK_MM = 3.0  # as the pair rule's PAIR_SLACK_MM


@njit
def _floor(params):
    """The gate floor's radius (mm): ``min_gate_mm``."""
    return np.sqrt(params.s_min * params.gate_chi2)


@njit
def _followed(i, points, index, dt, owner, tracks, params):
    """This frame's point that marker ``i``'s followed point went on as, -1 none."""
    if tracks.fol_n[i] <= 0 or not dt > 0.0:
        return -1
    r = _floor(params)
    c = np.empty(3)
    for a in range(3):
        c[a] = tracks.fol[i, a] + tracks.fol_v[i, a] * dt
    j, _ = _nearest(points, index, c, r * r, owner, ANY, -1)
    if j < 0 or owner[j] >= 0 or not _alone(points, index, c, 2.0 * r, j):
        return -1
    return j


@njit
def _follow_update(i, points, index, dt, owner, tracks, params):
    """End of a frame in which marker ``i`` has no point: start or go on following."""
    j = -1
    if tracks.fol_n[i] > 0:
        j = _followed(i, points, index, dt, owner, tracks, params)
    elif tracks.age[i] > 0 and dt > 0.0:  # observed in the previous frame: start
        r = 2.0 * _floor(params)
        c = tracks.kx[i]
        if c[0] == c[0]:  # noqa: PLR0124 (NaN: no prediction)
            j, _ = _nearest(points, index, c, r * r, owner, ANY, -1)
            if j >= 0 and (owner[j] >= 0 or not _alone(points, index, c, r, j)):
                j = -1
    if j < 0:
        tracks.fol_n[i] = 0
        return
    for a in range(3):
        last = np.float64(tracks.pos[i, a]) if tracks.fol_n[i] == 0 else tracks.fol[i, a]
        v = (np.float64(points[j, a]) - last) / dt
        tracks.fol_v[i, a] = v if v == v else 0.0  # noqa: PLR0124
        tracks.fol[i, a] = points[j, a]
    tracks.fol_n[i] += 1


@njit
def _acquire_followed(points, index, dt, frame_no, tracks, bodies, scratch, params):
    """Lost markers take back the point they followed (module doc). Returns how many."""
    assigned, owner = scratch.assigned, scratch.owner
    placed = 0
    for m in range(tracks.x.shape[0]):
        if tracks.fol_n[m] <= 0 or assigned[m] >= 0 or not tracks.active[m] or tracks.gone[m]:
            continue
        j = _followed(m, points, index, dt, owner, tracks, params)
        if j < 0:
            continue
        tot, cnt = _link_excess(
            m, j, -1, points, bodies, assigned, tracks.age, 1, params.a_floor_mm, params.a_relative
        )
        if cnt < FOLLOW_PAIRS or tot > FOLLOW_SLACK_MM:
            continue
        if params.anonymous_tracks and _refused(m, j, scratch.anon, tracks, frame_no):
            continue
        _take(m, j, points, assigned, owner, scratch.obs)
        # a new track on the point, moving as the point was followed moving
        for a in range(3):
            tracks.x[m, a] = points[j, a]
            tracks.x[m, 3 + a] = tracks.fol_v[m, a]
        tracks.P[m, 0], tracks.P[m, 1], tracks.P[m, 2] = params.r, 0.0, params.v0
        placed += 1
    return placed
