"""A labeler started from a model (``Labeler.from_model``) places a marker its labeled frames
never showed by its bodies' trained shapes (``kernels/unseen.py``, ``acquire_unseen``): without
a Kalman state or a recovery snapshot it was never labeled (the service's ``boot = false``
start from one labeled frame)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.params import V0
from labeler_service.labeling.labeler import Labeler

LABELED = 12
PARTNER = {"P2:LFRM": "P2:LWRA", "P2:LKNE": "P2:LTIB", "P2:LANK": "P2:LHEE"}
HIDDEN = 60  # frames the marker is hidden at the start (0.5 s at 120 Hz)


def _labeled_share(marker: str, acquire: bool, decoy_mm: float | None = None) -> tuple[float, int]:
    """The share of the marker's visible frames (from 5 frames after it appears) in which its
    own point carries its label, and the frames its label sat on another point. ``decoy_mm``:
    a free point that far from the marker towards its first body partner, in every frame after
    the labeled ones (off the marker's trained distances; off its circle of places)."""
    model, cap = split_walk(3, 6.0, seed=5, rate=120.0)
    lab = Labeler.from_model(model, cap.rate, LabelerConfig(acquire_unseen=acquire))
    col = {n: i for i, n in enumerate(cap.labels)}
    g = np.array([col[n] for n in model.marker_names])
    k = model.marker_names.index(marker)
    partner = model.marker_names.index(PARTNER[marker])
    pos = cap.positions[:, g].copy()
    pos[:HIDDEN, k] = np.nan
    rng = np.random.default_rng(0)
    good = seen = wrong = 0
    for f in range(cap.n_frames):
        idx = np.flatnonzero(np.isfinite(pos[f, :, 0]))
        idx = idx[rng.permutation(idx.size)]
        given = idx.astype(np.int32) if f < LABELED else None
        pts = pos[f, idx].astype(np.float32)
        if decoy_mm is not None and f >= LABELED:
            here = cap.positions[f, g[k]]
            toward = cap.positions[f, g[partner]] - here
            decoy = here + decoy_mm * toward / np.linalg.norm(toward)
            pts = np.concatenate([pts, decoy[None].astype(np.float32)])
        out = lab.process(pts, f / cap.rate, given)
        out_labels = out.point_labels[: idx.size]
        if f >= HIDDEN + 5 and k in idx:
            seen += 1
            good += int(out_labels[np.flatnonzero(idx == k)[0]] == k)
        wrong += int(np.any(out.point_labels == k) and not np.any((out_labels == k) & (idx == k)))
    return good / max(seen, 1), wrong


@pytest.mark.parametrize("marker", ["P2:LKNE", "P2:LANK", "P2:LFRM"])
def test_a_marker_the_labeled_frames_never_showed_is_labeled_when_it_appears(marker):
    # the pair rule (the walkers' bodies are triangles): P2:LKNE is in two (4 members), P2:LANK
    # in two sharing a member, P2:LFRM in one (2 pairs: the only free point on their circle)
    share, wrong = _labeled_share(marker, acquire=True)
    assert share >= 0.95
    assert wrong == 0


def test_a_free_point_off_the_trained_distances_is_not_taken_for_it():
    # a decoy 40 mm away: the pair rule weighs every distance (a rule that took any free point
    # in reach would see two candidates and place nothing, or the decoy)
    share, wrong = _labeled_share("P2:LFRM", acquire=True, decoy_mm=40.0)
    assert share >= 0.95
    assert wrong == 0


def test_without_the_acquisition_it_is_never_labeled():
    share, _ = _labeled_share("P2:LKNE", acquire=False)
    assert share == 0.0


def _rigid_cluster(frames: int = 240, rate: float = 120.0):
    """Six markers on one rigid plate turning and moving (one body of 4+ members)."""
    from labeler_service.capture import Capture

    rng = np.random.default_rng(3)
    shape = rng.normal(scale=60.0, size=(6, 3))
    t = np.arange(frames) / rate
    pos = np.empty((frames, 6, 3))
    for f, tt in enumerate(t):
        a = 0.8 * tt
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
        pos[f] = shape @ R.T + np.array([300.0 * tt, 50.0 * np.sin(tt), 900.0])
    pos += rng.normal(scale=0.3, size=pos.shape)
    return Capture(pos.astype(np.float32), tuple(f"s:m{i}" for i in range(6)), rate)


@pytest.mark.parametrize("hidden", [30, 3])
def test_a_body_of_four_or_more_places_the_marker_by_its_trained_shape(hidden):
    # hidden 3: it appears in the first unlabeled frame, its neighbours continuing from the
    # labeled ones (their warm start leaves the state as it was: continuing is by age)
    from labeling.walks import train

    cap = _rigid_cluster()
    model = train(cap.frames(0, 120))
    sizes = [len(b) for s in model.subjects for b in s.bodies]
    assert max(sizes) >= 4  # (the shape rule, not the pair rule)
    lab = Labeler.from_model(model, cap.rate)
    later = cap.frames(120, 240)
    pos = later.positions.copy()
    pos[:hidden, 5] = np.nan
    got = []
    for f in range(later.n_frames):
        idx = np.flatnonzero(np.isfinite(pos[f, :, 0]))
        out = lab.process(pos[f, idx], f / cap.rate, idx.astype(np.int32) if f < 3 else None)
        if f >= hidden:
            got.append(out.point_labels[np.flatnonzero(idx == 5)[0]] == 5)
    assert got[0] and all(got)  # labeled in the frame it appears, and kept


def test_a_pair_without_a_trained_distance_is_no_evidence():
    """A model may hold a body pair with no trained distance (``null``): the pair rule must not
    count it (it passed every distance, and a decoy at the one trained distance was taken)."""
    from labeling.walks import train

    from labeler_service.capture import Capture
    from labeler_service.labeling.templates import LabelerModel

    rng = np.random.default_rng(3)
    tri = np.array([[0, 0, 0], [120.0, 0, 0], [40.0, 90.0, 10.0]])
    tri2 = np.array([[0, 0, 0], [100.0, 20, 0], [30.0, -80.0, 40.0]])  # (a second plate: the
    rate, n = 120.0, 240  # subject keeps 3+ markers while c is hidden, so it is present)
    pos = np.empty((n, 6, 3))
    for f in range(n):
        a, b2 = 0.8 * f / rate, 1.7 * np.sin(2.0 * f / rate)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        R2 = np.array([[1, 0, 0], [0, np.cos(b2), -np.sin(b2)], [0, np.sin(b2), np.cos(b2)]])
        pos[f, :3] = tri @ R.T + np.array([300.0 * f / rate, 0, 900.0])
        pos[f, 3:] = tri2 @ R2.T + np.array([300.0 * f / rate, 600.0, 900.0])
    pos += rng.normal(scale=0.3, size=pos.shape)
    cap = Capture(pos.astype(np.float32), tuple(f"s:{c}" for c in "abcdef"), rate)
    raw = train(cap.frames(0, 120)).model_dump()
    sub = raw["subjects"][0]
    sub["D"][1][2] = sub["D"][2][1] = sub["A"][1][2] = sub["A"][2][1] = None
    sub["chirality"], sub["twin_witnesses"] = [], []
    lab = Labeler.from_model(LabelerModel.model_validate(raw), rate)
    later = pos[120:].copy()
    later[:30, 2] = np.nan
    taken = 0
    for f in range(later.shape[0]):
        idx = np.flatnonzero(np.isfinite(later[f, :, 0]))
        pts = later[f, idx]
        if 3 <= f < 30:  # a decoy at the trained a-c distance from a, far off the unknown b-c
            a, b = later[f, 0], later[f, 1]
            decoy = a + np.linalg.norm(tri[0] - tri[2]) * (a - b) / np.linalg.norm(a - b)
            pts = np.concatenate([pts, decoy[None]])
        out = lab.process(pts.astype(np.float32), f / rate, idx.astype(np.int32) if f < 3 else None)
        taken += int(3 <= f < 30 and out.point_labels[-1] == 2)
    assert taken == 0


def _lost_limb(lost_frames: int, rng):
    """The tennis hand of ``test_swap_repair.limb`` (its links to the pelvis bend): the wrist
    marker R was observed before and has been lost ``lost_frames`` frames; its point is back,
    free; the others hold theirs (observed 8 frames)."""
    from labeling.test_swap_repair import limb

    from labeler_service.labeling.kernels.state import NONE

    pts, tracks, bodies, scratch = limb(rng, LabelerConfig(), [0, NONE, 2, 3, 4])
    tracks.age[:] = 8
    tracks.age[1] = 0
    tracks.lost[1] = lost_frames
    return pts, tracks, bodies, scratch


def _place_lost(pts, tracks, bodies, scratch, config, frame_no=100) -> int:
    from labeler_service.labeling.kernels.params import kernel_params
    from labeler_service.labeling.kernels.spatial import _index
    from labeler_service.labeling.kernels.unseen import _acquire_unseen

    params = kernel_params(config)
    return _acquire_unseen(pts, _index(pts), frame_no, tracks, bodies, scratch, params)


def test_a_marker_lost_for_long_takes_the_point_its_links_that_hold_agree_on(rng):
    # the tennis wrist after the serve (issue 10): its stale prediction and its recovery set
    # (trained on the still window, with the pelvis) put it far off; the distances to the
    # forearm and hand markers that do not bend place it
    config = LabelerConfig()
    assert config.acquire_lost_frames == 5
    pts, tracks, bodies, scratch = _lost_limb(10, rng)
    assert _place_lost(pts, tracks, bodies, scratch, LabelerConfig(acquire_lost_frames=0)) == 0
    assert scratch.assigned[1] < 0
    assert _place_lost(pts, tracks, bodies, scratch, config) == 1
    assert scratch.assigned[1] == 1 and scratch.owner[1] == 1
    assert np.allclose(scratch.obs[1], pts[1])


def test_a_lost_marker_is_not_placed_early_nor_on_a_point_seen_beside_it(rng):
    config = LabelerConfig()
    # lost 4 frames: its own prediction still searches for it
    pts, tracks, bodies, scratch = _lost_limb(4, rng)
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # the point was there, unlabeled (an anonymous run of 20 frames), while the marker was still
    # on a track of its own 10 frames ago: another point
    pts, tracks, bodies, scratch = _lost_limb(10, rng)
    scratch.anon[1] = 20
    tracks.seen_at[1], tracks.track_from[1] = 90, 10
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # F's link bends too: two links hold (to E and U), a circle of places; a lost marker needs 3
    pts, tracks, bodies, scratch = _lost_limb(10, rng)
    bodies.A[0, 0, 2] = bodies.A[0, 2, 0] = 40.0
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # every link bends (the pelvis's and the hand's): no evidence, nothing placed
    pts, tracks, bodies, scratch = _lost_limb(10, rng)
    bodies.A[:, :4, :4] = 40.0
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0


def _lost_hand(rng, lost_frames=10):
    """The tennis hand of ``test_swap_repair.limb`` lost whole: R, U and F observed before and
    lost ``lost_frames`` frames, their points back and free; the elbow E (its links to R and U
    hold) and the pelvis P (its links to the hand bend, 539 mm from R: the repair searches
    around it) on theirs, observed 8 frames; the hand
    body's reference is its trained shape. Each rule alone places nothing here: R and U keep
    one link that holds (to E), F none."""
    from labeling.test_swap_repair import FOREARM, PELVIS, limb

    from labeler_service.labeling.kernels.state import NONE

    pts, tracks, bodies, scratch = limb(rng, LabelerConfig(), [0, NONE, NONE, NONE, 4])
    pts[4] = scratch.obs[4] = pts[1] + np.float32([200.0, 400.0, -300.0])  # within the search
    tracks.age[:] = 8
    tracks.age[1:4] = 0
    tracks.lost[1:4] = lost_frames
    bodies.ref[0, :4] = np.vstack([FOREARM, PELVIS])[1:]  # R, U, F, P
    bodies.ref_ok[0] = True
    return pts, tracks, bodies, scratch


def test_markers_of_a_body_lost_together_are_placed_together(rng):
    # the tennis hand after the serve (issue 10): wrist and finger lost in the swing; their
    # triangle's shape and the elbow's links name its three points at once
    config = LabelerConfig()
    assert config.acquire_together
    pts, tracks, bodies, scratch = _lost_hand(rng)
    alone = LabelerConfig(acquire_together=False)
    assert _place_lost(pts, tracks, bodies, scratch, alone) == 0
    assert _place_lost(pts, tracks, bodies, scratch, config) == 3
    assert list(scratch.assigned[:5]) == [0, 1, 2, 3, 4]
    assert list(scratch.owner[:5]) == [0, 1, 2, 3, 4]


def test_markers_lost_together_are_not_placed_without_evidence(rng):
    config = LabelerConfig()
    # lost 4 frames: their predictions still search for them
    pts, tracks, bodies, scratch = _lost_hand(rng, lost_frames=4)
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # the elbow's links bend too: the triangle is anchored to nothing
    pts, tracks, bodies, scratch = _lost_hand(rng)
    bodies.A[1] = 40.0
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # the finger's point 30 mm off: the three points are not the hand's shape
    pts, tracks, bodies, scratch = _lost_hand(rng)
    pts[3] += np.float32(30.0)
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    # the elbow 40 mm off where it should be for R and U: the shape fits, the anchor refuses it
    pts, tracks, bodies, scratch = _lost_hand(rng)
    pts[0] += np.float32(40.0) * (pts[0] - pts[1]) / np.linalg.norm(pts[0] - pts[1])
    scratch.obs[0] = pts[0]
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    assert all(scratch.assigned[1:4] < 0)


def test_the_together_rule_waits_for_one_member_lost_long_enough(rng):
    # asked directly (the kernel's entry returns early when no marker is wanted at all)
    from labeler_service.labeling.kernels.params import kernel_params
    from labeler_service.labeling.kernels.spatial import _index
    from labeler_service.labeling.kernels.unseen import _acquire_together

    params = kernel_params(LabelerConfig())
    for lost_frames, placed in ((4, 0), (5, 3)):
        pts, tracks, bodies, scratch = _lost_hand(rng, lost_frames=lost_frames)
        got = _acquire_together(pts, _index(pts), 100, tracks, bodies, scratch, params)
        assert got == placed, lost_frames


def test_markers_lost_together_take_no_point_seen_beside_them(rng):
    # the wrist point R would take continues an anonymous run that began at frame 80, while R
    # was still on a track of its own (seen until frame 90, its track from frame 0)
    pts, tracks, bodies, scratch = _lost_hand(rng)
    tracks.seen_at[1], tracks.track_from[1] = 90, 0
    scratch.anon[1] = 20  # frame 100 - 20
    assert _place_lost(pts, tracks, bodies, scratch, LabelerConfig()) == 0
    assert all(scratch.assigned[1:4] < 0)
    off = LabelerConfig(anonymous_tracks=False)
    assert _place_lost(pts, tracks, bodies, scratch, off) == 3


def test_markers_lost_together_are_placed_only_when_the_map_places_each_of_them(rng):
    # the pelvis P lost too (its point gone): the hand's three points could be any three of the
    # four lost members, and the readings checked are of the map's members only
    pts, tracks, bodies, scratch = _lost_hand(rng)
    scratch.assigned[4], scratch.owner[4] = -1, -1
    scratch.obs[4] = np.nan
    tracks.lost[4] = 10
    tracks.x[4, :3] = pts[4]  # the body, none of it on a point now, is searched around its
    tracks.x[1:4, :3] = pts[1:4] + 40.0  # members' estimates: the hand's points in reach
    pts[4] = np.float32(1e5)  # P's point gone far
    assert _place_lost(pts, tracks, bodies, scratch, LabelerConfig()) == 0
    assert all(scratch.assigned[1:5] < 0)


def _equidistant(f, r, u):
    """``f`` moved along the line ``r``-``u`` to be as far from ``r`` as from ``u``."""
    axis = (u - r) / np.linalg.norm(u - r)
    return f - np.dot(f - (r + u) / 2.0, axis) * axis


def test_two_readings_the_anchors_cannot_tell_apart_place_nothing(rng):
    # the finger as far from one wrist marker as from the other: the hand's triangle reads the
    # two wrist markers either way, and the elbow's links (272 / 265 mm, 16 mm allowed) do too
    config = LabelerConfig()
    pts, tracks, bodies, scratch = _lost_hand(rng)
    ref = bodies.ref[0]
    ref[2] = _equidistant(ref[2], ref[0], ref[1])
    pts[3] = _equidistant(pts[3].astype(float), pts[1].astype(float), pts[2].astype(float))
    assert _place_lost(pts, tracks, bodies, scratch, config) == 0
    assert all(scratch.assigned[1:4] < 0)


def test_a_lost_marker_placed_starts_a_new_track_moving_with_its_anchors(rng):
    # its coasted velocity says nothing of a hand that swung on while it was lost
    config = LabelerConfig()
    assert config.acquire_restart
    pts, tracks, bodies, scratch = _lost_hand(rng)
    tracks.x[0, 3:] = [400.0, -200.0, 100.0]  # the elbow's velocity, mm/s
    tracks.x[1:4, 3:] = [-900.0, 0.0, 0.0]  # coasted
    tracks.P[1:4] = [5000.0, 300.0, 9000.0]
    finger = tracks.x[3].copy()
    assert _place_lost(pts, tracks, bodies, scratch, config) == 3
    for m in (1, 2):  # R, U: anchored by the elbow's links
        assert np.allclose(tracks.x[m, :3], pts[m])
        assert np.allclose(tracks.x[m, 3:], [400.0, -200.0, 100.0])
        assert tuple(tracks.P[m]) == pytest.approx((config.measurement_noise_mm**2, 0.0, V0))
    assert np.array_equal(tracks.x[3], finger)  # F: no link that holds to a tracked member
    pts, tracks, bodies, scratch = _lost_hand(rng)
    tracks.x[1:4, 3:] = [-900.0, 0.0, 0.0]
    off = LabelerConfig(acquire_restart=False)
    assert _place_lost(pts, tracks, bodies, scratch, off) == 3
    assert np.allclose(tracks.x[1:4, 3:], [-900.0, 0.0, 0.0])
