"""A lost marker follows its own point (``kernels/follow.py``, ``acquire_follow``): a toe whose
point left its gate in a landing's deceleration (tune18 ``rate``: ``Viktor:RTOE`` unlabeled for
44 frames, its third link bending at the ankle) takes back the point it went on as, where two
links that hold leave a circle of places and the lost rules need three."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.test_unseen_markers import _lost_limb

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.follow import _acquire_followed, _follow_update
from labeler_service.labeling.kernels.params import V0, kernel_params
from labeler_service.labeling.kernels.spatial import _index
from labeler_service.labeling.kernels.state import NONE

DT = 1.0 / 50.0
V = np.array([-400.0, 150.0, 0.0])  # the followed point's velocity, mm/s


def _followed_limb(rng, *, bend_f: bool = True, frames: int = 3):
    """:func:`_lost_limb`: the wrist R lost 3 frames, its point (1) free; with ``bend_f`` its
    link to the finger F bends too, so two links hold (to the elbow E and to U). R's own point
    was followed ``frames`` frames, last at its place now less one frame of ``V``."""
    pts, tracks, bodies, scratch = _lost_limb(3, rng)
    if bend_f:
        bodies.A[0, 0, 2] = bodies.A[0, 2, 0] = 40.0
    tracks.fol[1, 6] = frames
    tracks.fol[1, :3] = pts[1] - V * DT
    tracks.fol[1, 3:6] = V
    return pts, tracks, bodies, scratch


def _take_back(pts, tracks, bodies, scratch) -> int:
    params = kernel_params(LabelerConfig())
    return _acquire_followed(pts, _index(pts), DT, 100, tracks, bodies, scratch, params)


def test_a_lost_marker_takes_back_the_point_it_followed_on_two_links_that_hold(rng):
    config = LabelerConfig()
    assert config.acquire_follow
    pts, tracks, bodies, scratch = _followed_limb(rng)
    assert _take_back(pts, tracks, bodies, scratch) == 1
    assert scratch.assigned[1] == 1 and scratch.owner[1] == 1
    assert np.allclose(scratch.obs[1], pts[1])
    # a new track on the point, moving as the point was followed moving
    assert np.allclose(tracks.x[1, :3], pts[1]) and np.allclose(tracks.x[1, 3:], V)
    assert tuple(tracks.P[1]) == pytest.approx((config.measurement_noise_mm**2, 0.0, V0))


def test_without_a_followed_point_two_links_place_nothing(rng):
    pts, tracks, bodies, scratch = _followed_limb(rng)
    tracks.fol[1, 6] = 0
    assert _take_back(pts, tracks, bodies, scratch) == 0
    assert scratch.assigned[1] == NONE


def test_a_followed_point_needs_two_links_that_hold_and_no_refusal(rng):
    # the elbow's link alone holds (U's and F's bend): a sphere of places, nothing taken
    pts, tracks, bodies, scratch = _followed_limb(rng)
    bodies.A[:, :, :] = 40.0
    bodies.A[1, 0, 1] = bodies.A[1, 1, 0] = 1.0
    assert _take_back(pts, tracks, bodies, scratch) == 0
    # U's link alone holds (E's bends too): U is in both of R's bodies, still one anchor and a
    # sphere of places (counted once per body, it made two)
    pts, tracks, bodies, scratch = _followed_limb(rng)
    bodies.A[1, 0, 1] = bodies.A[1, 1, 0] = 40.0
    assert _take_back(pts, tracks, bodies, scratch) == 0
    # the point is off the trained distances (it is not the wrist's)
    pts, tracks, bodies, scratch = _followed_limb(rng)
    pts[1] += np.float32([0.0, 0.0, 30.0])
    tracks.fol[1, :3] = pts[1] - V * DT
    assert _take_back(pts, tracks, bodies, scratch) == 0
    # an anonymous run seen beside the marker while it was on a track of its own refuses it
    pts, tracks, bodies, scratch = _followed_limb(rng)
    scratch.anon[1] = 20
    tracks.seen_at[1], tracks.track_from[1] = 90, 10
    assert _take_back(pts, tracks, bodies, scratch) == 0


def test_the_followed_point_must_be_alone_and_free(rng):
    floor = LabelerConfig().min_gate_mm
    # a second point within twice the gate floor of where the followed point should be
    pts, tracks, bodies, scratch = _followed_limb(rng)
    pts = np.vstack([pts, pts[1] + np.float32([1.5 * floor, 0.0, 0.0])])
    scratch.owner[pts.shape[0] - 1] = NONE
    assert _take_back(pts, tracks, bodies, scratch) == 0
    # the point went to another marker this frame
    pts, tracks, bodies, scratch = _followed_limb(rng)
    scratch.owner[1] = 3
    assert _take_back(pts, tracks, bodies, scratch) == 0
    # it moved farther than the gate floor from where its velocity put it
    pts, tracks, bodies, scratch = _followed_limb(rng)
    tracks.fol[1, :3] = pts[1] - V * DT - np.float32([1.2 * floor, 0.0, 0.0])
    assert _take_back(pts, tracks, bodies, scratch) == 0


def _update(pts, owner, tracks) -> None:
    params = kernel_params(LabelerConfig())
    _follow_update(1, pts, _index(pts), DT, owner, tracks, params)


def test_following_starts_where_the_marker_lost_its_point_and_stops_when_unsure(rng):
    floor = LabelerConfig().min_gate_mm
    pts, tracks, _, scratch = _followed_limb(rng, frames=0)
    owner = np.full(pts.shape[0], NONE, dtype=np.int64)
    last = pts[1].astype(np.float64) - V * DT
    # observed in the previous frame at ``last``; predicted 1.5 gate floors off its point now
    tracks.age[1], tracks.pos[1] = 1, last
    tracks.kx[1] = pts[1] + [1.5 * floor, 0.0, 0.0]
    _update(pts, owner, tracks)
    assert tracks.fol[1, 6] == 1 and np.allclose(tracks.fol[1, :3], pts[1])
    assert np.allclose(tracks.fol[1, 3:6], V, atol=1e-3)
    # the next frame: the point went on by its velocity
    tracks.age[1] = 0
    nxt = pts.copy()
    nxt[1] = pts[1] + V * DT
    _update(nxt, owner, tracks)
    assert tracks.fol[1, 6] == 2 and np.allclose(tracks.fol[1, :3], nxt[1])
    # then another point beside it: ambiguous, following stops
    amb = np.vstack([nxt, nxt[1] + V * DT + [0.0, 1.2 * floor, 0.0]])
    amb[1] = nxt[1] + V * DT
    _update(amb, np.full(amb.shape[0], NONE, dtype=np.int64), tracks)
    assert tracks.fol[1, 6] == 0
    # no start on a point another marker holds, nor beyond twice the gate floor
    pts, tracks, _, _ = _followed_limb(rng, frames=0)
    tracks.age[1], tracks.pos[1] = 1, last
    tracks.kx[1] = pts[1]
    taken = owner.copy()
    taken[1] = 3
    _update(pts, taken, tracks)
    assert tracks.fol[1, 6] == 0
    tracks.kx[1] = pts[1] + [2.2 * floor, 0.0, 0.0]
    _update(pts, owner, tracks)
    assert tracks.fol[1, 6] == 0
    # a point another marker follows already (two neighbours lost in one frame, one point)
    pts, tracks, _, _ = _followed_limb(rng, frames=0)
    tracks.age[1], tracks.pos[1] = 1, last
    tracks.kx[1] = pts[1]
    tracks.fol[3, 6], tracks.fol[3, :3] = 2, pts[1]
    _update(pts, owner, tracks)
    assert tracks.fol[1, 6] == 0
    # a marker whose subject left follows nothing
    pts, tracks, _, _ = _followed_limb(rng)
    tracks.gone[1] = True
    nxt = pts.copy()
    nxt[1] = pts[1] + V * DT
    _update(nxt, owner, tracks)
    assert tracks.fol[1, 6] == 0
    # a marker lost before the previous frame does not start following
    pts, tracks, _, _ = _followed_limb(rng, frames=0)
    tracks.age[1] = 0
    tracks.kx[1] = pts[1]
    _update(pts, owner, tracks)
    assert tracks.fol[1, 6] == 0
