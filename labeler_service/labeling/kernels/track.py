"""Frame-to-frame matching of anonymous points (the boot's ``PointTracker``, every frame).

``PointTracker.update`` pairs each point of a frame with the previous frame's point whose
constant-velocity prediction it continues: a pair must be *mutual* (the point's nearest
prediction is that one, and that prediction's nearest point is this one) and within the
prediction's gate. It ran as two KD-tree builds and two unbounded nearest-neighbour queries per
frame: ~0.5 ms of a 10-performer frame at 360 Hz (500 points), a third of the booting labeler's
frame once every subject is booted (the labeled start, which tracks nothing, costs ~0.9 ms).

Here the same pairs come from the sweep index of :mod:`.spatial`, with bounded searches:

1. the nearest prediction ``j`` of point ``i`` is looked for within the largest gate only: if
   the unbounded nearest lies farther, no gate holds it anyway, and if it lies within, the
   bounded search finds that same one; the pair needs ``d(i, j) <= gate[j]``. The search
   tries the smallest gate first (a nearest found there is the nearest);
2. mutuality: prediction ``j``'s nearest point is ``i`` exactly when no other point lies
   closer to ``j`` than ``i`` does, so one search within radius ``d(i, j)`` decides it.

Both searches visit a slab a few centimetres wide instead of all points. Ties (two points at
one distance, which float data does not produce) go to the lower index, as in
:func:`.spatial._nearest`; the KD-tree picked either. The plain twin (the KD-tree version) is
``tests/reference.py:match_tracks``.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.spatial import ANY, _index, _nearest

# tracks whose velocities predict a track that has none yet (``_neighbour_velocity``)
NEIGHBOURS = 3
# relative slack on squared distances handed to a bounded search as its (strict) limit
_REL = 1e-9


@njit
def _match_tracks(pts, pred, gate):
    """``(N,)`` per point of ``pts (N, 3)`` the index of its mutual nearest prediction in
    ``pred (K, 3)`` within ``gate (K,)`` mm of it, or -1."""
    n = pts.shape[0]
    k = pred.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    if n == 0 or k == 0:
        return out
    gmax = 0.0
    gmin = np.inf
    for j in range(k):
        gmax = max(gmax, gate[j])
        gmin = min(gmin, gate[j])
    lim = gmax * gmax * (1.0 + _REL) + 1e-12
    # first within the smallest gate: a prediction found there is the nearest (any nearer one
    # lies there too), and most points continue a track that close; the largest gate (a track
    # without velocity: ~5 times wider) only for the others
    lim0 = min(gmin * gmin * (1.0 + _REL) + 1e-12, lim)
    ipred = _index(pred)
    ipts = _index(pts)
    none = np.empty(0, dtype=np.int64)
    for i in range(n):
        j, d2 = _nearest(pred, ipred, pts[i], lim0, none, ANY, -1)
        if j < 0 and lim0 < lim:
            j, d2 = _nearest(pred, ipred, pts[i], lim, none, ANY, -1)
        if j < 0 or d2 > gate[j] * gate[j]:
            continue
        back, _ = _nearest(pts, ipts, pred[j], d2 * (1.0 + _REL) + 1e-12, none, ANY, -1)
        if back == i:
            out[i] = j
    return out


@njit(fastmath=False)
def _neighbour_velocity(prev, prev_vel, prev_has_vel, j, radius, out):
    """The mean velocity of the (up to) ``NEIGHBOURS`` tracks with a velocity nearest
    ``prev[j]`` within ``radius`` mm, into ``out (3,)``; False when there is none."""
    bd = np.full(NEIGHBOURS, radius * radius)
    bi = np.full(NEIGHBOURS, -1, dtype=np.int64)
    for q in range(prev.shape[0]):
        if not prev_has_vel[q]:
            continue
        d2 = 0.0
        for c in range(3):
            d = prev[q, c] - prev[j, c]
            d2 += d * d
        if d2 >= bd[NEIGHBOURS - 1]:
            continue
        s = NEIGHBOURS - 1
        while s > 0 and bd[s - 1] > d2:
            bd[s] = bd[s - 1]
            bi[s] = bi[s - 1]
            s -= 1
        bd[s] = d2
        bi[s] = q
    m = 0
    for c in range(3):
        out[c] = 0.0
    for s in range(NEIGHBOURS):
        if bi[s] >= 0:
            m += 1
            for c in range(3):
                out[c] += prev_vel[bi[s], c]
    if m == 0:
        return False
    for c in range(3):
        out[c] /= m
    return True


@njit(fastmath=False)
def _track_step(
    pts, prev, prev_vel, prev_has_vel, prev_ids, prev_birth, dt, t, g0, speed_dt, nxt,
    rel_dt, radius,
):  # fmt: skip
    """One frame of ``PointTracker.update`` (boot_tracks.py) in one pass: the previous points
    ``prev (K, 3)`` predicted at constant velocity (``prev_vel`` where ``prev_has_vel``) with
    gates ``g0`` (``g0 + speed_dt`` without a velocity), matched (:func:`_match_tracks`), and
    per point of ``pts (N, 3)`` its track id (new ones from ``nxt`` on, in point order), velocity,
    whether it has one, and its track's birth time (``t`` for a new track). Returns ``(ids,
    vel, has_vel, birth, nxt)``. The same arithmetic as the former numpy steps, without
    fastmath (no fused or reassociated operations): the same tracks to the bit; the numpy
    steps around the kernel cost more than the kernel (~55 of ~90 us at 300 points).

    A track with no velocity yet moves with its neighbours when ``radius > 0``: predicted at
    the mean velocity of the nearest tracks that have one within ``radius`` mm, gate ``g0 +
    rel_dt`` (a marker's speed relative to its neighbours)."""
    n = pts.shape[0]
    k = prev.shape[0]
    ids = np.full(n, -1, dtype=np.int64)
    vel = np.zeros((n, 3))
    has_vel = np.zeros(n, dtype=np.bool_)
    birth = np.full(n, t)
    if n > 0 and k > 0:
        pred = np.empty((k, 3))
        gate = np.empty(k)
        v = np.empty(3)
        for j in range(k):
            if prev_has_vel[j]:
                for a in range(3):
                    pred[j, a] = prev[j, a] + prev_vel[j, a] * dt
                gate[j] = g0
            elif radius > 0.0 and _neighbour_velocity(prev, prev_vel, prev_has_vel, j, radius, v):
                for a in range(3):
                    pred[j, a] = prev[j, a] + v[a] * dt
                gate[j] = g0 + rel_dt
            else:
                for a in range(3):
                    pred[j, a] = prev[j, a] + 0.0
                gate[j] = g0 + speed_dt
        j_pt = _match_tracks(pts, pred, gate)
        for i in range(n):
            j = j_pt[i]
            if j >= 0:
                ids[i] = prev_ids[j]
                birth[i] = prev_birth[j]
                for a in range(3):
                    vel[i, a] = (pts[i, a] - prev[j, a]) / dt
                has_vel[i] = True
    for i in range(n):
        if ids[i] < 0:
            ids[i] = nxt
            nxt += 1
    return ids, vel, has_vel, birth, nxt


def match_tracks(pts: np.ndarray, pred: np.ndarray, gate: np.ndarray) -> np.ndarray:
    """Validating entry of :func:`_match_tracks` (float64, C-contiguous, finite positions)."""
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    pred = np.ascontiguousarray(pred, dtype=np.float64)
    gate = np.ascontiguousarray(gate, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pred.ndim != 2 or pred.shape[1] != 3:
        raise ValueError(f"points must be (N, 3) and (K, 3), got {pts.shape} and {pred.shape}")
    if gate.shape != (pred.shape[0],):
        raise ValueError(f"gate must be ({pred.shape[0]},), got {gate.shape}")
    return _match_tracks(pts, pred, gate)


@njit
def _track_history(ids, points, fids, starts, out):
    """Fills ``out (Q, W, 3)`` (NaN beforehand) with the positions of the tracks ``ids (Q,)`` in
    the ``W`` frames whose points ``points (sum N_w, 3)`` and track ids ``fids`` are stacked,
    frame ``w`` at rows ``starts[w]:starts[w + 1]``: one lookup table over the window's id
    range, filled and cleared per frame (track ids are unique within a frame)."""
    q = ids.shape[0]
    w_all = starts.shape[0] - 1
    if q == 0 or fids.shape[0] == 0:
        return
    lo = fids[0]
    hi = fids[0]
    for k in range(fids.shape[0]):
        lo = min(lo, fids[k])
        hi = max(hi, fids[k])
    table = np.full(hi - lo + 1, -1, dtype=np.int64)
    for w in range(w_all):
        for k in range(starts[w], starts[w + 1]):
            table[fids[k] - lo] = k
        for i in range(q):
            t = ids[i] - lo
            if 0 <= t <= hi - lo:
                k = table[t]
                if k >= 0:
                    out[i, w, 0] = points[k, 0]
                    out[i, w, 1] = points[k, 1]
                    out[i, w, 2] = points[k, 2]
        for k in range(starts[w], starts[w + 1]):
            table[fids[k] - lo] = -1


@njit
def _no_point_within(points, queries, gate):
    """``(Q,)`` True where no point of ``points (N, 3)`` lies within ``gate (Q,)`` mm of query
    ``queries[q] (Q, 3)`` (a jump watch's predictions: a few dozen a frame, so a plain scan
    that stops at the first point found)."""
    n = points.shape[0]
    q = queries.shape[0]
    out = np.ones(q, dtype=np.bool_)
    for i in range(q):
        g2 = gate[i] * gate[i]
        for j in range(n):
            d2 = 0.0
            for c in range(3):
                d = points[j, c] - queries[i, c]
                d2 += d * d
            if d2 <= g2:
                out[i] = False
                break
    return out
