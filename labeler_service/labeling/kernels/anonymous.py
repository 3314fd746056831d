"""Anonymous point tracks (ours, issue 10): a point that was there, unlabeled, while a marker was
still tracked on a point of its own is not that marker.

A marker that vanishes (hidden, occluded) is searched for around its prediction, in the wide
re-acquisition pass up to ``reacquire_mm`` (250 mm) when its bodies show nothing. Any free point
there may be taken, and the one taken is often a point that was already in the frame, unlabeled,
while the marker was still seen on its own point a few centimetres away: a ghost, a marker the
model does not know (a marker the window never saw), another performer's marker nobody holds.
Their coexistence is proof that the two are different points; distances and predictions alone
do not see it (the BTS walker's ``LATT`` took the point of ``SCL1``, 124 mm away, for 99
frames after an occlusion: holdout07 ``occlude2``).

Per point, the labeler keeps the frames in a row it has been unlabeled, following it from frame
to frame where that is unambiguous (:func:`_link_anonymous`): the point of the last frame moved
by its velocity (from the two frames before; none after one frame) has exactly one point of
this frame within ``jump_mm``, and none other within twice that; and the last frame's point
had no other point within twice ``jump_mm`` (:func:`_store_anonymous`). A point that continues
an anonymous run is refused to every marker that was observed during the run on a track that
had begun before the run did (``tracks.seen_at``, ``tracks.track_from``: a track goes on while
the marker is observed in every frame, each point near its prediction; :func:`_continue_track`;
:func:`_refuse_anonymous`, on every gate's candidates). A marker whose point reappears starts a
new run; a marker that was lost before the run began may take it; a label that jumped to
another point (the serve arm's labels shifted along the chain, its own points left unlabeled)
starts a new track, so it may go back; a run broken by ambiguity starts again (no refusal):
where following is unsure, nothing changes.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.frame import OBSERVED
from labeler_service.labeling.kernels.spatial import ANY, _alone, _nearest


@njit
def _link_anonymous(points, index, dt, frame_no, scratch, params):
    """``scratch.anon[j]``: the frames in a row point ``j``'s track was unlabeled before this
    frame (0: none, or not followed), ``scratch.avel[j]`` its velocity (mm/s), from the last
    frame's points (:func:`_store_anonymous`) when they were stored the frame before this one.
    Returns how many of this frame's points continue a run (0: nothing to refuse)."""
    n = points.shape[0]
    anon, avel = scratch.anon, scratch.avel
    pprev, pvel, panon = scratch.pprev, scratch.pvel, scratch.panon
    for j in range(n):
        anon[j] = 0
        for a in range(3):
            avel[j, a] = 0.0
    nprev, stored = scratch.pinfo[0], scratch.pinfo[1]
    if nprev == 0 or stored != frame_no - 1 or not dt > 0.0:
        return 0
    r = params.jump_mm
    c = np.empty(3)
    for q in range(nprev):
        if panon[q] <= 0:
            continue
        for a in range(3):
            c[a] = pprev[q, a] + pvel[q, a] * dt
        j, _ = _nearest(points, index, c, r * r, scratch.owner, ANY, -1)
        if j < 0 or not _alone(points, index, c, 2.0 * r, j):
            continue
        if anon[j] != 0:
            anon[j] = -1  # two last-frame points on one: not followed
            continue
        anon[j] = panon[q]
        for a in range(3):
            avel[j, a] = (points[j, a] - pprev[q, a]) / dt
    runs = 0
    for j in range(n):
        if anon[j] < 0:
            anon[j] = 0
            for a in range(3):
                avel[j, a] = 0.0
        elif anon[j] > 0:
            runs += 1
    return runs


@njit
def _store_anonymous(points, index, frame_no, scratch, params):
    """This frame's points for the next frame's :func:`_link_anonymous`: each unlabeled point
    with no other point within twice ``jump_mm`` carries its run (``anon + 1``) and velocity on;
    a labeled or crowded point carries none."""
    n = points.shape[0]
    pprev, pvel, panon = scratch.pprev, scratch.pvel, scratch.panon
    if n > pprev.shape[0]:
        scratch.pinfo[0] = 0
        return
    iso = 2.0 * params.jump_mm
    c = np.empty(3)
    for j in range(n):
        for a in range(3):
            c[a] = points[j, a]
            pprev[j, a] = c[a]
        if scratch.owner[j] < 0 and _alone(points, index, c, iso, j):
            panon[j] = scratch.anon[j] + 1
            for a in range(3):
                pvel[j, a] = scratch.avel[j, a]
        else:
            panon[j] = 0
            for a in range(3):
                pvel[j, a] = 0.0
    scratch.pinfo[0] = n
    scratch.pinfo[1] = frame_no


@njit
def _track_radius(tracks, i, r, jump_mm):
    """How far from its prediction marker ``i``'s track may continue: ``jump_mm``, or twice
    its predicted deviation ``sqrt(P + r)`` when that is wider (a fast limb, a low rate)."""
    return max(jump_mm, 2.0 * np.sqrt(tracks.P[i, 0] + r))


@njit
def _continue_track(i, a, points, frame_no, tracks, r, jump_mm):
    """Marker ``i`` is observed on point ``a`` in frame ``frame_no`` (before its Kalman update,
    ``tracks.age`` counted): ``tracks.seen_at``; ``tracks.track_from`` goes on only when the
    marker was observed in the previous frame and its point lies within
    ``max(jump_mm, 2 sqrt(P + r))`` of its prediction (a label that moved to another point
    starts a new track); a track the labeled frames began (the marker never observed here
    before, or reset) counts from its first of them."""
    x = tracks.x
    if tracks.seen_at[i] < 0 and tracks.age[i] > 1:
        # begun in labeled frames (they set no track): ``age`` (counted) frames ago; before
        # frame 0 when a labeler that labeled no frame yet was seeded (``add_subjects``)
        tracks.track_from[i] = frame_no - tracks.age[i] + 1
    else:
        go_on = tracks.state[i] == OBSERVED
        if go_on:
            lim = _track_radius(tracks, i, r, jump_mm)
            d2 = 0.0
            for k in range(3):
                d = points[a, k] - x[i, k]
                d2 += d * d
            go_on = d2 <= lim * lim
        if not go_on:
            tracks.track_from[i] = frame_no
    tracks.seen_at[i] = frame_no


@njit
def _track_taken(i, points, index, owner, tracks, r, jump_mm):
    """Marker ``i``, observed in the previous frame, has no point in this one: when the point its
    track continues onto (the nearest to its prediction, within ``max(jump_mm, 2 sqrt(P + r))``)
    went to another marker (a repair, an exchange, a contest took it back), the marker was on
    a point not its own, and its track is no evidence against any point (``seen_at`` and
    ``track_from`` forgotten)."""
    lim = _track_radius(tracks, i, r, jump_mm)
    j, _ = _nearest(points, index, tracks.x[i, :3], lim * lim, owner, ANY, -1)
    if j >= 0 and owner[j] >= 0 and owner[j] != i:
        tracks.seen_at[i] = -1
        tracks.track_from[i] = -1


@njit
def _refused(i, j, anon, seen_at, track_from, frame_no):
    """Point ``j`` continues an anonymous run (``anon``) that began while marker ``i`` was on a
    track that had begun before it and went on into it (``tracks.seen_at``,
    ``tracks.track_from``): it is not marker ``i``. Arrays, not ``tracks``: called per gate
    candidate (:func:`.unseen._want`)."""
    run = anon[j]
    start = frame_no - run
    return run > 0 and seen_at[i] >= start and track_from[i] < start


@njit
def _refuse_anonymous(cand, cand_d2, ncand, anon, tracks, frame_no):
    """Drops from each marker's gate candidates (in order) the points that continue an
    anonymous run which began while the marker was on a track that had begun before it and
    went on into it."""
    seen_at, track_from = tracks.seen_at, tracks.track_from
    for i in range(ncand.shape[0]):
        if seen_at[i] < 0:
            continue
        k2 = 0
        for k in range(ncand[i]):
            j = cand[i, k]
            if _refused(i, j, anon, seen_at, track_from, frame_no):
                continue
            cand[i, k2] = j
            cand_d2[i, k2] = cand_d2[i, k]
            k2 += 1
        ncand[i] = k2
