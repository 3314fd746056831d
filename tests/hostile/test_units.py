"""A sender that streams metres to a model stream: the points are a thousand times closer than
the model's subjects, nothing is ever labeled and the stream read ``booting`` for good, as if
nobody were in the volume, with no word of why. Now the log says what is wrong, while the
stream keeps flowing (every frame still published, nothing dropped)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from hostile.helpers import collect, frames_of, run, settings
from service.helpers import until
from synthetic import moving_clusters

from labeler_service.labeling.templates import LabelerModel, load_model, save_model
from labeler_service.labeling.training import train_subject
from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport
from labeler_service.service.units import UnitCheck, init_span_warning

TRAIN = 60


@pytest.fixture(scope="module")
def scene():
    return moving_clusters(np.random.default_rng(5), subjects=2, markers=6, frames=TRAIN + 360)


@pytest.fixture(scope="module")
def model_path(scene, tmp_path_factory):
    subjects = []
    for s in scene.subjects:
        cols = scene.subject_columns(s)
        markers = [scene.labels[c].split(":")[1] for c in cols]
        subjects.append(train_subject(s, markers, scene.positions[:TRAIN, cols], scene.rate))
    path = tmp_path_factory.mktemp("units") / "model.json"
    save_model(LabelerModel(rate=scene.rate, subjects=subjects), path)
    return path


async def _serve(model_path, items):
    """A booting stream of the model at ``model_path`` fed the encoded frames ``items``:
    ``(server, labeled messages)``."""
    mem = MemoryTransport()
    over = {"streams": [{"name": "vol", "model": str(model_path)}], "boot": True,
            "boot_worker": "thread"}  # fmt: skip
    async with Server(settings(**over), [mem]) as srv:
        for p in items:
            mem.inject(p)
        # (every frame handled first: a frame whose kernels compile, on a cold cache, holds the
        # stream's worker for seconds with its queue empty, which ``collect`` took for idle; the
        # callers allow for a first boot attempt that compiles, ~1 min on a loaded machine)
        await until(
            lambda: srv.metrics.value("mocap_frames_out_total", stream="vol")
            + srv.metrics.drops() >= len(items), "every frame handled", timeout=180.0,
        )  # fmt: skip
        return srv, await collect(srv, mem, "vol")


def _stream(scene, model_path, scale: float, caplog):
    frames = frames_of(scene, np.random.default_rng(1))
    items = [
        encode_frame("vol", k, k / scene.rate, frames[f][0] * np.float32(scale))
        for k, f in enumerate(range(TRAIN, scene.n_frames))
    ]

    with caplog.at_level(logging.WARNING, logger="labeler_service.service.server"):
        srv, msgs = run(_serve(model_path, items), timeout=240.0)
    warned = [r.getMessage() for r in caplog.records
              if "Points travel in millimetres" in r.getMessage()]  # fmt: skip
    return srv, msgs, warned, len(items)


def test_points_in_metres_are_named_in_the_log(scene, model_path, caplog):
    srv, msgs, warned, n = _stream(scene, model_path, 1e-3, caplog)
    assert len(msgs) == n and srv.metrics.drops() == 0  # the stream flows as before
    assert warned, [r.getMessage() for r in caplog.records]
    assert "stream vol" in warned[0] and "metres" in warned[0]


def test_points_in_millimetres_give_no_such_warning(scene, model_path, caplog):
    srv, msgs, warned, n = _stream(scene, model_path, 1.0, caplog)
    assert len(msgs) == n and not warned


def test_the_check_waits_for_a_window_with_nothing_labeled_and_restarts_on_a_label(model_path):
    model = load_model(model_path)
    small = np.random.default_rng(0).normal(scale=0.3, size=(6, 3)).astype(np.float32)  # metres
    chk = UnitCheck()
    # 1.9 s of frames with nothing labeled: not yet
    assert all(chk.update("v", small, k / 100, 0, model) is None for k in range(190))
    assert chk.update("v", small, 1.9, 3, model) is None  # a label restarts the window
    assert all(chk.update("v", small, 1.9 + k / 100, 0, model) is None for k in range(1, 200))
    assert "metres" in (chk.update("v", small, 3.95, 0, model) or "")
    # no model (the baseline, a labeler not trained yet): nothing to compare with
    assert all(chk.update("v", small, 10 + k / 100, 0, None) is None for k in range(400))


def test_a_stream_trained_from_init_frames_in_metres_is_named_in_the_log(scene, caplog):
    # its model is trained on the metres themselves, so points and model agree: the check
    # is the model's own size (no person's markers span less than 50 mm)
    frames = frames_of(scene, np.random.default_rng(1))
    items = []
    for k in range(200):
        p, truth = frames[k]
        labels = [scene.labels[i] for i in truth] if k < 20 else None
        items.append(encode_frame("default", k, k / scene.rate, p * np.float32(1e-3), labels))

    async def go():
        mem = MemoryTransport()
        async with Server(settings(), [mem]) as srv:
            for p in items:
                mem.inject(p)
            return srv, await collect(srv, mem)

    with caplog.at_level(logging.WARNING, logger="labeler_service.service.stream"):
        srv, msgs = run(go())
    warned = [r.getMessage() for r in caplog.records if "init frames span" in r.getMessage()]
    assert len(msgs) == 200 - 20 and len(warned) == 1, warned
    assert "stream default" in warned[0] and "metres" in warned[0]
    # the same frames in millimetres: no warning
    idx = [np.asarray(t, dtype=np.int16) for _, t in (frames[k] for k in range(20))]
    pts = [frames[k][0] for k in range(20)]
    assert init_span_warning("v", pts, idx, list(scene.labels)) is None
    assert init_span_warning("v", [p * 1e-3 for p in pts], idx, list(scene.labels))


def test_points_of_another_marker_set_are_named_in_the_log(model_path, caplog):
    """A model stream fed another marker set's points (the model of 2 x 6 markers, frames of
    3 x 7 other markers, in millimetres) read ``booting`` for good with no word of why. After
    ``MATCH_S`` of stream with points and nothing labeled, the log compares the points per
    frame with the model's markers and names the fix; the frames still flow."""
    other = moving_clusters(np.random.default_rng(9), subjects=3, markers=7, frames=1300)
    frames = frames_of(other, np.random.default_rng(1))
    items = [encode_frame("vol", k, k / other.rate, frames[k][0]) for k in range(other.n_frames)]

    with caplog.at_level(logging.WARNING, logger="labeler_service.service.server"):
        srv, msgs = run(_serve(model_path, items), timeout=240.0)
    warned = [r.getMessage() for r in caplog.records if "nothing labeled for" in r.getMessage()]
    assert len(msgs) == len(items) and srv.metrics.drops() == 0
    assert len(warned) == 1, warned
    assert "stream vol" in warned[0] and "21 points (median)" in warned[0]
    assert "its model has 12 markers" in warned[0] and "train structure" in warned[0]
    assert "metres" not in warned[0]


def test_a_rate_warning_doubts_the_model_while_nothing_is_labeled(model_path, caplog):
    """Another marker set's points (3 x 7 markers) at 30 Hz on a stream of a 120 Hz model of 2
    x 6 markers, no ``streams[].rate``: the rate warning (after 2 s of stream) told the
    operator to set a rate, 8 s before the match check said the model may not be theirs. While
    nothing is labeled, the rate warning says it too, with the points per frame."""
    other = moving_clusters(np.random.default_rng(9), subjects=3, markers=7, frames=400)
    frames = frames_of(other, np.random.default_rng(1))
    items = [encode_frame("vol", k, k / 30.0, frames[k][0]) for k in range(other.n_frames)]
    with caplog.at_level(logging.WARNING, logger="labeler_service.service.server"):
        run(_serve(model_path, items), timeout=240.0)
    warned = [r.getMessage() for r in caplog.records if "its frames come at" in r.getMessage()]
    assert len(warned) == 1, warned
    assert "set rate = 30" in warned[0] and "nothing is labeled yet" in warned[0]
    assert "21 points (median) where its model has 12 markers" in warned[0]


def test_the_models_doubt_is_said_only_while_nothing_is_labeled(model_path):
    model = load_model(model_path)
    person = np.random.default_rng(0).normal(scale=300.0, size=(9, 3)).astype(np.float32)
    chk = UnitCheck()
    assert chk.model_doubt(model) == ""
    for k in range(5):
        chk.update("v", person, k / 30, 0, model)
    assert "9 points (median) where its model has 12 markers" in chk.model_doubt(model)
    chk.update("v", person, 5 / 30, 3, model)  # a label
    assert chk.model_doubt(model) == ""


def test_the_match_check_waits_for_points_and_gives_way_to_the_unit_warning(model_path):
    model = load_model(model_path)
    rng = np.random.default_rng(0)
    person = rng.normal(scale=300.0, size=(12, 3)).astype(np.float32)  # mm, a person's size
    chk = UnitCheck()
    # empty frames (nobody in the volume) never count, however long
    assert all(chk.update("v", person[:1], k / 100, 0, model) is None for k in range(2000))
    # points with nothing labeled: said once MATCH_S of them went by, not before
    got = [chk.update("v", person, 20 + k / 100, 0, model) for k in range(1001)]
    assert all(g is None for g in got[:-1])
    assert "12 points (median) where its model has 12 markers" in (got[-1] or "")
    assert "the boot has not placed them" in (got[-1] or "")
    # a label restarts it
    assert chk.update("v", person, 31, 5, model) is None
    assert all(chk.update("v", person, 31 + k / 100, 0, model) is None for k in range(1, 900))
    # metres: the unit warning, and no second one about the markers
    chk = UnitCheck()
    got = [chk.update("v", person * 1e-3, k / 100, 0, model) for k in range(1200)]
    said = [g for g in got if g is not None]
    assert said and all("metres" in g for g in said)


def test_the_match_check_says_it_less_and_less_often(model_path):
    """A stream of other performers (nothing ever labeled) logged the points-against-markers
    line every 10 s for as long as it ran. Each repeat now waits twice as long (10, 20, 40 s
    of stream) and says when it comes again; a label starts the count over."""
    model = load_model(model_path)
    person = np.random.default_rng(0).normal(scale=300.0, size=(12, 3)).astype(np.float32)
    chk = UnitCheck()
    times = [k / 10 for k in range(1, 751)]  # 75 s at 10 Hz
    said = [t for t in times if chk.update("v", person, t, 0, model) is not None]
    assert said == pytest.approx([10.1, 30.2, 70.3], abs=0.05), said
    chk.update("v", person, 75.1, 4, model)  # a label
    got = [chk.update("v", person, 75.1 + k / 10, 0, model) for k in range(1, 102)]
    assert [g is not None for g in got].count(True) == 1 and got[-1] is not None
    assert "(said again after 20 s of the same)" in got[-1]


def test_a_new_run_forgets_the_previous_runs_points_for_the_match_check(model_path):
    """A sender of another marker set (62 points) for 5 s, then the right one from ``t`` =
    100 (a new run): the match check said at the new run's first frame "nothing labeled for
    100 s; its frames carry 62 points". The new run starts its own count."""
    model = load_model(model_path)
    rng = np.random.default_rng(0)
    wrong = rng.normal(scale=300.0, size=(62, 3)).astype(np.float32)
    right = rng.normal(scale=300.0, size=(12, 3)).astype(np.float32)
    chk = UnitCheck()
    assert all(chk.update("v", wrong, k / 100, 0, model) is None for k in range(500))
    chk.new_run()
    got = [chk.update("v", right, 100 + k / 100, 0, model) for k in range(1001)]
    assert all(g is None for g in got[:-1])
    assert "12 points (median)" in (got[-1] or "") and "10.0 s of stream" in (got[-1] or "")


def _rate_warnings(scene, model_path, step: int, caplog) -> tuple[int, list[str]]:
    frames = frames_of(scene, np.random.default_rng(1))
    items = [
        encode_frame("vol", k, f / scene.rate, frames[f][0])
        for k, f in enumerate(range(TRAIN, scene.n_frames, step))
    ]

    with caplog.at_level(logging.WARNING, logger="labeler_service.service.server"):
        _, msgs = run(_serve(model_path, items), timeout=240.0)
    return len(msgs) - len(items), [
        r.getMessage() for r in caplog.records if "its frames come at" in r.getMessage()
    ]


def test_frames_at_another_rate_than_the_model_name_the_setting(scene, model_path, caplog):
    """A model trained at 120 Hz fed a stream at 30 Hz (every 4th frame): the stream ran at
    the model's rate, its boot window and point tracks sized for 120 Hz, with no word. Now
    the log says the rate the frames come at and the setting to change, once; frames flow."""
    lost, warned = _rate_warnings(scene, model_path, 4, caplog)
    assert lost == 0
    assert len(warned) == 1, warned
    assert "stream vol: its frames come at 30 Hz" in warned[0]
    assert "runs at 120 Hz" in warned[0] and "set rate = 30" in warned[0]


def test_frames_at_the_model_rate_give_no_rate_warning(scene, model_path, caplog):
    lost, warned = _rate_warnings(scene, model_path, 1, caplog)
    assert lost == 0 and not warned


def test_the_rate_check_measures_again_after_a_time_jump():
    from labeler_service.service.units import RateCheck

    chk = RateCheck()
    # 1.5 s at 100 Hz, then a jump back (a new run): nothing yet
    assert all(chk.update("v", k / 100, 100.0) is None for k in range(150))
    assert all(chk.update("v", k / 25, 100.0) is None for k in range(40))  # 1.6 s at 25 Hz
    said = [chk.update("v", 1.6 + k / 25, 100.0) for k in range(1, 20)]
    assert sum(s is not None for s in said) == 1
    assert all(chk.update("v", 3 + k / 25, 100.0) is None for k in range(200))  # said once


def test_the_rate_check_names_a_fifth_off_and_not_a_drifting_clock():
    """A stream set for 100 Hz fed 120 Hz (a helper's run: 0.17 % of the labels wrong, none
    at the right rate) said nothing under the 25 % threshold; a 2 % clock drift and 1 ms of
    jitter at the right rate say nothing."""
    from labeler_service.service.units import RateCheck

    for sent, warned in ((120.0, True), (100.0 * 1.02, False)):
        chk = RateCheck()
        t = np.arange(600) / sent + np.random.default_rng(1).normal(0, 0.001, 600)
        assert np.all(np.diff(t) > 0)
        said = [s for s in (chk.update("v", float(x), 100.0) for x in t) if s is not None]
        assert len(said) == int(warned), (sent, said)
        if warned:
            assert "come at 12" in said[0] and "set rate = 12" in said[0]


def test_the_rate_check_advises_no_rate_for_times_no_capture_has():
    """Frames whose ``t`` steps irregularly, or at no capture's rate, ask about the sender's
    ``t`` instead of advising ``set rate = 1`` (what a hostile stream was told)."""
    from labeler_service.service.units import RateCheck

    rng = np.random.default_rng(0)
    chk = RateCheck()
    t = np.cumsum(rng.uniform(0.001, 0.05, 400))  # steps of 1-50 ms at random
    said = [s for s in (chk.update("v", float(x), 120.0) for x in t) if s is not None]
    assert len(said) == 1 and "irregularly" in said[0] and "set rate" not in said[0]
    chk = RateCheck()
    said = [s for s in (chk.update("v", float(k), 120.0) for k in range(40)) if s]  # 1 Hz
    assert len(said) == 1 and "steadily" in said[0] and "seconds?" in said[0]


def test_a_streams_new_run_restarts_its_match_check():
    """The wiring of the test above: ``StreamState.new_run`` restarts the stream's check."""
    from labeler_service.service.continuity import Verdict
    from labeler_service.service.protocol import FrameMsg
    from labeler_service.service.settings import load_settings
    from labeler_service.service.stream import StreamState

    settings = load_settings(labeler="online", metrics_port=None, warmup=False,
                             streams=[{"name": "vol"}])  # fmt: skip
    st = StreamState("vol", settings, settings.streams[0])
    st.units._quiet_since, st.units._counts = 0.0, [62, 62]
    frame = FrameMsg("vol", 5, 100.0, np.zeros((3, 3), np.float32))
    st.new_run(frame, Verdict(new_run=True, time_jumped=True))
    assert st.units._quiet_since is None and st.units._counts == []
