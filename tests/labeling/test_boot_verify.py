"""Re-verification of booted subjects over time (labeling/boot_verify.py) and the
``Labeler`` calls it uses (``withdraw_markers``, ``seed_markers``)."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture
from labeler_service.errors import LabelerError
from labeler_service.labeling.boot import BootConfig, Booter
from labeler_service.labeling.boot_verify import BootVerifier, extend_blocked
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.simulate import simulate_scene

RATE = 120.0


def _train(capture: Capture) -> LabelerModel:
    from offline.structure import StructureTrainer

    return StructureTrainer().fit([capture]).model_


@pytest.fixture(scope="module")
def scene():
    """Three simulated walkers; model from the first half, the second half verified."""
    cap = simulate_scene(3, 6.0, "walk", seed=5, rate=RATE, ghosts=0.0)
    half = cap.n_frames // 2
    model = _train(cap.frames(0, half))
    test = cap.frames(half, cap.n_frames)
    col = {lab: i for i, lab in enumerate(test.labels)}
    gidx = np.array([col[n] for n in model.marker_names])
    pos = test.positions[:, gidx].astype(np.float64)  # (F, M, 3) in model marker order
    return model, pos


def _index(model: LabelerModel, names: list[str]) -> np.ndarray:
    idx = {n: i for i, n in enumerate(model.marker_names)}
    return np.array([idx[n] for n in names], dtype=np.int64)


def _run(model, pos, *, swap=None, config=None, frames=None):
    """Feeds the verifier every frame of ``pos`` (all subjects verified from the start);
    ``swap = (markers, sources)``: those markers sit on the sources' points (and tracks), the
    sources are unlabeled.
    Returns the verifier and ``[(frame, verdict)]``."""
    cfg = config or BootConfig()
    v = BootVerifier(Booter(model, cfg), RATE, cfg)
    for s in range(len(model.subjects)):
        v.start(s)
    m = pos.shape[1]
    track = np.arange(m, dtype=np.int64)
    out = []
    for f in range(frames or pos.shape[0]):
        p = pos[f].copy()
        tr = track.copy()
        if swap is not None:
            p[swap[0]] = pos[f, swap[1]]
            tr[swap[0]] = swap[1]
            p[swap[1]] = np.nan  # (a point carries one label: the source lost it)
        obs = np.isfinite(p[:, 0])
        tr[~obs] = -1
        verdict = v.update(p, obs, tr)
        if verdict is not None:
            out.append((f, verdict))
    return v, out


def _withdrawn(model, verdicts) -> set[str]:
    names = model.marker_names
    return {names[k] for _, v in verdicts for mk in v.withdraw.values() for k in mk}


def test_right_labels_are_never_withdrawn(scene):
    model, pos = scene
    v, verdicts = _run(model, pos)
    assert verdicts == []
    assert v.withdrawn == 0 and v.dropped == 0
    assert v.ea.size > 0 and (v.joint >= 0).any()  # rigid and joint edges were checked


def test_a_partners_forearm_and_hand_are_withdrawn(scene):
    """P1's right forearm and hand labeled on P2's (the hug failure): the joint between P1's
    upper arm and forearm breaks; forearm and hand are withdrawn, nothing else."""
    model, pos = scene
    seg = ["RFRM", "RWRA", "RWRB", "RFIN", "RHM2", "RHM5"]
    seg = [s for s in seg if f"P1:{s}" in model.marker_names]
    mk = _index(model, [f"P1:{s}" for s in seg])
    src = _index(model, [f"P2:{s}" for s in seg])
    _, verdicts = _run(model, pos, swap=(mk, src))
    assert verdicts, "the wrong segment was never withdrawn"
    first = verdicts[0][0]
    assert first / RATE < 1.0  # evidence over a few tenths of a second
    assert _withdrawn(model, verdicts) <= {f"P1:{s}" for s in seg}
    assert {f"P1:{s}" for s in ("RFRM", "RWRA", "RWRB")} <= _withdrawn(model, verdicts)
    assert all(not v.drop for _, v in verdicts)


def test_one_marker_on_a_partners_point_is_withdrawn_alone(scene):
    model, pos = scene
    mk = _index(model, ["P1:LSHO"])
    src = _index(model, ["P2:LSHO"])
    _, verdicts = _run(model, pos, swap=(mk, src))
    assert verdicts
    assert _withdrawn(model, verdicts) == {"P1:LSHO"}


def test_a_subject_mostly_wrong_is_dropped(scene):
    """Half of P1's markers on P3's points (arms, legs, head; the trunk is P1's): dropped."""
    model, pos = scene
    p1 = [n for n in model.marker_names if n.startswith("P1:")]
    trunk = {"C7", "T10", "CLAV", "STRN", "RBAK", "LSHO", "RSHO", "LASI", "RASI", "LPSI", "RPSI"}
    moved = [n for n in p1 if n.split(":")[1] not in trunk]
    mk = _index(model, moved)
    src = _index(model, ["P3:" + n.split(":")[1] for n in moved])
    cfg = BootConfig(verify_drop=0.3)
    _, verdicts = _run(model, pos, swap=(mk, src), config=cfg)
    assert any(0 in v.drop for _, v in verdicts)
    # a joint at a time would withdraw less than 0.3 of P1's markers: no drop then
    _, kept = _run(model, pos, swap=(mk[:3], src[:3]), config=cfg)
    assert not any(0 in v.drop for _, v in kept)


def test_hidden_markers_give_no_evidence(scene):
    """A marker that is not observed is never judged: hiding half of P1 withdraws nothing."""
    model, pos = scene
    p = pos.copy()
    p1 = np.flatnonzero([n.startswith("P1:") for n in model.marker_names])
    p[::2, p1[::2]] = np.nan
    p[1::2, p1[1::2]] = np.nan
    _, verdicts = _run(model, p)
    assert verdicts == []


def test_stopped_subjects_are_not_verified(scene):
    model, pos = scene
    seg = _index(model, ["P1:RFRM", "P1:RWRA", "P1:RWRB"])
    src = _index(model, ["P2:RFRM", "P2:RWRA", "P2:RWRB"])
    cfg = BootConfig()
    v = BootVerifier(Booter(model, cfg), RATE, cfg)
    v.start(1)  # P2 only
    for f in range(pos.shape[0]):
        p = pos[f].copy()
        p[seg] = pos[f, src]
        assert v.update(p, np.isfinite(p[:, 0]), np.arange(p.shape[0])) is None


def test_extend_blocked_keeps_blocked_points_from_their_subject(scene):
    """A booted subject's free points: the extension places them, unless they are blocked for
    that subject."""
    model, pos = scene
    booter = Booter(model, BootConfig())
    f = 100
    w = 12
    hist = np.transpose(pos[f - w + 1 : f + 1], (1, 0, 2))  # (M, W, 3): one point per marker
    pts = pos[f]
    labels = np.arange(pos.shape[1], dtype=np.int64)
    free = _index(model, ["P1:RFRM", "P1:RWRA", "P1:RWRB"])
    labels[free] = -1
    plain = extend_blocked(booter, pts, hist, labels, [0, 1, 2], None)
    assert np.array_equal(plain[free], free)  # (the control: placed back without blocks)
    block = np.zeros(pts.shape[0], dtype=bool)
    block[free] = True
    out = extend_blocked(booter, pts, hist, labels, [0, 1, 2], {0: block})
    assert np.all(out[free] == -1)
    # a block of another subject does not matter
    out = extend_blocked(booter, pts, hist, labels, [0, 1, 2], {1: block})
    assert np.array_equal(out[free], free)


def test_labeler_withdraw_markers_then_seed_them_again(scene):
    """``Labeler.withdraw_markers``: the markers take no point until ``seed_markers``; the
    other markers keep labeling."""
    model, pos = scene
    lab = Labeler.from_model(model, RATE, subjects=())
    m = pos.shape[1]

    def frame(f):
        seen = np.flatnonzero(np.isfinite(pos[f, :, 0]))
        return f / RATE, pos[f, seen].astype(np.float32), seen

    lab.add_subjects([s.name for s in model.subjects], [frame(f) for f in range(12)])
    gone = _index(model, ["P1:RFRM", "P1:RWRA", "P1:RWRB"])
    lab.withdraw_markers(gone)
    assert set(lab.active_subjects) == {s.name for s in model.subjects}
    right = seen_total = 0
    for f in range(12, 40):
        t, pts, truth = frame(f)
        got = lab.process(pts, t).point_labels
        assert not np.isin(got, gone).any()
        others = ~np.isin(truth, gone)
        right += int(np.sum(got[others] == truth[others]))
        seen_total += int(others.sum())
    assert right > 0.99 * seen_total  # the other markers keep labeling
    lab.seed_markers(gone, [frame(f) for f in range(28, 40)])
    hits = visible = 0
    for f in range(40, 60):
        t, pts, truth = frame(f)
        got = lab.process(pts, t).point_labels
        mine = np.isin(truth, gone)
        hits += int(np.sum(got[mine] == truth[mine]))
        visible += int(mine.sum())
    assert visible > 0 and hits >= 0.9 * visible
    with pytest.raises(LabelerError):
        lab.withdraw_markers([m + 5])
    with pytest.raises(LabelerError):  # (nothing built yet)
        Labeler(["x:a", "x:b", "x:c"], RATE).withdraw_markers([0])


def test_the_frame_cost_benchmark_times_both_settings_on_one_stream():
    """``benchmarks/boot_frame_cost.py``: one run per ``--verify`` value on the same frames;
    with re-verification off nothing is withdrawn, and every run times the same frames."""
    import contextlib
    import io
    import json

    from benchmark_scripts import load_benchmark

    bench = load_benchmark("boot_frame_cost")
    argv = ["--subjects", "3", "--rate", "120", "--seconds", "1", "--train-seconds", "2"]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert bench.main([*argv, "--verify", "off", "on"]) == 0
    out = json.loads(buf.getvalue())
    off, on = out["runs"]
    assert (off["verify"], on["verify"]) == (False, True)
    assert off["withdrawals"] == 0
    assert off["frames_timed"] == on["frames_timed"] == 120 - 60
    assert 0 < off["process_ms_p50"] <= off["process_ms_p99"] <= off["process_ms_p99_9"]


def test_the_catch_up_benchmark_boots_and_digests_the_same_labels_twice():
    """``benchmarks/catch_up_cost.py``: the first attempt boots the scene's performers, and the
    label digest (what its speed-ups are checked against) is the same in a second run."""
    import contextlib
    import io
    import json

    from benchmark_scripts import load_benchmark

    bench = load_benchmark("catch_up_cost")
    argv = ["--subjects", "3", "--rate", "120", "--seconds", "2", "--train-seconds", "2",
            "--late-s", "0.3", "--after-s", "0.5"]  # fmt: skip
    outs = []
    for _ in range(2):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert bench.main(argv) == 0
        outs.append(json.loads(buf.getvalue()))
    assert outs[0]["subjects_booted"] == 3 and outs[0]["attempt_cpu_ms"] > 0
    assert outs[0]["labels_sha256"] == outs[1]["labels_sha256"]


@pytest.mark.realdata
def test_a_body_trained_still_across_a_joint_keeps_its_right_labels(real_path):
    """A model trained on 0.56 s of a kneeling performer made the lower-back plate and two
    pelvis markers one rigid body (deviations under 1 mm); once she bends, the plate's pairs to
    the pelvis are 50 mm off. Those labels are right: the plate's markers each keep three pairs
    of their body, so none is withdrawn - also next to a walker (``verify_contact_mm`` 0: every
    marker counts as in contact). Without the support rule (``verify_support`` past any count)
    the plate is withdrawn, as it was on the ``--start boot`` matrix (tune27)."""
    from labeler_service.scenes.compose import TakeSpec, compose_scene

    kneel = real_path("kneel_to_prone_62markers_240hz.c3d")
    gait = real_path("clinical_gait_pig_35markers_100hz.c3d")
    train = compose_scene(
        [TakeSpec(path=gait), TakeSpec(path=kneel)], radius=220.0, frames=56, seed=128, rate=100.0
    )
    model = _train(train)
    test = compose_scene(
        [TakeSpec(path=gait, start=56), TakeSpec(path=kneel, start=285)],
        radius=220.0,
        frames=608,
        seed=127,
        rate=100.0,
    )
    col = {lab: i for i, lab in enumerate(test.labels)}
    gidx = np.array([col[n] for n in model.marker_names])
    pos = test.positions[:, gidx].astype(np.float64)
    plate = {f"kneel_to_prone_62markers_240hz:{m}" for m in ("LBUL", "LBLL", "LBUR", "LBLR")}
    subject = model.subjects[
        [s.name for s in model.subjects].index("kneel_to_prone_62markers_240hz")
    ]
    body = [
        b
        for b in subject.bodies
        if {subject.markers[i] for i in b} >= {m.split(":")[1] for m in plate}
    ]
    assert body, "the still training no longer glues the plate into one body: test moot"

    def withdrawn(support: int) -> set[str]:
        cfg = BootConfig(verify_contact_mm=0.0, verify_support=support)
        v = BootVerifier(Booter(model, cfg), 100.0, cfg)
        for s in range(len(model.subjects)):
            v.start(s)
        track = np.arange(pos.shape[1], dtype=np.int64)
        out = []
        for f in range(pos.shape[0]):
            obs = np.isfinite(pos[f, :, 0])
            verdict = v.update(pos[f], obs, np.where(obs, track, -1))
            if verdict is not None:
                out.append((f, verdict))
        return _withdrawn(model, out)

    assert not plate & withdrawn(BootConfig().verify_support)
    assert plate & withdrawn(10_000)
