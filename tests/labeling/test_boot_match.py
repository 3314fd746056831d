"""Steps of the boot's matching (labeling/boot_match.py) on one simulated subject: markers with
no rigid evidence, exchanged markers, mirrored segments; and the tracker at sprint speed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labeler_service.labeling.boot import BootConfig, Booter, PointTracker, track_history
from labeler_service.labeling.boot_match import (
    _ambiguous,
    _articulate,
    _exchange,
    _fill_reversed,
    _handedness,
    _hypotheses,
    _one_sided,
    _orphans,
    _pair_error,
    _Pairs,
    _relocate,
    _strict_partners,
    _swap_mirrors,
)
from labeler_service.scenes.simulate import simulate_scene

RATE = 120.0


@pytest.fixture(scope="module")
def walker():
    """One simulated walker: its template (trained on the first half) and a 12-frame window of
    the second half with each point's true marker."""
    from offline.structure import StructureTrainer

    cap = simulate_scene(1, 4.0, "walk", seed=5, rate=RATE, ghosts=0.0)
    half = cap.n_frames // 2
    model = StructureTrainer().fit([cap.frames(0, half)]).model_
    tpl = Booter(model, BootConfig())._templates[0]
    col = {lab: i for i, lab in enumerate(cap.labels)}
    cols = np.array([col[n] for n in model.marker_names])
    hist = np.transpose(cap.positions[half : half + 12, cols].astype(np.float64), (1, 0, 2))
    keep = np.isfinite(hist).all(axis=(1, 2))
    truth = np.where(keep, np.cumsum(keep) - 1, -1)  # marker -> point index
    return tpl, hist[keep], truth


def _total(tpl, assign, pts):
    m = np.flatnonzero(assign >= 0)
    return _pair_error(tpl, m, assign[m], np.full(tpl.n, -1), pts)


def test_marker_without_rigid_evidence_joins_only_when_its_point_is_unique(walker):
    tpl, hist, truth = walker
    pts = hist[:, -1]
    config = BootConfig()
    # markers with three or more steady partners (A <= art_a_mm) but left out of the placement
    limit = float(config.art_a_mm)
    n_steady = np.sum(np.less_equal(tpl.A, limit), axis=1) - 1
    steady = n_steady >= config.art_min_anchors + 2
    out = np.flatnonzero(steady & (truth >= 0))[:3]
    assert out.size == 3
    assign = truth.copy()
    assign[out] = -1
    taken = np.zeros(len(pts), dtype=bool)
    taken[assign[assign >= 0]] = True
    _articulate(tpl, assign, taken, pts, hist, cKDTree(pts), config)
    np.testing.assert_array_equal(assign, truth)  # placed, each on its own point
    # a second point beside one of them (a ghost 3 mm away): that marker is not guessed
    ghost = hist[truth[out[0]]] + np.array([3.0, 0.0, 0.0])
    hist2 = np.concatenate([hist, ghost[None]])
    pts2 = hist2[:, -1]
    assign = truth.copy()
    assign[out] = -1
    taken = np.zeros(len(pts2), dtype=bool)
    taken[assign[assign >= 0]] = True
    _articulate(tpl, assign, taken, pts2, hist2, cKDTree(pts2), config)
    assert assign[out[0]] == -1
    np.testing.assert_array_equal(assign[out[1:]], truth[out[1:]])


def test_exchanged_markers_are_put_back(walker):
    tpl, hist, truth = walker
    pts = hist[:, -1]
    rng = np.random.default_rng(2)
    fixed = 0
    for _ in range(10):
        a, b = rng.choice(np.flatnonzero(truth >= 0), 2, replace=False)
        assign = truth.copy()
        assign[a], assign[b] = truth[b], truth[a]
        if _total(tpl, assign, pts) <= _total(tpl, truth, pts) + 1.0:
            continue  # the distances cannot tell these two apart
        _exchange(tpl, assign, pts)
        np.testing.assert_array_equal(assign, truth)
        fixed += 1
    assert fixed >= 5


def test_mirrored_segments_are_swapped_back(walker):
    tpl, hist, truth = walker
    pts = hist[:, -1]
    assert tpl.mirrors  # left and right limbs
    swapped = 0
    for s1, s2 in tpl.mirrors:
        assign = truth.copy()
        assign[s1], assign[s2] = truth[s2], truth[s1]
        if _total(tpl, assign, pts) <= _total(tpl, truth, pts) + 1.0:
            continue
        _swap_mirrors(tpl, assign, pts)
        if np.array_equal(assign, truth):
            swapped += 1
    assert swapped >= 1
    # the right reading is left alone
    assign = truth.copy()
    _swap_mirrors(tpl, assign, pts)
    np.testing.assert_array_equal(assign, truth)


def test_chirality_tells_a_subject_from_its_mirror_image(walker):
    """Pair distances are the same for a body and its mirror image; the trained signed volumes
    are not: the right reading keeps them all, the same reading of the mirrored points (x -> -x:
    every distance unchanged) reverses them all, and a boot on the mirrored window does not
    label it as the original (it would be a reading reversing every quadruple)."""
    tpl, hist, truth = walker
    pts = hist[:, -1]
    assert tpl.chirality.shape[0] >= 4
    kept, rev, local = _handedness(tpl, truth, pts)
    assert kept >= 4 and rev == 0 and local == 0
    flip = np.array([-1.0, 1.0, 1.0])
    assert _handedness(tpl, truth, pts * flip)[:2] == (0, kept)
    # the hypotheses on the mirrored window read it left for right (a consistent body), never
    # as the original labels (every distance fits them, every volume is reversed)
    mirrored = hist * flip
    pairs = _Pairs(mirrored[:, -1], tpl.r_max)
    hyps = _hypotheses(tpl, mirrored[:, -1], mirrored, pairs, BootConfig())
    for h in hyps:
        placed = h.assign >= 0
        assert np.mean(h.assign[placed] == truth[placed]) < 0.8


def test_tracker_follows_a_sprinter_from_the_second_frame(rng):
    """9 m/s at 250 Hz is 36 mm a frame: a point with no velocity yet must still be linked
    (the gate allowed 3 m/s before, so no track of a sprinter lasted two frames)."""
    rate = 250.0
    # 40 markers 70-90 mm apart (a body seen by a capture system: markers are never closer
    # than about the distance a sprinter covers in two frames)
    gy, gz = np.meshgrid(np.arange(5) * 80.0, np.arange(8) * 80.0)
    base = np.stack([np.zeros(40), gy.ravel(), gz.ravel()], axis=1) + rng.uniform(-5, 5, (40, 3))
    vel = np.array([9000.0, 0.0, 0.0])
    tracker = PointTracker(rate)
    frames = []
    for k in range(6):
        order = rng.permutation(40)
        pts = base[order] + vel * k / rate
        frames.append((pts, tracker.update(pts, k / rate)))
    hist = track_history(frames, frames[-1][1])
    assert np.isfinite(hist[:, :, 0]).all()  # every point tracked through all six frames


def test_marker_on_a_wrong_point_moves_to_its_free_point(walker):
    """A limb read one marker along its chain leaves the right point free: the marker moves
    there (and a marker on its right point stays)."""
    tpl, hist, truth = walker
    pts = hist[:, -1]
    rng = np.random.default_rng(4)
    moved = 0
    for m in rng.choice(np.flatnonzero(truth >= 0), 8, replace=False):
        stray = pts[truth[m]] + rng.normal(0, 1, 3) / np.sqrt(3) * 60.0  # 60 mm off
        pts2 = np.concatenate([pts, stray[None]])
        assign = truth.copy()
        assign[m] = len(pts)  # on the stray point, its own point left free
        free = np.zeros(len(pts2), dtype=bool)
        free[truth[m]] = True
        if _total(tpl, assign, pts2) <= _total(tpl, truth, pts2) + 1.0:
            continue
        _relocate(tpl, assign, pts2, free, cKDTree(pts2))
        np.testing.assert_array_equal(assign, truth)
        moved += 1
    assert moved >= 4
    assign = truth.copy()
    free = np.ones(len(pts), dtype=bool)
    free[truth[truth >= 0]] = False
    _relocate(tpl, assign, pts, free, cKDTree(pts))
    np.testing.assert_array_equal(assign, truth)


@pytest.mark.realdata
def test_a_body_on_one_placed_marker_completes_a_booted_subject(real_path):
    """The CMU right foot: its bodies (ankle, toe, fifth metatarsal; ankle, heel, fifth
    metatarsal) share only the ankle with the rest of the subject, and heel, toe and metatarsal
    have no other rigid partner placed, so no marker of them alone has the two agreements a node
    needs. The extension takes the body candidate on the placed ankle (it was refused because its
    ankle node was the placed one: the booted demo performer kept its foot unlabeled for 10 s)."""
    from labeler_service.capture import read_capture
    from offline.structure import StructureTrainer

    cap = read_capture(real_path("cmu_01_01_playground.c3d"))
    model = StructureTrainer().fit([cap.frames(1800, 2400)]).model_  # the demo's bodies
    names = list(model.marker_names)
    col = {lab: i for i, lab in enumerate(cap.labels)}
    cols = np.array([col[n] for n in names])
    hist = np.transpose(cap.positions[600:612, cols].astype(np.float64), (1, 0, 2))
    keep = np.isfinite(hist).all(axis=(1, 2))
    truth = np.where(keep, np.cumsum(keep) - 1, -1)  # marker -> point index
    hist = hist[keep]
    foot = [names.index(f"{model.subjects[0].name}:{m}") for m in ("RHEE", "RTOE", "RMT5")]
    assert (truth[foot] >= 0).all()
    labels = np.full(hist.shape[0], -1, dtype=np.int64)
    placed = np.flatnonzero(truth >= 0)
    placed = placed[~np.isin(placed, foot)]
    labels[truth[placed]] = placed
    out = Booter(model, BootConfig()).extend(hist[:, -1], hist, labels, [0])
    assert out[truth[foot]].tolist() == foot
    assert np.array_equal(out[truth[placed]], placed)  # labels given are kept


def _dense_relations(tpl, M, P, pts):
    """The node relations of ``boot_match._Graph`` written out over the whole square."""
    d = np.linalg.norm(pts[P][:, None] - pts[P][None], axis=2)
    mm = (M[:, None], M[None, :])
    D, tol, rig, st = tpl.D[mm], tpl.tol[mm], tpl.rigid[mm], tpl.strict[mm]
    dev = d - D
    known = np.isfinite(D)
    other = (M[:, None] != M[None, :]) & (P[:, None] != P[None, :])
    agree = rig & other & (np.abs(dev) <= tol)
    differ = rig & other & ~st & (np.abs(dev) > tol)
    clash = (M[:, None] == M[None, :]) != (P[:, None] == P[None, :])
    clash |= known & st & (np.abs(dev) > tol)
    clash |= known & ~st & (dev > tpl.bound[mm])
    t = tpl.link[mm]
    art = known & ~rig & (t > 0) & other
    link = art & (np.abs(dev) <= t)
    link_err = np.where(link, np.abs(dev) / np.where(t > 0, t, 1.0), 0.0)
    return agree, clash, differ, link, link_err, art


def test_graph_rows_on_demand_match_the_whole_square(walker):
    """Rows computed when a hypothesis reads them (in any order, some twice) equal the relations
    over the whole square, and the agreement counts equal the row sums of ``agree``."""
    from labeler_service.labeling.boot_match import _Graph

    tpl, hist, truth = walker
    rng = np.random.default_rng(3)
    # the true placement, every marker on a few wrong points too, and ghosts
    pts = np.concatenate([hist[:, -1], hist[:, -1][rng.integers(0, len(hist), 6)] + 40.0])
    placed = np.flatnonzero(truth >= 0)
    M = np.concatenate([placed, rng.integers(0, tpl.n, 300)])
    P = np.concatenate([truth[placed], rng.integers(0, len(pts), 300)])
    key = np.unique(M * len(pts) + P)
    M, P = key // len(pts), key % len(pts)
    g = _Graph(tpl, M, P, pts)
    ref = _dense_relations(tpl, M, P, pts)
    np.testing.assert_array_equal(g.support, ref[0].sum(axis=1))
    order = rng.permutation(M.size)
    for part in np.array_split(order, 5):
        g.rows(part)
    g.rows(order[:10])  # again: no change
    names = ("agree", "clash", "differ", "link", "link_err", "art")
    for name, want in zip(names, ref, strict=True):
        got = getattr(g, name)
        if name == "link_err":
            np.testing.assert_allclose(got, want, atol=1e-9)
        else:
            np.testing.assert_array_equal(got, want, err_msg=name)
    assert ref[0].any() and ref[1].any() and ref[3].any()  # the case is not trivial


def _two_walkers_window():
    """Two simulated walkers, a model of their first half, and a 12-frame window after it:
    ``(booter, history (n, 12, 3), last points, template 0, template 1, the true point of each
    marker of subject 0 and of subject 1 (-1: not seen))``."""
    from offline.structure import StructureTrainer

    cap = simulate_scene(2, 4.0, "walk", seed=5, rate=RATE, ghosts=0.0)
    half = cap.n_frames // 2
    model = StructureTrainer().fit([cap.frames(0, half)]).model_
    booter = Booter(model, BootConfig())
    col = {lab: i for i, lab in enumerate(cap.labels)}
    cols = np.array([col[n] for n in model.marker_names])
    h = np.transpose(cap.positions[half : half + 12, cols].astype(np.float64), (1, 0, 2))
    keep = np.isfinite(h).all(axis=(1, 2))
    h = h[keep]
    pts = h[:, -1]
    gidx = np.flatnonzero(keep)  # point -> global marker
    t0, t1 = booter._templates
    a0, a1 = np.full(t0.n, -1), np.full(t1.n, -1)
    for p, g in enumerate(gidx):
        if g < t0.n:
            a0[g] = p
        else:
            a1[g - t0.n] = p
    return booter, h, pts, t0, t1, a0, a1


def _run_two(monkeypatch, booter, pts, h, a0, a1):
    """``booter.run`` with the hypotheses fixed: subject 0 reading ``a0`` (the better score),
    subject 1 reading ``a1``."""
    import labeler_service.labeling.boot as boot_mod
    from labeler_service.labeling.boot_match import _Hypothesis

    hyps = [
        _Hypothesis(0, a0, score=100.0, rms=1.0),
        _Hypothesis(1, a1.copy(), score=50.0, rms=1.0),
    ]
    monkeypatch.setattr(boot_mod, "_hypotheses", lambda tpl, *a, **k: [
        x for x in hyps if x.template == tpl.index
    ])  # fmt: skip
    return booter.run(pts, h)


def test_a_contested_point_goes_to_the_subject_with_rigid_evidence_for_it(monkeypatch):
    """Two subjects' hypotheses claim one point: the better-scored one reads it as a loose
    marker (no rigid partner placed), the other as a marker of a placed rigid body. The point
    goes to the second, the first keeps the rest of its subject."""
    import labeler_service.labeling.boot as boot_mod

    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    # a marker of subject 1 with the most rigid partners: its point is contested
    sup1 = boot_mod._rigid_support(t1, a1, pts)
    m1 = int(np.argmax(sup1))
    p = a1[m1]
    assert sup1[m1] >= 3
    # subject 0 reads that point as one of its markers that has no rigid partner placed
    loose = np.flatnonzero(~t0.strict.any(axis=1) | (a0 < 0))
    m0 = int(loose[0]) if loose.size else 0
    bad0 = a0.copy()
    bad0[m0] = p
    assert boot_mod._rigid_support(t0, bad0, pts)[m0] <= 1
    res = _run_two(monkeypatch, booter, pts, h, bad0, a1)
    assert sorted(res.subjects) == sorted([t0.name, t1.name])
    assert res.labels[p] == t1.offset + m1
    # subject 0 keeps its other markers
    others = np.flatnonzero(bad0 >= 0)
    others = others[others != m0]
    np.testing.assert_array_equal(res.labels[bad0[others]], t0.offset + others)


def test_a_limb_read_on_another_subjects_points_goes_back_to_its_owner():
    """Two walkers: subject 1's hypothesis holds subject 0's limb (under its own names for
    that limb) and subject 0's hypothesis left the limb out, so no point is contested. The
    reclaim completes subject 0 with the others' points free and takes the limb back, since
    subject 0's model explains those points far better given the rest of it."""
    from labeler_service.labeling.boot_match import _Hypothesis

    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    truth0 = a0.copy()
    limb = next(s1 for s1, _ in t0.mirrors if np.all(a0[s1] >= 0) and s1.size >= 3)
    names0 = [booter.model.marker_names[t0.offset + k].split(":")[-1] for k in limb]
    names1 = [n.split(":")[-1] for n in booter.model.marker_names[t1.offset : t1.offset + t1.n]]
    limb1 = np.array([names1.index(n) for n in names0])
    a1[limb1] = a0[limb]  # subject 1 reads subject 0's limb as its own
    a0[limb] = -1
    accepted = [_Hypothesis(0, a0, 0.0), _Hypothesis(1, a1, 0.0)]
    booter._reclaim(accepted, pts, h)
    np.testing.assert_array_equal(accepted[0].assign[limb], truth0[limb])
    assert not np.isin(truth0[limb], accepted[1].assign).any()


def test_a_mirror_segment_without_handedness_is_not_guessed_and_fill_maps_see_chirality(walker):
    """A mirror segment placed whole on one side, its partner and a quadruple over it not yet
    placed, is reported by ``_one_sided`` (nothing has told its side); once its quadruples are
    placed it is not. A fill map placing markers on their true points reverses no quadruple;
    the same map on the mirrored points (every distance kept) does."""
    tpl, hist, truth = walker
    pts = hist[:, -1]
    assert tpl.mirrors and tpl.chirality.shape[0]
    found = False
    for s1, s2 in tpl.mirrors:
        # every quadruple over s1 lacks a marker outside it (its knee), none lies inside it
        over = np.array([np.isin(q, s1).any() for q in tpl.chirality], dtype=bool)
        quads = tpl.chirality[over]
        if not over.any() or np.any(truth[s1] < 0) or any(np.isin(q, s1).all() for q in quads):
            continue
        # the walker's quadruples over a limb are wide ones; only a local one (a leg's knee,
        # ankle and toes) holds the segment back: as wide ones they do not
        assign = truth.copy()
        assign[s2] = -1
        for q in quads:
            assign[[m for m in q if m not in s1]] = -1
        assert not np.isin(
            s1, _one_sided(replace(tpl, chiral_local=np.zeros_like(over)), assign)
        ).any()
        tpl = replace(tpl, chiral_local=over)
        if np.isin(s1, _one_sided(tpl, assign)).all():
            found = True
            assert _one_sided(tpl, truth).size == 0  # everything placed: nothing one-sided
            break
    assert found
    marks = np.flatnonzero(truth >= 0)[None]
    empty = np.full(tpl.n, -1, dtype=np.int64)
    assert not _fill_reversed(tpl, empty, pts, marks, truth[marks])[0]
    flip = np.array([-1.0, 1.0, 1.0])
    assert _fill_reversed(tpl, empty, pts * flip, marks, truth[marks])[0]


def test_completions_in_a_memo_reuse_candidates_and_give_the_same_markers(walker, monkeypatch):
    """A subject with two segments unplaced and two markers exchanged is completed
    (:func:`_complete_weak`) inside :func:`memo` and without: the same markers; a completion
    on the same local points again (a re-reading) takes every body candidate from the memo."""
    import labeler_service.labeling.boot_match as bm

    tpl, hist, truth = walker
    pts = hist[:, -1]
    assign = truth.copy()
    for body in tpl.bodies[-2:]:  # two segments hidden from the boot
        assign[body.markers] = -1
    # two markers of another segment exchanged (weakly placed: their pairs are off)
    a, b = [m for m in tpl.bodies[0].markers if assign[m] >= 0][:2]
    assign[[a, b]] = assign[[b, a]]
    taken = np.zeros(pts.shape[0], dtype=bool)
    calls = []
    real = bm._body_candidates

    def counted(*args):
        calls.append(args[1])
        return real(*args)

    monkeypatch.setattr(bm, "_body_candidates", counted)
    cfg = BootConfig()
    plain = bm._complete_weak(tpl, assign.copy(), pts, hist, taken, cfg)
    assert (plain >= 0).sum() > (assign >= 0).sum()  # it did complete
    n_plain = len(calls)
    calls.clear()
    with bm.memo():
        memoized = bm._complete_weak(tpl, assign.copy(), pts, hist, taken, cfg)
        assert len(calls) <= n_plain
        first = len(calls)
        # the same subject completed again on the same points (as a re-reading does)
        again = bm._complete(tpl, assign.copy(), pts, hist, taken, cfg, reread=True)
        assert len(calls) == first  # every candidate from the memo
    np.testing.assert_array_equal(memoized, plain)
    np.testing.assert_array_equal(
        again, bm._complete(tpl, assign.copy(), pts, hist, taken, cfg, reread=True)
    )
    assert bm._MEMO.get() is None  # closed


def _turned_about(h, a, b, angle=np.pi):
    """Track ``h (W, 3)`` turned by ``angle`` about the axis through tracks ``a`` and ``b``,
    frame by frame (Rodrigues): its distances to ``a`` and ``b`` are kept."""
    k = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    v = h - a
    c, s = np.cos(angle), np.sin(angle)
    kv = np.sum(k * v, axis=1, keepdims=True)
    return a + v * c + np.cross(k, v) * s + k * kv * (1 - c)


def test_a_new_marker_another_free_point_fits_as_well_is_not_placed(walker):
    """``_ambiguous``: a marker placed beside two strict partners only, while another unused
    point keeps the same two distances (its own point turned about their axis), has nothing
    to tell the two points apart; a third partner placed tells them."""
    tpl, hist, truth = walker
    config = BootConfig()
    placed = truth >= 0
    cands = [m for m in np.flatnonzero(placed) if np.count_nonzero(tpl.strict[m] & placed) >= 3]
    assert cands
    m = cands[0]
    partners = np.flatnonzero(tpl.strict[m] & placed)
    p1, p2, p3 = partners[:3]
    alt = _turned_about(hist[truth[m]], hist[truth[p1]], hist[truth[p2]])
    lh = np.concatenate([hist, alt[None]])
    assert np.linalg.norm(alt[-1] - hist[truth[m], -1]) > 20.0  # (another point, not a twin)
    fresh = np.zeros(tpl.n, dtype=bool)
    fresh[m] = True
    la = np.full(tpl.n, -1, dtype=np.int64)
    la[[m, p1, p2]] = truth[[m, p1, p2]]
    assert _ambiguous(tpl, la, lh, fresh, config)[m]
    la[p3] = truth[p3]  # the third distance differs on the turned point
    assert not _ambiguous(tpl, la, lh, fresh, config).any()
    la[[p1, p2, p3]] = -1  # (no partner placed: nothing to judge here)
    assert not _ambiguous(tpl, la, lh, fresh, config).any()


def test_a_marker_whose_strict_partners_were_all_refuted_goes_with_them(walker):
    """``_orphans``, as a completion runs it after ``_constancy``: a new marker whose strict
    partners the check dropped, all of them (its candidate refuted), goes too; a marker placed
    before the completion (not movable), or one that had no strict partner placed, keeps its
    place, and so does one with a partner left."""
    tpl, hist, truth = walker
    placed = truth >= 0
    n_strict = (tpl.strict & placed[None]).sum(axis=1)
    ok = placed & (n_strict >= 2)
    m = int(np.flatnonzero(ok)[np.argmin(n_strict[ok])])
    partners = np.flatnonzero(tpl.strict[m] & placed)
    assign = np.full(tpl.n, -1, dtype=np.int64)
    assign[np.r_[partners, m]] = truth[np.r_[partners, m]]
    had = _strict_partners(tpl, assign)
    assert had[m] == partners.size
    refuted = assign.copy()
    refuted[partners] = -1  # (what the check dropped)
    movable = np.zeros(tpl.n, dtype=bool)
    kept = refuted.copy()
    _orphans(tpl, kept, had, movable)
    assert kept[m] == truth[m]  # placed before: not this test's
    movable[m] = True
    _orphans(tpl, kept, np.zeros_like(had), movable)
    assert kept[m] == truth[m]  # no strict partner at the start: not this test's either
    _orphans(tpl, kept, had, movable)
    assert kept[m] == -1
    one_left = assign.copy()
    one_left[partners[1:]] = -1
    _orphans(tpl, one_left, had, movable)
    assert one_left[m] == truth[m]


def test_a_completion_does_not_keep_a_marker_whose_candidate_was_refuted(walker, monkeypatch):
    """``_complete``: a triangle body whose markers are each other's only strict partners is
    placed whole; when the constancy check drops two of them (here forced: the check's verdict
    on a candidate read on another limb's points), the third is not kept alone."""
    import labeler_service.labeling.boot_match as bm

    tpl, hist, truth = walker
    config = BootConfig()
    pts = hist[:, -1]
    # a three-marker body whose markers have no strict partner outside it
    seg = next(
        b.markers
        for b in tpl.bodies
        if b.markers.size == 3
        and np.all(truth[b.markers] >= 0)
        and np.all(tpl.strict[b.markers].sum(axis=1) == 2)
    )
    assign = truth.copy()
    assign[seg] = -1
    taken = np.zeros(len(pts), dtype=bool)
    taken[assign[assign >= 0]] = True
    out = bm._complete(tpl, assign, pts, hist, taken, config)
    np.testing.assert_array_equal(out[seg], truth[seg])
    check = bm._constancy

    def refuted(tpl_, a, h, c):
        a = check(tpl_, a, h, c)
        a[seg[:2]] = -1
        return a

    monkeypatch.setattr(bm, "_constancy", refuted)
    out = bm._complete(tpl, assign, pts, hist, taken, config)
    assert np.all(out[seg] == -1)
    np.testing.assert_array_equal(out[assign >= 0], assign[assign >= 0])


def test_a_reading_left_below_its_boot_count_by_contested_points_does_not_boot(monkeypatch):
    """The better-scored hypothesis of subject 0 holds half its boot count on its own points and
    half on points of subject 1 that subject 1's hypothesis holds with rigid evidence (two
    placed partners or more; subject 0 has none there). Subject 1 takes those points back, and
    what subject 0 keeps is below its boot count: subject 0 does not boot from that run (it is
    searched again at the next attempt), and none of its labels is given."""
    import labeler_service.labeling.boot as boot_mod

    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    need = booter.config.boot_markers(t0.n)
    sup1 = boot_mod._rigid_support(t1, a1, pts)
    strong = np.flatnonzero(sup1 >= 2)
    own = np.flatnonzero(a0 >= 0)
    half = need // 2
    assert strong.size >= need - half and own.size >= half
    bad0 = np.full(t0.n, -1)
    bad0[own[:half]] = a0[own[:half]]
    # the rest of the boot count read on subject 1's rigidly supported points
    rest = [m for m in range(t0.n) if bad0[m] < 0][: need - half]
    bad0[rest] = a1[strong[: need - half]]
    assert (bad0 >= 0).sum() == need
    assert (boot_mod._rigid_support(t0, bad0, pts)[rest] <= 0).all()
    res = _run_two(monkeypatch, booter, pts, h, bad0, a1)
    assert res.subjects == [t1.name]
    assert not ((res.labels >= t0.offset) & (res.labels < t0.offset + t0.n)).any()
    have1 = np.flatnonzero(a1 >= 0)
    np.testing.assert_array_equal(res.labels[a1[have1]], t1.offset + have1)
