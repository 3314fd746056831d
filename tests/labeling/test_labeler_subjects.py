"""Subjects added to and dropped from a running labeler (``Labeler.add_subjects``,
``seed_markers``, ``drop_subject``): the others' state is untouched, no rebuild."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.scene import articulated, frame_points
from labeling.test_labeler import INIT, run

from labeler_service.errors import LabelerError
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.labeler import Labeler

RATE = 120.0
W = 12  # labeled frames a subject is added from


@pytest.fixture()
def scene(rng):
    pos, names = articulated(rng, subjects=3, frames=400)
    trainer = Labeler(names, RATE)
    run(trainer, rng, pos[: INIT + 1])
    model = trainer.model
    perm = [names.index(n) for n in model.marker_names]  # the model's marker order
    return model, pos[:, perm]


def _subject(model, name: str) -> np.ndarray:
    return np.array([i for i, n in enumerate(model.marker_names) if n.startswith(f"{name}:")])


def _state(lab: Labeler, markers: np.ndarray) -> list[np.ndarray]:
    tr, rc = lab._tracks, lab._recovery
    return [a[markers].copy() for a in (tr.x, tr.P, tr.age, tr.state, tr.pos, rc.ref, rc.ok)]


def _window(rng, pos, frames, labeled):
    """Labeled frames ``(t, points, labels)`` with the labels of markers ``labeled`` only."""
    out = []
    for f in frames:
        pts, truth = frame_points(rng, pos[f])
        out.append((f / RATE, pts, np.where(np.isin(truth, labeled), truth, -1)))
    return out


def test_subjects_are_added_and_dropped_without_touching_the_others(rng, scene):
    model, pos = scene
    p0, p1, p2 = (_subject(model, s) for s in ("P0", "P1", "P2"))
    lab = Labeler.from_model(model, RATE, subjects=())
    assert not lab.trained and lab.active_subjects == ()
    lab.add_subjects(["P0"], _window(rng, pos, range(W), p0))
    assert lab.trained and lab.active_subjects == ("P0",)

    def stream(frames, mine, never):
        ok = tot = 0
        for f in frames:
            pts, truth = frame_points(rng, pos[f])
            out = lab.process(pts, f / RATE)
            assert not np.isin(out.point_labels, never).any()
            want = np.isin(truth, mine)
            ok += int(np.count_nonzero(out.point_labels[want] == truth[want]))
            tot += int(want.sum())
            assert np.all(out.state[never] == MarkerState.MISSING)
        return ok / tot

    assert stream(range(W, 100), p0, np.concatenate([p1, p2])) == 1.0
    before = _state(lab, p0)
    bodies = lab._bodies.s1.copy()
    lab.add_subjects(["P1"], _window(rng, pos, range(100 - W, 100), np.concatenate([p0, p1])))
    for a, b in zip(before, _state(lab, p0), strict=True):
        np.testing.assert_array_equal(a, b)  # P0's labels in the window were not read
    added = lab._subject_bodies["P1"]
    kept = np.setdiff1d(np.arange(bodies.shape[0]), added)
    np.testing.assert_array_equal(bodies[kept], lab._bodies.s1[kept])
    assert np.any(lab._bodies.s1[added] > 0)  # P1's window starts from the labeled frames
    assert lab.active_subjects == ("P0", "P1")
    assert stream(range(100, 200), np.concatenate([p0, p1]), p2) == 1.0

    before = _state(lab, p1)
    lab.drop_subject("P0")
    for a, b in zip(before, _state(lab, p1), strict=True):
        np.testing.assert_array_equal(a, b)
    assert lab.active_subjects == ("P1",)
    assert stream(range(200, 300), p1, np.concatenate([p0, p2])) == 1.0
    lab.add_subjects(["P0"], _window(rng, pos, range(300 - W, 300), p0))
    assert stream(range(300, 400), np.concatenate([p0, p1]), p2) == 1.0


def test_adding_every_subject_starts_like_labeled_first_frames(rng, scene):
    """``add_subjects`` from W labeled frames seeds the Kalman states as the labeled start of
    ``from_model`` does from the same frames."""
    model, pos = scene
    every = np.arange(len(model.marker_names))
    window = _window(rng, pos, range(W), every)
    ref = Labeler.from_model(model, RATE)
    for t, pts, lab in window:
        ref.process(pts, t, lab)
    inc = Labeler.from_model(model, RATE, subjects=())
    inc.add_subjects([s.name for s in model.subjects], window)
    for f in range(W, 150):
        pts, truth = frame_points(rng, pos[f])
        a, b = ref.process(pts, f / RATE), inc.process(pts, f / RATE)
        if f == W:  # the same Kalman states and windows after the same labeled frames
            np.testing.assert_allclose(inc._tracks.x, ref._tracks.x, rtol=1e-9, atol=1e-6)
            np.testing.assert_allclose(inc._bodies.D, ref._bodies.D, rtol=1e-9, equal_nan=True)
        np.testing.assert_array_equal(a.point_labels, b.point_labels)
        np.testing.assert_array_equal(b.point_labels, truth)


def test_seed_markers_starts_a_marker_hidden_when_its_subject_was_added(rng, scene):
    model, pos = scene
    p0 = _subject(model, "P0")
    late = p0[2]
    lab = Labeler.from_model(model, RATE, subjects=["P0"])
    lab.add_subjects([], [(0.0, pos[0], np.full(pos.shape[1], -1))])  # no-op: nothing to add
    assert not lab.trained
    # as the booting labeler builds its inner labeler: a marker never observed is its to place
    # (without acquire_unseen off the kernel places it itself: test_unseen_markers.py)
    inner = LabelerConfig(acquire_unseen=False)
    lab = Labeler.from_model(model, RATE, inner, subjects=())
    lab.add_subjects(["P0"], _window(rng, pos, range(W), p0[p0 != late]))
    assert np.isnan(lab._tracks.x[late]).all()
    for f in range(W, 60):
        pts, _ = frame_points(rng, pos[f])
        out = lab.process(pts, f / RATE)
        assert out.state[late] == MarkerState.MISSING  # never seen: no state to gate from
    lab.seed_markers([late], _window(rng, pos, range(60 - W, 60), p0))
    before = _state(lab, p0[p0 != late])
    lab.seed_markers([late], _window(rng, pos, range(60 - W, 60), p0))
    for a, b in zip(before, _state(lab, p0[p0 != late]), strict=True):
        np.testing.assert_array_equal(a, b)
    for f in range(60, 120):
        pts, truth = frame_points(rng, pos[f])
        out = lab.process(pts, f / RATE)
        assert out.point_labels[truth == late] == late


def test_subject_call_errors(rng, scene):
    model, pos = scene
    with pytest.raises(LabelerError, match="not in the model"):
        Labeler.from_model(model, RATE, subjects=["nobody"])
    lab = Labeler.from_model(model, RATE, subjects=["P0"])
    window = _window(rng, pos, range(3), np.arange(len(model.marker_names)))
    with pytest.raises(LabelerError, match="labeled already"):
        lab.add_subjects(["P0"], window)
    with pytest.raises(LabelerError, match="not in the model"):
        lab.add_subjects(["nobody"], window)
    with pytest.raises(LabelerError, match="not in the model"):
        lab.drop_subject("nobody")
    with pytest.raises(LabelerError, match="at least one labeled frame"):
        lab.add_subjects(["P1"], [])
    with pytest.raises(LabelerError, match="active subjects only"):
        lab.seed_markers(_subject(model, "P1"), window)
    t, pts, labels = window[0]
    lab.process(pts, t, labels)
    with pytest.raises(LabelerError, match="pending"):
        lab.add_subjects(["P1"], window)
    with pytest.raises(LabelerError, match="only to a labeler from a model"):
        Labeler(model.marker_names, RATE).add_subjects(["P0"], window)


@pytest.fixture(scope="module")
def walkers():
    """Three walkers streamed, a model of five (as ``test_boot.walk``)."""
    from labeling.walks import absent_walk

    return absent_walk(RATE)


def test_booting_labeler_installs_a_later_subject_without_a_rebuild(walkers):
    """P3 enters later: its boot adds it to the inner labeler (the same object throughout) and
    leaves P1's and P2's Kalman states, windows and recovery snapshots as they were."""
    from labeling.test_boot import Stream, _run

    from labeler_service.labeling.booting import BootingLabeler

    model, cap = walkers
    pos = cap.positions.copy()
    pos[:90, [i for i, n in enumerate(cap.labels) if n.startswith("P3:")]] = np.nan
    lab = BootingLabeler(model, RATE)
    inner = lab._inner
    subj = np.array([n.split(":")[0] for n in model.marker_names])
    seen = []

    def spy(names, frames):
        others = ~np.isin(subj, list(names))
        bodies = np.setdiff1d(
            np.arange(inner._bodies.s1.shape[0]),
            np.concatenate([inner._subject_bodies[n] for n in names]),
        )
        state = lambda: [  # noqa: E731
            *(a[others].copy() for a in (inner._tracks.x, inner._tracks.P, inner._recovery.ref)),
            *(a[bodies].copy() for a in (inner._bodies.s1, inner._bodies.cnt, inner._bodies.D)),
        ]
        before = state()
        type(inner).add_subjects(inner, names, frames)
        for a, b in zip(before, state(), strict=True):
            np.testing.assert_array_equal(a, b)
        seen.append(tuple(names))

    inner.add_subjects = spy
    outs, truths = _run(lab, Stream(cap.with_positions(pos), model, seed=4), range(cap.n_frames))
    assert lab._inner is inner
    assert ("P3",) in seen and sorted(n for names in seen for n in names) == ["P1", "P2", "P3"]
    p3 = subj == "P3"
    tail = slice(90 + round(0.5 * RATE), None)
    ok = vis = 0
    for o, t in zip(outs[tail], truths[tail], strict=True):
        m = (t >= 0) & p3[np.maximum(t, 0)]
        ok += int(np.count_nonzero(o.point_labels[m] == t[m]))
        vis += int(m.sum())
    assert ok / vis >= 0.9


def test_labels_without_a_subject_prefix_train_one_unnamed_subject(rng):
    """A single performer streamed with bare marker names (``LASI``, no ``subject:``): the
    labeler trained in place groups them as subject ``""`` and its model gives the bare names
    back (:attr:`SubjectTemplate.labels`); it used to look for ``":LASI"`` and refuse."""
    pos, names = articulated(rng, subjects=1)
    bare = tuple(n.split(":", 1)[1] for n in names)
    lab = Labeler(list(bare), rate=120.0)
    acc, _, _ = run(lab, rng, pos)
    assert lab.model is not None
    assert [s.name for s in lab.model.subjects] == [""]
    assert lab.model.marker_names == bare
    assert acc > 0.99
