"""3D template check, swap repair, joint re-acquisition and the guarded Eq. 1-2 window
(``kernels/repair.py``, issue 10 class C)."""

from __future__ import annotations

import numpy as np
import pytest
import reference as ref_twin
from labeling.scene import _rot_y, _rot_z, frame_points

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.gating import _gate
from labeler_service.labeling.kernels.params import kernel_params
from labeler_service.labeling.kernels.repair import (
    _fit_template,
    _link_excess,
    _mirrors,
    _pair_check,
    _repair,
    _shape_rms,
)
from labeler_service.labeling.kernels.spatial import _index
from labeler_service.labeling.kernels.state import (
    MAX_BODY,
    NONE,
    new_bodies,
    new_kabsch_scratch,
    new_scratch,
    new_tracks,
)
from labeler_service.labeling.kernels.window import _window_update
from labeler_service.labeling.labeler import Labeler

# a chiral shape: B and C are mirror images across the plane of A, D, E; exchanging the labels
# of B and C keeps every pair distance and mirrors the body
MIRROR = np.array(
    [[0.0, 0.0, 0.0], [40.0, 30.0, 10.0], [40.0, -30.0, 10.0], [80.0, 0.0, 35.0], [20.0, 0.0, 60.0]]
)


def _frame(points) -> np.ndarray:
    """``points`` as a frame's points reach the kernels: float32, as decoded from the wire. The
    tests run the specialization the labeler runs (a float64 frame compiled a twin of
    ``_repair`` only the tests used: ~25 s of a cold cache)."""
    return np.ascontiguousarray(points, dtype=np.float32)


def _rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _work(nc):
    return (
        np.zeros(MAX_BODY, dtype=np.int64),
        np.zeros(max(nc, 1), dtype=np.bool_),
        np.zeros(MAX_BODY, dtype=np.int64),
        np.zeros(MAX_BODY, dtype=np.int64),
        new_kabsch_scratch(),
    )


@pytest.mark.parametrize("trial", range(6))
def test_fit_template_equals_itertools_product(rng, trial):
    n = int(rng.integers(3, 6))
    shape = rng.uniform(-60, 60, (n, 3))
    pose = _rotation(rng)
    # the body's points (some missing, noisy), plus free points (some a mirrored copy)
    seen = rng.random(n) > 0.25
    pts = [shape[k] @ pose.T + 500 + rng.normal(0, 1.0, 3) for k in range(n) if seen[k]]
    pts += [rng.uniform(-60, 60, 3) + 500 for _ in range(int(rng.integers(0, 3)))]
    pts = np.array(rng.permutation(np.array(pts)))
    tol = np.full((n, n), 8.0)
    pos, used, choice, best, kab = _work(len(pts))
    n32 = np.int32(n)  # (a body's size as _repair passes it)
    c, rms = _fit_template(
        n32, shape, tol, pts, len(pts), 6.0, 100000, pos, used, choice, best, kab
    )
    c2, rms2, choice2 = ref_twin.fit_template(shape, tol, pts, 6.0)
    assert c == c2
    if c2 >= 3:
        assert rms == pytest.approx(rms2, abs=1e-6)
        assert ref_twin.shape_rms(shape, pts, best[:n]) == (c, pytest.approx(rms, abs=1e-6))


def test_shape_rms_sees_chirality_distances_do_not(rng):
    pose = _rotation(rng)
    pts = MIRROR @ pose.T + [100.0, 200.0, 900.0]
    kab = new_kabsch_scratch()
    right = np.arange(5)
    mirrored = np.array([0, 2, 1, 3, 4])
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert np.allclose(d, d[np.ix_(mirrored, mirrored)])  # same distances
    c, rms = _shape_rms(MIRROR, pts, right, 5, kab.src, kab.dst, kab.R, kab.t)
    assert (c, rms) == (5, pytest.approx(0.0, abs=1e-6))
    c, rms = _shape_rms(MIRROR, pts, mirrored, 5, kab.src, kab.dst, kab.R, kab.t)
    assert c == 5 and rms > 10.0
    assert ref_twin.shape_rms(MIRROR, pts, mirrored) == (5, pytest.approx(rms, abs=1e-6))


def _one_body_state(config, points, assigned, ref_shape, age=100):
    """Kernel state of one 5-marker body with reference ``ref_shape``; marker ``m`` holds point
    ``assigned[m]``."""
    m = len(ref_shape)
    d0 = np.linalg.norm(ref_shape[:, None] - ref_shape[None], axis=2)
    tracks = new_tracks(np.full(m, 1e6), np.ones(m, dtype=bool), [list(range(m))])
    tracks.x[:, :3] = ref_shape + [100.0, 200.0, 900.0]
    tracks.x[:, 3:] = 0.0
    tracks.age[:] = age
    bodies = new_bodies(m, [list(range(m))], [d0], [np.full((m, m), 1.0)], 20)
    bodies.ref[0, :m] = ref_shape
    bodies.ref_ok[0] = True
    scratch = new_scratch(m, 1, 1, config.K, max(64, len(points)))
    _set_assignment(scratch, points, assigned)
    return tracks, bodies, scratch


def _set_assignment(scratch, points, assigned) -> None:
    """``assigned[m]``: marker ``m``'s row of ``points`` (or ``NONE``), with ``owner`` and
    ``obs`` to match."""
    scratch.assigned[: len(assigned)] = assigned
    scratch.owner[:] = NONE
    for k, a in enumerate(assigned):
        if a >= 0:
            scratch.owner[a] = k
            scratch.obs[k] = points[a]
        else:
            scratch.obs[k] = np.nan


def test_mirrored_assignment_is_repaired_after_repair_frames(rng):
    config = LabelerConfig()
    params = kernel_params(config)
    pts = _frame(MIRROR @ _rotation(rng).T + [100.0, 200.0, 900.0])
    swapped = np.array([0, 2, 1, 3, 4], dtype=np.int32)
    tracks, bodies, scratch = _one_body_state(config, pts, swapped, MIRROR)
    index = _index(pts)
    # tracked for long, the body keeps its points (a deforming body against a stale reference
    # must not be "repaired"), and the mirrored shape does not become its reference
    for frame in range(config.repair_frames + 1):
        assert (
            _repair(pts, index, frame * config.verify_every, tracks, bodies, scratch, params) == 0
        )
    assert list(scratch.assigned[:5]) == list(swapped)
    assert np.allclose(bodies.ref[0, :5], MIRROR)
    tracks.age[1:3] = 3  # B and C were re-acquired 3 frames ago
    for frame in range(config.repair_frames - 1):
        assert _repair(pts, index, frame, tracks, bodies, scratch, params) == 0
        assert list(scratch.assigned[:5]) == list(swapped)  # one check is not enough
        assert not bodies.ok[0]  # the window does not learn it meanwhile
    assert _repair(pts, index, 9, tracks, bodies, scratch, params) == 1
    assert list(scratch.assigned[:5]) == [0, 1, 2, 3, 4]
    assert list(scratch.owner[:5]) == [0, 1, 2, 3, 4]
    assert np.allclose(scratch.obs[:5], pts)
    assert bodies.ok[0]


def test_body_that_only_deformed_keeps_its_points_and_follows_them():
    config = LabelerConfig()
    params = kernel_params(config)
    pts = _frame(MIRROR)
    pts[3] += [0.0, 0.0, 25.0]  # one marker slid 25 mm: no permutation fits better
    tracks, bodies, scratch = _one_body_state(config, pts, np.arange(5, dtype=np.int32), MIRROR)
    tracks.x[:, :3] = pts
    assert _repair(pts, _index(pts), 0, tracks, bodies, scratch, params) == 0
    assert list(scratch.assigned[:5]) == [0, 1, 2, 3, 4]
    assert bodies.ok[0]
    # a 25 mm jump off the trained distances (tolerance 10 mm + 3 deviations) is no drift: the
    # reference keeps the trained shape (a swap must not become the reference, issue 10)
    assert np.allclose(bodies.ref[0, :5], MIRROR)


def test_reference_follows_slow_drift_of_a_body_that_deformed():
    config = LabelerConfig()
    params = kernel_params(config)
    pts = _frame(MIRROR)
    tracks, bodies, scratch = _one_body_state(config, pts, np.arange(5, dtype=np.int32), MIRROR)
    for step in range(5):  # 25 mm in 5 mm steps: each within the tolerance of the last reference
        pts = pts.copy()
        pts[3] += [0.0, 0.0, 5.0]
        tracks.x[:, :3] = pts
        assert _repair(pts, _index(pts), 0, tracks, bodies, scratch, params) == 0
        assert list(scratch.assigned[:5]) == [0, 1, 2, 3, 4]
        assert np.allclose(bodies.ref[0, :5], pts), step  # the new shape is the reference now


def _bent_and_exchanged(rng):
    """A 5-marker body whose fifth marker slid 30 mm while the body was hidden (skin), back with
    B and C exchanged: every map of all five misses the reference by more than
    ``repair_check_mm``, the right map of the other four fits it exactly."""
    pts = _frame(MIRROR @ _rotation(rng).T + [100.0, 200.0, 900.0])
    pts[4] += np.array([30.0, 0.0, 0.0], dtype=np.float32) @ _rotation(rng).T.astype(np.float32)
    swapped = np.array([0, 2, 1, 3, 4], dtype=np.int32)
    return pts, swapped


def test_exchange_in_a_body_that_also_bent_is_repaired_by_the_members_that_fit(rng):
    config = LabelerConfig()
    params = kernel_params(config)
    pts, swapped = _bent_and_exchanged(rng)
    tracks, bodies, scratch = _one_body_state(config, pts, swapped, MIRROR)
    tracks.age[1:3] = 3  # B and C were re-acquired 3 frames ago; E was tracked throughout
    index = _index(pts)
    for frame in range(config.repair_frames - 1):
        assert _repair(pts, index, frame, tracks, bodies, scratch, params) == 0
        assert list(scratch.assigned[:5]) == list(swapped)
    assert _repair(pts, index, 9, tracks, bodies, scratch, params) == 1
    # B and C take their points back; E, which the map of four leaves out, keeps its own
    assert list(scratch.assigned[:5]) == [0, 1, 2, 3, 4]
    assert list(scratch.owner[:5]) == [0, 1, 2, 3, 4]
    assert np.allclose(scratch.obs[:5], pts)


def test_a_map_of_fewer_members_never_moves_a_member_tracked_for_long(rng):
    config = LabelerConfig()
    params = kernel_params(config)
    pts, swapped = _bent_and_exchanged(rng)
    tracks, bodies, scratch = _one_body_state(config, pts, swapped, MIRROR)
    tracks.age[2] = 3  # only C was re-acquired: B, tracked for long, keeps its point
    index = _index(pts)
    for frame in range(config.repair_frames + 2):
        assert _repair(pts, index, frame, tracks, bodies, scratch, params) == 0
    assert list(scratch.assigned[:5]) == list(swapped)


def test_joint_reacquisition_assigns_returning_points_together(rng):
    config = LabelerConfig()
    params = kernel_params(config)
    pose = _rotation(rng)
    body = MIRROR @ pose.T + [100.0, 200.0, 900.0]
    # four of the five markers are back, shuffled, with a distractor 70 mm from the fifth's
    # place; the stale predictions sit 40 mm off (a triangle has no chirality: with three
    # points of a mirror-symmetric body the map is ambiguous, with four it is not)
    pts = _frame([body[3], body[1], body[4], body[2] + [0.0, 0.0, 70.0], body[0]])
    tracks, bodies, scratch = _one_body_state(config, pts, np.full(5, NONE, np.int32), MIRROR)
    tracks.x[:, :3] = body + [40.0, 0.0, 0.0]
    assert _repair(pts, _index(pts), 0, tracks, bodies, scratch, params) == 1
    assert list(scratch.assigned[:5]) == [4, 1, NONE, 0, 2]
    assert scratch.owner[3] == NONE


def test_guarded_window_does_not_learn_a_failed_body_and_drift_is_bounded():
    m = 3
    shape = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 80.0, 0.0]])
    d0 = np.linalg.norm(shape[:, None] - shape[None], axis=2)
    bodies = new_bodies(m, [[0, 1, 2]], [d0], [np.full((3, 3), 1.0)], 4)
    wrong = shape[[1, 0, 2]]  # a swapped assignment: link 0-2 is 94 mm instead of 80
    bodies.ok[0] = False
    for ptr in range(4):
        _window_update(bodies, wrong, ptr, 1, True, 0.0)
    assert np.all(bodies.cnt[0, :3, :3] == 0)
    assert bodies.D[0, 0, 2] == pytest.approx(80.0)  # the trained value
    bodies.ok[0] = True
    for ptr in range(4):
        _window_update(bodies, wrong, ptr, 1, True, 5.0)
    assert bodies.D[0, 0, 2] == pytest.approx(85.0)  # learned, within 5 mm of the template
    for ptr in range(4):
        _window_update(bodies, wrong, ptr, 1, False, 0.0)
    assert bodies.D[0, 0, 2] == pytest.approx(np.hypot(50.0, 80.0), rel=1e-6)  # unguarded


def _cluster_scene(rng, frames, rate):
    """One subject: a trunk of four markers and a forearm-like plate of five markers 25-60 mm
    apart (near-symmetric), the plate swinging about an elbow."""
    t = np.arange(frames) / rate
    trunk = rng.uniform(-80, 80, (4, 3)) + [0, 0, 100]
    plate = MIRROR * 0.8 + [0.0, 0.0, 250.0] + rng.normal(0, 2.0, (5, 3))
    centre = np.stack([80 * np.sin(0.5 * t), 60 * np.cos(0.4 * t), 1000 + 0 * t], axis=1)
    r_a = _rot_z(0.5 * np.sin(2 * np.pi * 0.2 * t))
    r_b = r_a @ _rot_y(0.6 + 0.5 * np.sin(2 * np.pi * 0.35 * t))
    pa = centre[:, None] + np.einsum("fij,mj->fmi", r_a, trunk)
    pb = centre[:, None] + np.einsum("fij,mj->fmi", r_b, plate)
    pos = np.concatenate([pa, pb], axis=1).astype(np.float32)
    pos += rng.normal(0, 0.3, pos.shape).astype(np.float32)
    names = tuple([f"S:t{i}" for i in range(4)] + [f"S:p{i}" for i in range(5)])
    return pos, names


def test_occluded_cluster_returning_one_marker_at_a_time_is_labeled_correctly(rng):
    rate, frames, init = 100.0, 400, 40
    pos, names = _cluster_scene(rng, frames, rate)
    plate = list(range(4, 9))
    hidden = np.zeros(pos.shape[:2], dtype=bool)
    hidden[100:130][:, plate] = True
    for k, m in enumerate(plate):  # back one at a time, two frames apart
        hidden[130 : 130 + 2 * k, m] = True
    lab = Labeler(names, rate)
    last_back = 130 + 2 * (len(plate) - 1)
    wrong_after = 0
    for f in range(frames):
        pts, truth = frame_points(rng, pos[f], hidden[f])
        out = lab.process(pts, f / rate, truth if f < init else None)
        if f >= last_back + 4:
            wrong_after += int(np.count_nonzero(out.point_labels != truth))
    assert wrong_after == 0


def test_gone_matches_twin(rng):
    from labeler_service.labeling.kernels.step import _gone

    groups = [[0, 1, 2], [3, 4], [5, 6, 7, 8]]
    active = rng.random(9) > 0.2
    tracks = new_tracks(np.full(9, 1e6), active, groups)
    for _ in range(5):
        tracks.lost[:] = rng.integers(0, 120, 9)
        tracks.lost[5:] = rng.integers(55, 70, 4)
        _gone(tracks, 60)
        assert list(tracks.gone) == list(ref_twin.gone(tracks.lost, active, groups, 60))


def test_a_subject_who_left_keeps_no_label_on_the_others(rng):
    from labeling.scene import articulated

    pos, names = articulated(rng, subjects=3, frames=500)
    left = [i for i, n in enumerate(names) if n.startswith("P0:")]
    hidden = np.zeros(pos.shape[:2], dtype=bool)
    hidden[150:, left] = True  # P0 walks out at frame 150
    lab = Labeler(names, 120.0)
    taken = 0
    for f in range(pos.shape[0]):
        pts, truth = frame_points(rng, pos[f], hidden[f])
        out = lab.process(pts, f / 120.0, truth if f < 40 else None)
        if f >= 150 + LabelerConfig().absent_frames:
            taken += int(np.isin(out.point_labels, left).sum())
    assert taken == 0


# a forearm seen from two triangles (the dance take of issue 10): radius R and ulna U 83 mm
# apart, a finger F 159 / 108 mm from them, the elbow E 272 / 265 mm from them. Each body has
# three members, so no body shows chirality and the template repair leaves them alone; the
# trained distances to the long-tracked F and E tell R from U.
FOREARM = np.array(
    [[-260.0, 64.1, 47.7], [0.0, 0.0, 0.0], [0.0, 83.0, 0.0], [95.0, 122.8, 33.5]]
)  # E, R, U, F
FOREARM_BODIES = [[1, 2, 3], [0, 1, 2]]


def _forearm_state(config, points, assigned, young=(1, 2)):
    m = len(FOREARM)
    d0 = [np.linalg.norm(FOREARM[b][:, None] - FOREARM[b][None], axis=2) for b in FOREARM_BODIES]
    tracks = new_tracks(np.full(m, 1e6), np.ones(m, dtype=bool), [list(range(m))])
    tracks.x[:, :3] = FOREARM
    tracks.age[:] = 100
    tracks.age[list(young)] = 3  # re-acquired 3 frames ago
    a0 = [np.full((3, 3), 1.0) for _ in FOREARM_BODIES]
    bodies = new_bodies(m, FOREARM_BODIES, d0, a0, 20)
    scratch = new_scratch(m, len(FOREARM_BODIES), 1, config.K, 64)
    _set_assignment(scratch, points, assigned)
    return tracks, bodies, scratch


def _forearm_points(rng):
    return _frame(FOREARM @ _rotation(rng).T + [300.0, -100.0, 1100.0] + rng.normal(0, 0.5, (4, 3)))


@pytest.mark.parametrize("trial", range(4))
def test_pair_check_undoes_a_swap_inside_triangles(rng, trial):
    pts = _forearm_points(rng)
    swapped = np.array([0, 2, 1, 3], dtype=np.int32)  # R on U's point, U on R's
    without = kernel_params(LabelerConfig(repair_pairs=False))
    tracks, bodies, scratch = _forearm_state(LabelerConfig(), pts, swapped)
    # the template repair cannot see it: three points have no chirality
    assert _repair(pts, _index(pts), 1, tracks, bodies, scratch, without) == 0
    assert list(scratch.assigned[:4]) == [0, 2, 1, 3]
    params = kernel_params(LabelerConfig())
    assert _repair(pts, _index(pts), 1, tracks, bodies, scratch, params) == 1
    assert list(scratch.assigned[:4]) == [0, 1, 2, 3]
    assert list(scratch.owner[:4]) == [0, 1, 2, 3]
    assert np.allclose(scratch.obs[:4], pts)
    # the right assignment is left alone
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0


def test_pair_check_gives_a_point_to_the_missing_partner_it_fits(rng):
    pts = _forearm_points(rng)
    taken = np.array([0, NONE, 1, 3], dtype=np.int32)  # U took R's point, R is missing
    params = kernel_params(LabelerConfig())
    tracks, bodies, scratch = _forearm_state(LabelerConfig(), pts, taken)
    assert _pair_check(pts, tracks, bodies, scratch, params) == 1
    assert list(scratch.assigned[:4]) == [0, 1, NONE, 3]
    assert scratch.owner[1] == 1 and scratch.owner[2] == NONE
    assert np.isnan(scratch.obs[2]).all()


def test_pair_check_leaves_tracked_markers_and_bending_bodies_alone(rng):
    pts = _forearm_points(rng)
    swapped = np.array([0, 2, 1, 3], dtype=np.int32)
    params = kernel_params(LabelerConfig())
    # R and U tracked for long: not a re-acquisition, the pair check does not look
    tracks, bodies, scratch = _forearm_state(LabelerConfig(), pts, swapped, young=())
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    # only R re-acquired: U, tracked for long, keeps its point (its track says so)
    tracks, bodies, scratch = _forearm_state(LabelerConfig(), pts, swapped, young=(1,))
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    # both bodies bend in the sliding window (a body trained across a joint held still): their
    # trained distances are no evidence
    tracks, bodies, scratch = _forearm_state(LabelerConfig(), pts, swapped)
    bodies.A[:2, :3, :3] = 40.0
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    assert list(scratch.assigned[:4]) == [0, 2, 1, 3]


PELVIS = np.array([[-150.0, 300.0, -400.0]])  # where :func:`limb`'s window held the pelvis


def limb(rng, config, assigned):
    """The tennis hand of issue 10, trained on a window held still: the only body holding the
    finger F and the wrist pair R, U also holds a pelvis marker P, whose links to the hand bend
    in the window once the arm moves (the pelvis is elsewhere now); the elbow triangle E, R, U.
    ``(points, tracks, bodies, scratch)`` with marker ``m`` on point ``assigned[m]``; every
    marker observed before (its Kalman state set), for 100 frames."""
    shape = np.vstack([FOREARM, PELVIS])  # E, R, U, F, P
    lists = [[1, 2, 3, 4], [0, 1, 2]]
    d0 = [np.linalg.norm(shape[b][:, None] - shape[b][None], axis=2) for b in lists]
    a0 = [np.full((len(b), len(b)), 1.0) for b in lists]
    pts = FOREARM @ _rotation(rng).T + [300.0, -100.0, 1100.0] + rng.normal(0, 0.5, (4, 3))
    pts = _frame(np.vstack([pts, [[0.0, 900.0, 600.0]]]))  # the pelvis elsewhere now
    tracks = new_tracks(np.full(5, 1e6), np.ones(5, dtype=bool), [list(range(5))])
    tracks.x[:, :3] = shape
    tracks.age[:] = 100
    bodies = new_bodies(5, lists, d0, a0, 20)
    bodies.A[0, 3, :3] = bodies.A[0, :3, 3] = 40.0  # every link to P bends in the window
    scratch = new_scratch(5, len(lists), 1, config.K, 64)
    _set_assignment(scratch, pts, np.asarray(assigned, dtype=np.int32))
    return pts, tracks, bodies, scratch


def test_pair_check_keeps_the_rigid_links_of_a_body_that_bends(rng):
    # R took U's point and U is missing. The elbow's links (272 / 265 mm) cannot tell R from U;
    # F's (159 / 108 mm) can, inside the body that bends elsewhere.
    config = LabelerConfig()
    assigned = np.array([0, 2, NONE, 3, 4], dtype=np.int32)
    pts, tracks, bodies, scratch = limb(rng, config, assigned)
    tracks.age[1] = 3  # R re-acquired 3 frames ago (on U's point)
    params = kernel_params(config)
    assert _pair_check(pts, tracks, bodies, scratch, params) == 1
    assert list(scratch.assigned[:5]) == [0, NONE, 2, 3, 4]  # U's point back to U
    # with F's links bending too, no link tells R from U: nothing moves
    _set_assignment(scratch, pts, assigned)
    bodies.A[0, :4, :4] = 40.0
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    assert list(scratch.assigned[:5]) == list(assigned)


def _limb_state(config, rng, anchor_age):
    """:func:`limb` with R on U's point, re-acquired 1 frame ago, U missing, and E, F, P
    observed ``anchor_age`` frames."""
    pts, tracks, bodies, scratch = limb(rng, config, [0, 2, NONE, 3, 4])
    tracks.age[:] = anchor_age
    tracks.age[1] = 1
    return pts, tracks, bodies, scratch


def test_senior_anchors_undo_a_limb_reacquired_whole_after_two_frames(rng):
    # the tennis serve (issue 10): the whole arm was lost in the fast swing and came back; its
    # markers were re-acquired a few frames apart, none is tracked for repair_age frames yet
    config = LabelerConfig()
    assert config.repair_senior_frames == 3
    assert config.repair_age > 8
    pts, tracks, bodies, scratch = _limb_state(config, rng, anchor_age=8)
    off = kernel_params(LabelerConfig(repair_senior_frames=0))
    assert _pair_check(pts, tracks, bodies, scratch, off) == 0  # no long-tracked anchor
    params = kernel_params(config)
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0  # asked once: it waits
    assert tracks.pair_wait[1] == 2
    assert list(scratch.assigned[:5]) == [0, 2, NONE, 3, 4]
    assert _pair_check(pts, tracks, bodies, scratch, params) == 1  # asked again: made
    assert list(scratch.assigned[:5]) == [0, NONE, 2, 3, 4]
    assert tracks.pair_wait[1] == -1


def test_senior_anchors_need_to_be_older_than_the_marker_and_ask_twice_in_a_row(rng):
    config = LabelerConfig()
    params = kernel_params(config)
    # anchors observed only 3 frames, the marker 1: not senior enough (1 + 3 > 3)
    pts, tracks, bodies, scratch = _limb_state(config, rng, anchor_age=3)
    for _ in range(3):
        assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    assert list(scratch.assigned[:5]) == [0, 2, NONE, 3, 4]
    # asked once, then not (R back on its own point): the wait is cleared
    pts, tracks, bodies, scratch = _limb_state(config, rng, anchor_age=8)
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    assert tracks.pair_wait[1] == 2
    _set_assignment(scratch, pts, np.array([0, 1, NONE, 3, 4], dtype=np.int32))
    assert _pair_check(pts, tracks, bodies, scratch, params) == 0
    assert tracks.pair_wait[1] == -1


@pytest.mark.parametrize("trial", range(6))
def test_link_excess_matches_twin(rng, trial):
    m_total = 6
    body_lists = [[0, 1, 2, 3], [1, 4, 5], [2, 3, 4]]
    shape = rng.uniform(-100, 100, (m_total, 3))
    d0 = [np.linalg.norm(shape[b][:, None] - shape[b][None], axis=2) for b in body_lists]
    a0 = [rng.uniform(0.2, 4.0, (len(b), len(b))) for b in body_lists]
    a0 = [(a + a.T) / 2 for a in a0]
    bodies = new_bodies(m_total, body_lists, d0, a0, 20)
    window_a = [a * rng.choice([1.0, 5.0], size=a.shape, p=[0.8, 0.2]) for a in a0]
    window_a[0][0, 1] = window_a[0][1, 0] = 50.0  # one link bends: the body's others still count
    for b, body in enumerate(body_lists):
        k = len(body)
        bodies.A[b, :k, :k] = (window_a[b] + window_a[b].T) / 2
        window_a[b] = bodies.A[b, :k, :k].copy()
    pts = shape + rng.normal(0, 6.0, shape.shape)
    assigned = rng.permutation(m_total).astype(np.int32)
    assigned[rng.random(m_total) < 0.2] = NONE
    age = rng.integers(0, 60, m_total)
    age[[0, 3]] = 40  # anchors of marker 2 inside the body that bends
    for m in range(m_total):
        for p in range(m_total):
            skip = int(rng.integers(-1, m_total))
            got = _link_excess(m, p, skip, pts, bodies, assigned, age, 30, 2.0, 0.02)
            want = ref_twin.link_excess(
                m, p, skip, pts, body_lists, d0, a0, window_a, assigned, age, 30, 2.0, 0.02
            )
            assert got[1] == want[1]
            assert got[0] == pytest.approx(want[0], abs=1e-9)


def test_pair_check_refuses_an_exchange_that_mirrors_a_body(rng):
    config = LabelerConfig()
    pts = _frame(MIRROR @ _rotation(rng).T + [100.0, 200.0, 900.0])
    right = np.arange(5, dtype=np.int32)
    tracks, bodies, scratch = _one_body_state(config, pts, right, MIRROR)
    kab = scratch.kab
    # B and C exchanging points keeps every distance (what the pair check sees) but mirrors
    # the body: its 5-point template refuses it; the exchange back from the mirror is allowed
    # (marker and point indices typed as _repair passes them)
    m, pm, m2, pm2 = 1, *np.array([2, 2, 1], dtype=np.int32)
    assert _mirrors(bodies, pts, scratch.assigned, m, pm, m2, pm2, config.repair_check_mm, kab)
    swapped = np.array([0, 2, 1, 3, 4], dtype=np.int32)
    pm, m2, pm2 = np.array([1, 2, 2], dtype=np.int32)
    assert not _mirrors(bodies, pts, swapped, m, pm, m2, pm2, config.repair_check_mm, kab)


@pytest.mark.realdata
@pytest.mark.slow
def test_dance_forearm_swap_after_occlusion_is_undone(real_path):
    """The cross-take matrix's tune05 ``occlude2`` cell (60 Hz): the dancer's radius and ulna
    markers, in triangle bodies only, came back exchanged after an occlusion and stayed so for
    215 frames (issue 10: no swap above 30 frames at 60 Hz and more)."""
    from labeler_service.evaluation.scoring import evaluate
    from labeler_service.scenes.compose import TakeSpec, compose_scene

    takes = [
        TakeSpec(path=real_path("dance_qualisys_28markers_60hz.c3d"), start=120),
        TakeSpec(path=real_path("clinical_gait_pig_35markers_100hz.c3d")),
    ]
    scene = compose_scene(takes, radius=350.0, frames=480, seed=105, rate=60.0)
    report, _ = evaluate(scene, ["online"], init_frames=24, seed=105, occlude=2, occlude_frames=18)
    assert report["max_swap_frames"] <= 30


@pytest.mark.realdata
@pytest.mark.slow
def test_dance_toes_hidden_together_come_back_in_place(real_path):
    """The cross-take matrix's tune09 ``occlude2`` cell (60 Hz, the labeled start's window
    model): the dancer's left big toe and little toe were hidden together; their only rigid
    partner of their own body is each other (the ankle, in the same trained body, moved
    against them in the window). Trilateration that counted only rigid partners of the
    marker's own body as its own evidence left both out of the completion when they came
    back; the inner labeler then read one on the other's point and the two stayed exchanged
    for 387 frames. Any placed marker of the marker's trained body (the ankle) is its own
    evidence (``boot_match._grow``)."""
    from labeler_service.evaluation.scoring import evaluate
    from labeler_service.scenes.compose import TakeSpec, compose_scene

    takes = [
        TakeSpec(path=real_path("kneel_to_prone_62markers_240hz.c3d"), start=960),
        TakeSpec(path=real_path("dance_qualisys_28markers_60hz.c3d"), start=240),
    ]
    scene = compose_scene(takes, radius=220.0, frames=480, seed=109, rate=60.0)
    report, _ = evaluate(scene, ["online"], init_frames=24, seed=109, occlude=2, occlude_frames=18)
    assert report["max_swap_frames"] <= 30  # (387 with rigid partners only, 0 now)


SCALENE = np.array([[0.0, 0.0, 0.0], [140.0, 0.0, 0.0], [100.0, 70.0, 0.0]])  # sides 140, 122, 81
ISOSCELES = np.array([[0.0, 0.0, 0.0], [120.0, 0.0, 0.0], [60.0, 90.0, 0.0]])  # sides 120, 108, 108


def _three_point_case(rng, shape, held, model_ref=True):
    """A 3-marker body at a random pose, its three points shuffled; marker ``k`` holds point
    ``held[k]`` (-1 none), every marker re-acquired a frame ago (a booted subject)."""
    config = LabelerConfig()
    body = shape @ _rotation(rng).T + [100.0, 200.0, 900.0]
    order = np.array([2, 0, 1])  # point i is marker order[i]
    pts = _frame(body[order])
    tracks, bodies, scratch = _one_body_state(config, pts, np.array(held, np.int32), shape, age=1)
    bodies.ref_model[0] = model_ref
    tracks.x[:, :3] = body + [40.0, 0.0, 0.0]
    changes = _repair(pts, _index(pts), 0, tracks, bodies, scratch, kernel_params(config))
    return changes, list(scratch.assigned[:3])


def test_a_body_never_seen_whole_is_read_from_three_points_that_name_themselves(rng):
    # marker 1 holds marker 0's point (point 1), markers 0 and 2 are missing: the three points
    # of a scalene triangle name their corners, whatever the held label said
    assert _three_point_case(rng, SCALENE, [NONE, 1, NONE]) == (1, [1, 2, 0])
    # a reference from the stream (the body was seen whole) leaves three points to Eq. 5
    assert _three_point_case(rng, SCALENE, [NONE, 1, NONE], model_ref=False) == (
        0,
        [NONE, 1, NONE],
    )


def test_three_points_do_not_read_again_two_held_points_or_an_isosceles_body(rng):
    # two held points that fit each other are evidence: a third point does not overturn them
    # (a ghost beside a heel and a toe read the foot turned round, walk-4 booted)
    assert _three_point_case(rng, SCALENE, [NONE, 1, 0]) == (0, [NONE, 1, 0])
    # an isosceles triangle fits its own mirror permutation: its points do not name themselves
    assert _three_point_case(rng, ISOSCELES, [NONE, 1, NONE]) == (0, [NONE, 1, NONE])


def _held_apart_case(rng, gate_mm):
    """A booted 3-marker body (scalene, a model's reference): marker 0 holds its own point 90
    mm beside three free points that fit the body's shape, markers 1 and 2 are missing; the
    frame's gates (``_gate``) have radius ``gate_mm``. The held point is the frame's last row
    (rows are not members). Returns ``(changes, assigned)``."""
    config = LabelerConfig()
    params = kernel_params(config)
    body = SCALENE @ _rotation(rng).T + [100.0, 200.0, 900.0]
    held = body[0] + [0.0, 0.0, 90.0]  # marker 0's own point, beside the triangle
    pts = _frame(np.vstack([body[[2, 0, 1]], held]))
    tracks, bodies, scratch = _one_body_state(
        config, pts, np.array([3, NONE, NONE], np.int32), SCALENE, age=1
    )
    bodies.ref_model[0] = True
    tracks.x[:, :3] = body
    tracks.x[0, :3] = held  # tracked where its point is
    scratch.s[:] = gate_mm**2 / params.gate_chi2
    index = _index(pts)
    _gate(
        tracks.x, scratch.s, tracks.active, pts, index, params.gate_chi2, params.K,
        scratch.cand, scratch.cand_d2, scratch.ncand,
    )  # fmt: skip
    changes = _repair(pts, index, 0, tracks, bodies, scratch, params)
    return changes, list(scratch.assigned[:3])


def test_three_points_do_not_take_a_held_marker_off_its_own_point(rng):
    """A booted jumper's right shoulder, tracked on its own point since the boot, was moved
    476 mm onto a neighbour's neck marker: its body's other two members were missing, and three
    free points (the neck and two of the jumper's own) happened to fit the body's shape. Three
    points name themselves, a held one among them; a map that leaves a point alone in its
    marker's gate for others is no reading of what the body holds (holdout21 ``rate`` from a
    model: the jumper's upper body read wrong for the whole scene, never booted)."""
    assert _held_apart_case(rng, 30.0) == (0, [3, NONE, NONE])


def test_three_points_overturn_a_held_point_its_gate_shared(rng):
    # a gate that holds the triangle's points too (12.5 Hz) leaves the held one in doubt: the
    # three points are read, and the held point is left
    changes, assigned = _held_apart_case(rng, 250.0)
    assert changes == 1 and sorted(assigned) == [0, 1, 2]
