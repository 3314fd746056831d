"""Structure re-formed from the stream's own motion (labeling/restructure.py, issue 10)."""

from __future__ import annotations

import numpy as np
from labeling.scene import articulated, frame_points

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.restructure import (
    _accumulate,
    add_prior,
    add_samples,
    pair_model,
    reform_bodies,
)
from labeler_service.labeling.training import model_pair_statistics


def _sums(m):
    return np.zeros((m, m)), np.zeros((m, m)), np.zeros((m, m))


def test_pair_model_is_the_training_statistics(rng):
    pos = rng.normal(0, 200, (30, 6, 3))
    pos[rng.random((30, 6)) < 0.2] = np.nan
    ev = _sums(6)
    add_samples(pos, np.array([0, 6]), np.arange(6), *ev)
    D, A = pair_model(np.arange(6), *ev)
    D0, A0 = model_pair_statistics(pos)
    np.testing.assert_allclose(D, D0, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(A, A0, rtol=1e-6, atol=1e-6)
    # a subset in another order reads the same pairs
    cols = np.array([4, 1, 3])
    Ds, _ = pair_model(cols, *ev)
    np.testing.assert_allclose(Ds, D0[np.ix_(cols, cols)], atol=1e-9)


def test_window_samples_are_summed_within_each_subject_only(rng):
    """Pairs of two subjects are never read (a subject's ``pair_model``): the window's samples
    are summed per subject, subjects in any marker order."""
    pos = rng.normal(0, 200, (10, 5, 3))
    ev = _sums(5)
    add_samples(pos, np.array([0, 2, 5]), np.array([3, 0, 1, 4, 2]), *ev)
    n = ev[2]
    inside = {(0, 3), (1, 4), (1, 2), (2, 4)}
    for i in range(5):
        for j in range(i + 1, 5):
            assert n[i, j] == (10 if (i, j) in inside else 0), (i, j)
    D, _ = pair_model(np.array([1, 4, 2]), *ev)
    D0, _ = model_pair_statistics(pos[:, [1, 4, 2]])
    np.testing.assert_allclose(D, D0, atol=1e-9)


def test_prior_counts_as_samples_of_the_model():
    D = np.array([[0.0, 100.0], [100.0, 0.0]])
    A = np.array([[0.0, 3.0], [3.0, 0.0]])
    ev = _sums(3)
    add_prior(np.array([2, 0]), D, A, 50.0, *ev)
    Dm, Am = pair_model(np.array([2, 0]), *ev)
    assert Dm[0, 1] == 100.0 and abs(Am[0, 1] - 3.0) < 1e-9
    assert ev[2][0, 2] == 50.0 and ev[2][0, 1] == 0.0


def test_only_confident_markers_are_evidence():
    m = 4
    state = np.array([MarkerState.OBSERVED] * 3 + [MarkerState.RECOVERED], dtype=np.uint8)
    age = np.array([20, 20, 3, 20])  # marker 2 re-acquired 3 frames ago
    pos = np.array([[0, 0, 0], [100, 0, 0], [0, 50, 0], [0, 0, 70]], dtype=np.float32)
    ok = np.array([True, False])  # body 1 fails the 3D check
    # body 0 = markers 0, 1; body 1 = markers 1, 3... marker 1 is in both
    mb_ptr = np.array([0, 1, 3, 3, 4])
    mb_idx = np.array([0, 0, 1, 1], dtype=np.int32)
    subj_ptr = np.array([0, 4])
    subj_idx = np.arange(4)
    conf = np.zeros(m, dtype=np.bool_)
    ev = _sums(m)
    _accumulate(state, age, pos, ok, mb_ptr, mb_idx, subj_ptr, subj_idx, 10, conf, *ev)
    # 0: confident; 1: its body 1 failed; 2: too young; 3: recovered, not observed
    assert conf.tolist() == [True, False, False, False]
    assert ev[2].sum() == 0
    ok[1] = True
    _accumulate(state, age, pos, ok, mb_ptr, mb_idx, subj_ptr, subj_idx, 10, conf, *ev)
    assert ev[2][0, 1] == 1 and ev[2].sum() == 1
    assert abs(ev[0][0, 1] - 100.0) < 1e-9


def _two_segments():
    """Markers 0-3 on one segment, 4-7 on another, bent against each other."""
    D = np.full((8, 8), 200.0)
    A = np.full((8, 8), 60.0)  # across the joint
    for seg in (range(4), range(4, 8)):
        for i in seg:
            for j in seg:
                D[i, j], A[i, j] = 80.0, 1.0
    np.fill_diagonal(D, 0.0)
    np.fill_diagonal(A, 0.0)
    return D, A


def test_reform_drops_a_bending_body_and_covers_its_markers():
    D, A = _two_segments()
    old = [[0, 1, 2, 3], [2, 3, 4, 5, 6, 7]]  # the second spans the joint
    # the relax form: bodies shown bending dropped, new ones only for what they held
    c = LabelerConfig(
        restructure_break_mm=40.0, restructure_tolerance_mm=20.0, restructure_add=False
    )
    kept, added = reform_bodies(D, A, np.ones(8, dtype=bool), old, c)
    assert kept == [[0, 1, 2, 3]]
    covered = {i for b in kept + added for i in b}
    assert covered == set(range(8))
    for b in added:  # no new body crosses the joint
        assert set(b) <= set(range(4)) or set(b) <= set(range(4, 8))
    # evidence that shows every body rigid keeps the structure
    A2 = np.where(A > 10, 5.0, A)
    assert reform_bodies(D, A2, np.ones(8, dtype=bool), old, c) == (old, [])
    # the default (break 0): every trained body stays, and the rigid parts the evidence shows
    # are added - also one inside a bending body ([4..7] inside [2..7])
    kept, added = reform_bodies(D, A, np.ones(8, dtype=bool), old, LabelerConfig())
    assert kept == old and sorted(map(sorted, added)) == [[4, 5, 6, 7]]
    # a rigid kept body that contains the rigid part: nothing to add
    kept, added = reform_bodies(
        D, A, np.ones(8, dtype=bool), [[0, 1, 2, 3], [4, 5, 6, 7]], LabelerConfig()
    )
    assert added == []


def test_a_structure_from_enough_frames_is_not_re_formed():
    pos, names = articulated(np.random.default_rng(1), subjects=2, frames=60)
    cfg = LabelerConfig(restructure_s=0.1)
    long, short = Labeler(names, 120.0, cfg), Labeler(names, 120.0, cfg)
    _run(long, np.random.default_rng(2), pos, 12)
    _run(short, np.random.default_rng(2), pos, 11)
    assert long._ev is None and short._ev is not None


def _run(lab, rng, pos, init, force_every=0):
    labels = []
    for f in range(pos.shape[0]):
        pts, truth = frame_points(rng, pos[f])
        out = lab.process(pts, f / 120.0, truth if f < init else None)
        labels.append((out.point_labels.copy(), truth))
        if force_every and f >= init and f % force_every == 0:
            bd = lab._bodies
            bl = [[int(v) for v in bd.members[b, : bd.size[b]]] for b in range(bd.size.shape[0])]
            d0 = [bd.D0[b, : len(x), : len(x)] for b, x in enumerate(bl)]
            a0 = [bd.A0[b, : len(x), : len(x)] for b, x in enumerate(bl)]
            rec = type(lab._recovery)(*(a.copy() for a in lab._recovery))
            same = (rec.members == lab._recovery.members).all(axis=1)
            lab._install(bl, d0, a0, rec, dict(lab._subject_bodies), lab._body_keys(), same)
    return labels


def test_installing_the_same_structure_changes_nothing():
    pos, names = articulated(np.random.default_rng(3), subjects=2, frames=200)
    plain = _run(Labeler(names, 120.0), np.random.default_rng(5), pos, 20)
    forced = _run(Labeler(names, 120.0), np.random.default_rng(5), pos, 20, force_every=15)
    for (a, _), (b, _) in zip(plain, forced, strict=True):
        np.testing.assert_array_equal(a, b)


def test_restructure_on_a_stream_that_bends():
    pos, names = articulated(np.random.default_rng(1), subjects=2, frames=480)
    cfg = LabelerConfig(restructure_s=0.5, restructure_break_mm=15.0)
    lab = Labeler(names, 120.0, cfg)
    out = _run(lab, np.random.default_rng(2), pos, 5)
    correct = sum(int((a[t >= 0] == t[t >= 0]).sum()) for a, t in out[5:])
    total = sum(int((t >= 0).sum()) for _, t in out[5:])
    assert correct / total > 0.99
    assert lab.restructures >= 1  # the 5-frame window trained a body across the joint
    # every body now holds only links the evidence shows rigid within the break
    for name, cols in lab._subject_cols.items():
        D, A = pair_model(cols, *lab._ev)
        local = {int(g): k for k, g in enumerate(cols)}
        cost = A + cfg.body_distance_weight * D
        for b in lab._subject_bodies[name]:
            mk = [local[int(v)] for v in lab._bodies.members[b, : lab._bodies.size[b]]]
            sub = cost[np.ix_(mk, mk)]
            assert np.nanmax(sub) <= max(cfg.restructure_break_mm, cfg.restructure_tolerance_mm)


def test_from_model_without_stream_evidence_keeps_the_model():
    pos, names = articulated(np.random.default_rng(4), subjects=2, frames=60)
    trainer = Labeler(names, 120.0)
    _run(trainer, np.random.default_rng(6), pos, 40)
    cfg = LabelerConfig(restructure_s=1.0, restructure_prior_s=0.05)  # 6 samples: re-formed
    assert Labeler.from_model(trainer.model, 120.0, LabelerConfig(restructure_s=1.0))._ev is None
    lab = Labeler.from_model(trainer.model, 120.0, cfg)
    pts, truth = frame_points(np.random.default_rng(7), pos[0])
    lab.process(pts, 0.0, truth)
    lab.process(*frame_points(np.random.default_rng(8), pos[1])[:1], 1 / 120.0)
    before = lab._bodies.members.copy()
    assert not lab.restructure()  # nothing confident yet: the model stays
    np.testing.assert_array_equal(lab._bodies.members, before)


def test_default_keeps_the_trained_bodies_and_adds_rigid_ones():
    pos, names = articulated(np.random.default_rng(1), subjects=2, frames=480)
    lab = Labeler(names, 120.0)  # 5 labeled frames: a thin structure, re-formed every 0.5 s
    out = _run(lab, np.random.default_rng(2), pos, 5)
    correct = sum(int((a[t >= 0] == t[t >= 0]).sum()) for a, t in out[5:])
    total = sum(int((t >= 0).sum()) for _, t in out[5:])
    assert correct / total > 0.99
    assert lab.restructures >= 1
    bd = lab._bodies
    now = {tuple(int(v) for v in bd.members[b, : bd.size[b]]) for b in range(bd.size.shape[0])}
    assert lab._trained < now  # every trained body stays, rigid ones were added


def test_recovery_sets_on_the_evidence_and_their_hysteresis():
    from labeler_service.labeling.restructure import better_set, recovery_sets

    D, A = _two_segments()
    c = LabelerConfig(recovery_set_size=3)
    sets = recovery_sets(D, A, np.ones(8, dtype=bool), c)
    assert sets[0][0] == 0 and set(sets[0][1:]) == {1, 2, 3}  # its own segment
    assert set(sets[5][1:]) == {4, 6, 7}
    # a set across the joint is replaced; one as rigid as the new one is not
    assert better_set(D, A, 0, [0, 1, 2, 3], [0, 1, 2, 4], c)
    assert not better_set(D, A, 0, [0, 1, 2, 3], [0, 3, 2, 1], c)
