"""Boot, re-identification, absent-subject and identity-swap scores (evaluation/scoring.py),
and the ``--leave`` corruption (scenes/corrupt.py).

The scorer is fed scripted answers whose scores are known by construction.
"""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture
from labeler_service.errors import SceneError
from labeler_service.evaluation.scoring import Scorer, score_labeler
from labeler_service.labeling.frame import LabeledFrame
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt

RATE = 100.0
# two subjects with the same marker set (same template) and a third with another one
NAMES = tuple(f"{s}:{m}" for s in ("A", "B") for m in ("m0", "m1", "m2", "m3", "m4")) + tuple(
    f"C:{m}" for m in ("x0", "x1", "x2", "x3", "x4")
)
M = len(NAMES)


def _frame(labels: np.ndarray) -> LabeledFrame:
    return LabeledFrame(
        t=0.0,
        point_labels=np.asarray(labels, dtype=np.int32),
        positions=np.full((M, 3), np.nan, dtype=np.float32),
        state=np.zeros(M, dtype=np.uint8),
    )


def _run(n_frames: int, truth_of, answer_of, init: int = 0, **kw) -> dict:
    sc = Scorer(NAMES, init, n_frames, rate=RATE, **kw)
    for f in range(n_frames):
        truth = np.asarray(truth_of(f), dtype=np.int64)
        sc.add(f, truth, _frame(answer_of(f, truth)))
    return sc.result().summary()


def _all(f: int) -> np.ndarray:
    return np.arange(M)


def test_boot_time_is_measured_from_presence_to_ten_good_frames():
    # A is labeled from frame 30 on, B from frame 12 on, C from the start
    def answer(f, truth):
        lab = truth.copy()
        if f < 30:
            lab[0:5] = -1
        if f < 12:
            lab[5:10] = -1
        return lab

    s = _run(100, _all, answer)
    assert s["boot_s"] == {"A": 0.30, "B": 0.12, "C": 0.0}
    assert s["boot_s_max"] == 0.30
    assert s["accuracy_after_boot"] == 1.0
    assert s["reid_s_p95"] is None and s["reid_s"] == []
    assert s["absent_labeled"] == 0 and s["identity_swaps"] == 0


def test_presence_needs_sixty_percent_of_the_template_and_a_run_must_be_unbroken():
    # A shows 2 of 5 markers until frame 20 (not present), then all; its labels are right from
    # frame 25 except one bad frame at 28, so the run of ten starts at 29
    def truth(f):
        cols = np.arange(M)
        return cols[(cols >= 3) | (f >= 20)]

    def answer(f, tr):
        lab = tr.copy()
        a = tr < 5
        if f < 25 or f == 28:
            lab[a] = -1
        return lab

    s = _run(80, truth, answer)
    assert s["boot_s"]["A"] == pytest.approx(0.09)  # present at 20, run from 29


def test_template_sizes_come_from_the_model():
    # B shows 3 of its 5 markers: present for a 5-marker template, not for a 6-marker one
    def truth(f):
        return np.array([0, 1, 2, 3, 4, 5, 6, 7, 10, 11, 12, 13, 14])

    s = _run(40, truth, lambda f, tr: tr)
    assert s["boot_s"]["B"] == 0.0
    s = _run(40, truth, lambda f, tr: tr, template_sizes={"A": 5, "B": 6, "C": 5})
    assert "B" not in s["boot_s"]


def test_never_booted_subject_makes_boot_s_max_null_and_is_left_out_of_accuracy():
    def answer(f, truth):
        lab = truth.copy()
        lab[10:15] = -1  # C never labeled
        lab[0] = 1 if f % 2 else 0  # A: one marker wrong every other frame (4/5 < 95 %)
        return lab

    s = _run(60, _all, answer)
    assert s["boot_s"]["C"] is None and s["boot_s"]["A"] is None
    assert s["boot_s_max"] is None
    assert s["accuracy_after_boot"] == 1.0  # only B booted, and B is always right


def test_reidentification_after_each_return():
    # B is gone in frames 40-59 and returns at 60; labeled again from 75. A is gone 20-29 and
    # its labels come back at once.
    def truth(f):
        cols = np.arange(M)
        keep = np.ones(M, dtype=bool)
        if 40 <= f < 60:
            keep[5:10] = False
        if 20 <= f < 30:
            keep[0:5] = False
        return cols[keep]

    def answer(f, tr):
        lab = tr.copy()
        if 60 <= f < 75:
            lab[(tr >= 5) & (tr < 10)] = -1
        return lab

    s = _run(120, truth, answer)
    assert sorted(s["reid_s"]) == [0.0, 0.15]
    assert s["reid_s_by_subject"] == {"A": [0.0], "B": [0.15]}  # which return took how long
    assert s["reid_s_p95"] == 0.15
    assert s["boot_s_max"] == 0.0


def test_a_return_never_relabeled_makes_reid_null():
    def truth(f):
        cols = np.arange(M)
        return cols[(cols >= 5) | (f < 30) | (f >= 40)]

    def answer(f, tr):
        lab = tr.copy()
        if f >= 40:
            lab[tr < 5] = -1
        return lab

    s = _run(90, truth, answer)
    assert s["reid_s"] == [None] and s["reid_s_p95"] is None


def test_absent_labeled_counts_labels_of_subjects_with_nothing_visible():
    # C is not in the volume (none of its markers visible); a ghost gets C:x0 in every frame
    # and, in frames 10-14, A's m0 point gets C:x1
    def truth(f):
        return np.concatenate([np.arange(10), [-1]])

    def answer(f, tr):
        lab = tr.copy()
        lab[-1] = 10
        if 10 <= f < 15:
            lab[0] = 11
        return lab

    s = _run(30, truth, answer)
    assert s["absent_labeled"] == 30 + 5
    assert s["errors"]["ghost_taken"] == 30
    assert "C" not in s["boot_s"]


def test_identity_swaps_count_whole_person_swaps_between_same_template_subjects():
    def answer(f, tr):
        lab = tr.copy()
        if 20 <= f < 30 or 50 <= f < 55:  # A and B fully swapped: 2 onsets per episode
            lab[0:5], lab[5:10] = tr[5:10], tr[0:5]
        if 70 <= f < 80:  # two of A's markers on B's: not a whole-person swap
            lab[0:2] = tr[5:7]
        return lab

    s = _run(100, _all, answer)
    assert s["identity_swaps"] == 4
    assert s["errors"]["cross_subject"] == 10 * 10 + 5 * 10 + 10 * 2


def test_cross_template_confusion_is_not_an_identity_swap():
    # C's markers given A's labels: different marker sets, no identity swap
    def answer(f, tr):
        lab = tr.copy()
        lab[10:15] = tr[0:5]
        lab[0:5] = -1
        return lab

    s = _run(40, _all, answer)
    assert s["identity_swaps"] == 0


def test_init_frames_are_not_scored_for_boot():
    def answer(f, tr):
        lab = tr.copy()
        if f < 20:
            lab[:] = -1
        return lab

    s = _run(60, _all, answer, init=20)
    assert s["boot_s_max"] == 0.0


# ---------------------------------------------------------------------------- score_labeler
class _Scripted:
    """A FrameLabeler over a model's marker list that answers the truth, mapped by name."""

    def __init__(self, model_names, stream_names, boot_frame: int):
        self._names = tuple(model_names)
        idx = {n: i for i, n in enumerate(self._names)}
        self._map = np.array([idx.get(n, -1) for n in stream_names])
        self.truth = None
        self.f = 0
        self.boot_frame = boot_frame

    @property
    def marker_names(self):
        return self._names

    def warmup(self):
        pass

    def body_extent(self):
        return np.full(len(self._names), 100.0)

    def process(self, points, t, labels=None):
        tr = self.truth[self.f]
        lab = np.where(tr >= 0, self._map[np.maximum(tr, 0)], -1)
        if self.f < self.boot_frame:
            lab[:] = -1
        if self.f >= self.boot_frame + 20:
            lab[tr < 0] = len(self._names) - 1  # ghosts get the absent subject's last marker
        self.f += 1
        m = len(self._names)
        return LabeledFrame(t, lab.astype(np.int32), np.full((m, 3), np.nan, np.float32),
                            np.zeros(m, np.uint8))  # fmt: skip


def _model(subjects: dict[str, list[str]]) -> LabelerModel:
    """A valid model of the given markers (the scorer only reads names): every marker on a
    circle of radius 100 mm, one rigid body of the first three."""
    from labeler_service.labeling.templates import make_subject

    out = []
    for s, mk in subjects.items():
        m = len(mk)
        a = 2 * np.pi * np.arange(m) / m
        p = np.stack([100 * np.cos(a), 100 * np.sin(a), 10.0 * np.arange(m)], axis=1)
        D = np.linalg.norm(p[:, None] - p[None], axis=2)
        A = np.where(np.eye(m, dtype=bool), 0.0, 1.0)
        body = [0, 1, 2]
        shape = p[body] - p[body].mean(axis=0)
        out.append(make_subject(s, list(mk), D, A, [body], [shape], np.full(m, 1e6)))
    return LabelerModel(rate=RATE, subjects=out)


def test_score_labeler_maps_model_markers_and_counts_absent_subjects(rng):
    n = 60
    pos = rng.normal(0, 500, (n, 11, 3)).astype(np.float32)
    names = NAMES[:10] + ("*0",)
    cap = Capture(pos, names, RATE)
    stream = corrupt(cap, CorruptionSpec(seed=1))
    model = _model({"B": ["m0", "m1", "m2", "m3", "m4"], "A": ["m0", "m1", "m2", "m3", "m4"],
                    "Z": ["z0", "z1", "z2"]})  # fmt: skip
    lab = _Scripted(model.marker_names, stream.marker_names, boot_frame=5)
    lab.truth = stream.truth
    res = score_labeler(lab, stream, 0, "online", model=model)
    s = res.summary()
    assert s["boot_s"] == {"A": 0.05, "B": 0.05}
    assert s["accuracy_after_boot"] == 1.0
    assert s["absent_labeled"] == n - 25  # one ghost per frame from frame 25 gets Z:z2
    assert s["ghost_labeled_rate"] == pytest.approx((n - 25) / n)


# ---------------------------------------------------------------------------- --leave
def _walkers(rng, subjects=3, n=300):
    names = tuple(f"P{s}:m{k}" for s in range(1, subjects + 1) for k in range(4))
    base = rng.normal(0, 100, (len(names), 3))
    for s in range(subjects):
        base[4 * s : 4 * s + 4, 0] += 2000 * s
    t = np.arange(n)[:, None, None] / RATE
    pos = base[None] + np.array([300.0, 0, 0]) * t
    return Capture(pos.astype(np.float32), names, RATE)


def test_leave_removes_subjects_once_and_brings_them_back_displaced(rng):
    cap = _walkers(rng)
    spec = CorruptionSpec(leave=2, leave_seconds=0.5, protect_frames=20, seed=3, shuffle=False)
    st = corrupt(cap, spec)
    assert len(st.departures) == 2
    assert len({d[0] for d in st.departures}) == 2
    for subject, f0, back in st.departures:
        assert back - f0 == 50 and f0 >= 20 and back + 50 <= cap.n_frames
        cols = [i for i, n in enumerate(st.marker_names) if n.startswith(subject + ":")]
        assert np.isnan(st.positions[f0:back, cols]).all()
        for f in range(f0, back):
            assert not np.isin(st.truth[f], cols).any()
        # rigid: distances kept; displaced: horizontal move <= 1 m, height kept
        a, b = cap.positions[back, cols], st.positions[back, cols]
        da = np.linalg.norm(a[:, None] - a[None], axis=2)
        db = np.linalg.norm(b[:, None] - b[None], axis=2)
        np.testing.assert_allclose(da, db, atol=1e-2)
        np.testing.assert_allclose(a[:, 2], b[:, 2], atol=1e-3)
        shift = np.linalg.norm(b.mean(0)[:2] - a.mean(0)[:2])
        spread = np.linalg.norm(a[:, :2] - a.mean(0)[:2], axis=1).max()
        assert shift <= 1000.0 + spread + 1e-3
        assert np.isfinite(st.positions[f0 - 1, cols]).all()
    stayed = {n.split(":")[0] for n in st.marker_names} - {d[0] for d in st.departures}
    cols = [i for i, n in enumerate(st.marker_names) if n.split(":")[0] in stayed]
    np.testing.assert_array_equal(st.positions[:, cols], cap.positions[:, cols])
    again = corrupt(cap, spec)
    assert again.departures == st.departures
    np.testing.assert_array_equal(np.nan_to_num(again.positions), np.nan_to_num(st.positions))


def test_leave_errors(rng):
    cap = _walkers(rng, subjects=2, n=100)
    with pytest.raises(SceneError, match="only 2 subjects"):
        corrupt(cap, CorruptionSpec(leave=3))
    with pytest.raises(SceneError, match="does not fit"):
        corrupt(cap, CorruptionSpec(leave=1, leave_seconds=0.6))
    with pytest.raises(SceneError, match="--leave-seconds must be positive"):
        CorruptionSpec(leave=1, leave_seconds=0.0)


def test_leave_picks_performers_present_through_the_return(rng):
    """In a composed scene a short take ends inside the window (its performer leaves the
    volume). ``--leave`` picked such a performer, or a departure after his take ended, and
    his return was into nothing: no return to re-identify. A departure now ends, and the
    performer stays ``leave_seconds`` after it, before his take does."""
    cap = _walkers(rng, subjects=3)
    pos = cap.positions.copy()
    pos[150:, 4:8] = np.nan  # P2's take ends at frame 150
    cap = cap.with_positions(pos)
    picked_p2 = 0
    for seed in range(40):
        st = corrupt(cap, CorruptionSpec(leave=2, leave_seconds=0.5, protect_frames=20, seed=seed))
        for subject, f0, back in st.departures:
            cols = [i for i, n in enumerate(st.marker_names) if n.startswith(subject + ":")]
            after = np.isfinite(st.positions[back : back + 50, cols, 0]).any(axis=1)
            assert after.all(), (seed, subject, f0, back)
            picked_p2 += subject == "P2"
    assert picked_p2 > 0  # a performer whose take ends is still chosen when his return fits
    pos[40:, 4:8] = np.nan  # P2 gone before a departure and a return fit
    with pytest.raises(SceneError, match="present"):
        corrupt(cap.with_positions(pos), CorruptionSpec(leave=3, leave_seconds=0.5))
    st = corrupt(cap.with_positions(pos), CorruptionSpec(leave=2, leave_seconds=0.5))
    assert {d[0] for d in st.departures} == {"P1", "P3"}


def test_scorer_sees_leave_returns(rng):
    """An oracle labeler on a --leave stream: every return is re-identified at once."""
    cap = _walkers(rng)
    st = corrupt(cap, CorruptionSpec(leave=2, leave_seconds=0.3, seed=5))
    sc = Scorer(st.marker_names, 0, st.n_frames, rate=st.rate)
    for f in range(st.n_frames):
        sc.add(f, st.truth[f], _oracle(st.truth[f], len(st.marker_names)))
    s = sc.result().summary()
    assert s["reid_s"] == [0.0, 0.0] and s["reid_s_p95"] == 0.0
    assert s["absent_labeled"] == 0


def _oracle(truth: np.ndarray, m: int) -> LabeledFrame:
    return LabeledFrame(0.0, truth.astype(np.int32), np.full((m, 3), np.nan, np.float32),
                        np.zeros(m, np.uint8))  # fmt: skip


def test_boot_over_the_known_markers_leaves_out_markers_the_labeler_cannot_name():
    # C's labeler knows x0-x3 but not x4 (its model was trained without it): C's labels are
    # right from frame 15 on and x4 is never labeled, so 4 of 5 visible markers are right (80 %)
    # and C never boots by the 95 % criterion; counted over its known markers it boots at 0.15 s
    known = np.ones(M, dtype=bool)
    known[NAMES.index("C:x4")] = False

    def answer(f, truth):
        lab = truth.copy()
        lab[truth == NAMES.index("C:x4")] = -1
        if f < 15:
            lab[10:15] = -1
        return lab

    s = _run(60, _all, answer, known=known)
    assert s["boot_s"]["C"] is None
    assert s["boot_s_known"] == {"A": 0.0, "B": 0.0, "C": 0.15}
    # a labeler that knows every marker: no second criterion
    assert _run(60, _all, answer)["boot_s_known"] == {}


def test_a_labeled_start_counts_boot_over_the_markers_its_init_frames_showed():
    # C:x4 is hidden through the 10 labeled frames, so the start never learns it: it shows up
    # at frame 12 and stays unlabeled. C (4 of 5 visible right after that) never boots by the
    # 95 % criterion; over the markers the init frames showed it boots at once
    x4 = NAMES.index("C:x4")

    def truth_of(f):
        return np.arange(M) if f >= 12 else np.delete(np.arange(M), x4)

    def answer(f, truth):
        return np.where(truth == x4, -1, truth)

    s = _run(60, truth_of, answer, init=10)
    assert s["unseen_at_init"] == 48
    assert s["boot_s"]["C"] is None
    assert s["boot_s_known"] == {"A": 0.0, "B": 0.0, "C": 0.0}
    # every marker shown in the labeled frames: no second criterion
    assert _run(60, _all, answer, init=10)["boot_s_known"] == {}
