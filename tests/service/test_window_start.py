"""A stream's labeled start through a window model (stream setting ``labeled_start = "model"``).

The stream trains subject templates on its labeled init frames in-stream (off the event loop,
``train_budget_s``) and runs the booting labeler from them (``make_window_labeler``), fed the
window's labels; the frames after the window come out labeled. The same simulated scene and
scoring as :mod:`test_online`, over UDP.
"""

from __future__ import annotations

import contextlib

import pytest
from service.helpers import run, until
from service.test_online import INIT, _score

from labeler_service.capture import Capture
from labeler_service.errors import ConfigError
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import Subscriber

RATE = 120.0


@pytest.fixture(scope="module")
def scene() -> Capture:
    return simulate_scene(2, 3.0, "walk", seed=7, rate=RATE, ghosts=0.5)


def _settings(labeled_start: str, **kw):
    return load_settings(
        labeler="online", metrics_port=None, queue_size=2048, udp={"port": 0},
        streams=[{"name": "vol", "labeled_start": labeled_start}], **kw,
    )  # fmt: skip


def test_a_stream_starts_from_its_window_model(scene):
    """The plain labeler labels from the first frame; the window labeler takes over once its
    model is trained and caught up (the replay loops until then, and a second more)."""
    import asyncio

    from labeler_service.cli.bench_latency import looped
    from labeler_service.tools.replay import frame_order

    frames = corrupt(scene, CorruptionSpec(protect_frames=INIT, seed=11))
    loops = 40

    async def go():
        async with Server(_settings("model")) as srv:
            host, port = srv.transports[0].address
            url = f"udp://{host}:{port}/vol"
            async with Subscriber(url) as sub:
                await until(lambda: srv.transports[0].subscribers, "the registration")
                async with open_sender(url) as (send, stream):
                    sending = asyncio.create_task(
                        replay(
                            frames, send, stream=stream, init_frames=INIT, speed=2.0, loops=loops
                        )  # fmt: skip
                    )
                    out = lambda: srv.metrics.value("mocap_frames_out_total", stream="vol")  # noqa: E731
                    await until(lambda: srv.streams["vol"].handovers == 1 or sending.done(),
                                "the window labeler's handover", timeout=120.0)  # fmt: skip
                    swapped = out()
                    await until(lambda: out() >= swapped + RATE or sending.done(),
                                "a second after the handover", timeout=60.0)  # fmt: skip
                    sending.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await sending
                await until(lambda: sub.stats.frames >= out() - 5, "the frames in flight")
                lab = srv.streams["vol"].labeler
                return sub.drain(), sub.models["vol"], srv.metrics, lab

    got, model_msg, metrics, lab = run(go(), timeout=300.0)
    # the booting labeler from a model trained on the stream's own init window, its boot and
    # extension handed to the server (off the event loop) once trained
    assert isinstance(lab, BootingLabeler)
    assert not lab.inline_boot and not lab.inline_extend
    assert lab.model is not None and "stream vol init window" in lab.model.source
    assert lab.config.restructure_prior_s == pytest.approx(INIT / RATE, rel=1e-3)
    assert metrics.drops() == metrics.drops("queue_full")  # no training failure, no error
    n = max(r.msg.seq for r in got) + 1
    assert metrics.drops("queue_full") <= 0.05 * n
    assert len(got) >= 0.95 * (n - INIT)
    assert min(r.msg.seq for r in got) >= INIT  # the frames after the window
    assert sorted(model_msg.names) == sorted(frames.marker_names)
    assert model_msg.rate == pytest.approx(RATE, rel=1e-6)
    seq_frames = looped(frames, frame_order(frames.n_frames, loops)[:n])
    acc, ghosts_labeled, scored = _score(seq_frames, got)
    assert acc >= 0.99, acc
    assert ghosts_labeled <= 0.02 * scored


def test_window_start_settings_are_checked(tmp_path):
    # the service trains in place by default (evaluate and label: auto; docs/service.md)
    assert load_settings().streams[0].labeled_start == "labeler"
    with pytest.raises(ConfigError, match="labeled_start"):
        _settings("window")
    with pytest.raises(ConfigError, match="labeler is 'baseline': set labeler = 'online', or"):
        load_settings(streams=[{"name": "vol", "labeled_start": "model"}], labeler="baseline")
    model = tmp_path / "m.json"
    model.write_text("{}")
    with pytest.raises(
        ConfigError, match="starts from that model: drop one of model and labeled_start"
    ):
        load_settings(streams=[{"name": "vol", "labeled_start": "model", "model": str(model)}])


def _train(names: list[str], labeled_start: str, rng, state_out: list | None = None):
    """A stream's training job on 12 labeled frames of 5 markers named ``names`` (the stream
    and its first unlabeled frame appended to ``state_out``)."""
    from labeler_service.service.protocol import FrameMsg
    from labeler_service.service.stream import StreamState

    settings = _settings(labeled_start, warmup=False)
    state = StreamState("vol", settings, settings.streams[0])
    base = rng.normal(scale=60.0, size=(5, 3))
    for k in range(12):
        pts = (base + rng.normal(size=(5, 3)) + k).astype("float32")
        state.buffer_init(FrameMsg("vol", k, k / 50.0, pts, tuple(names)))
    first = FrameMsg("vol", 12, 12 / 50.0, (base + 12).astype("float32"))
    if state_out is not None:
        state_out += [state, first]
    return state.train(state.take_init(), first)


@pytest.mark.parametrize("labeled_start", ["labeler", "model"])
def test_init_frames_timed_in_milliseconds_are_refused_by_their_rate(rng, labeled_start):
    """A client that sends ``t`` in milliseconds: the rate read from the init frames' times
    (0.05 Hz for 50 Hz frames) started a labeler at that rate, which predicted nothing."""
    from labeler_service.errors import LabelerError
    from labeler_service.service.protocol import FrameMsg
    from labeler_service.service.stream import StreamState

    settings = _settings(labeled_start, warmup=False)
    state = StreamState("vol", settings, settings.streams[0])
    base = rng.normal(scale=60.0, size=(5, 3))
    for k in range(12):
        pts = (base + rng.normal(size=(5, 3)) + k).astype("float32")
        state.buffer_init(FrameMsg("vol", k, k * 20.0, pts, tuple(f"s:m{i}" for i in range(5))))
    first = FrameMsg("vol", 12, 240.0, (base + 12).astype("float32"))
    with pytest.raises(LabelerError, match=r"is 0.05 Hz: expected 1 to 10000 Hz \(is t in sec"):
        state.train(state.take_init(), first)


def test_window_start_needs_subject_labels(rng):
    from labeler_service.errors import LabelerError

    with pytest.raises(
        LabelerError, match=r"subject:marker labels.*'m0'.*labeled_start = 'labeler'"
    ):
        _train([f"m{i}" for i in range(5)], "model", rng)
    labeler, rate, out, _ = _train([f"s:m{i}" for i in range(5)], "model", rng)
    assert isinstance(labeler, BootingLabeler) and rate == pytest.approx(50.0)
    assert labeler.model is not None and labeler.model.subjects[0].name == "s"
    # the same window with labeled_start = "labeler" trains the labeler in place
    plain, *_ = _train([f"s:m{i}" for i in range(5)], "labeler", rng)
    assert not isinstance(plain, BootingLabeler)


def test_the_auto_start_is_the_window_model_where_it_applies(rng, caplog):
    """``auto`` (the default): the window model's start for subject:marker labels; bare marker
    names (which the window model cannot name subjects from) train the labeler in place, and
    the log says why."""
    import logging

    window, *_ = _train([f"s:m{i}" for i in range(5)], "auto", rng)
    assert isinstance(window, BootingLabeler) and window.window_frames == 12
    with caplog.at_level(logging.INFO, logger="labeler_service.service.stream"):
        bare, *_ = _train([f"m{i}" for i in range(5)], "auto", rng)
    assert not isinstance(bare, BootingLabeler)
    assert "the labeler trained in place (the window model names its subjects" in caplog.text


def test_a_stream_setting_written_at_the_top_of_the_file_says_where_it_belongs(tmp_path):
    """``labeled_start = "model"`` above ``[[streams]]`` (TOML puts it at the top level, where
    it is no setting) says it belongs to a stream's table, not only 'Extra inputs are not
    permitted'."""
    path = tmp_path / "s.toml"
    path.write_text('labeled_start = "model"\n[[streams]]\nname = "vol"\n')
    with pytest.raises(ConfigError, match=r"labeled_start: not a setting.*setting of one stream"):
        load_settings(path)


@pytest.mark.parametrize("labeled_start", ["labeler", "model"])
def test_ghost_labels_in_the_init_frames_stay_ghosts(rng, labeled_start):
    """A point labeled ``*N`` in an init frame is a ghost (DESIGN.md): it used to become a
    marker ``*9`` of the labeler trained in place (its label then given to ghosts)."""
    labeler, *_ = _train(["s:m0", "s:m1", "s:m2", "s:m3", "*9"], labeled_start, rng)
    assert tuple(labeler.marker_names) == ("s:m0", "s:m1", "s:m2", "s:m3")


@pytest.mark.parametrize("labeled_start", ["labeler", "model"])
def test_an_empty_subject_name_is_refused_by_name(rng, labeled_start):
    """``:m0`` (an empty subject): the labeler trained in place refused its own model ('model
    marker 'm0' is not a labeler marker') and the window model renamed the subject, so the
    window's labels matched no marker; both now name the label."""
    from labeler_service.errors import LabelerError

    with pytest.raises(LabelerError, match=r"label ':m0' has an empty subject name"):
        _train([f":m{i}" for i in range(5)], labeled_start, rng)


@pytest.mark.parametrize("labeled_start", ["labeler", "model"])
def test_the_ready_line_says_which_labeled_start_ran(rng, caplog, labeled_start):
    """The operator sees in the log that the setting took effect (the ready line was the same
    for both starts)."""
    import logging

    got: list = []
    labeler, rate, out, ns = _train([f"s:m{i}" for i in range(5)], labeled_start, rng, got)
    state, first = got
    with caplog.at_level(logging.INFO, logger="labeler_service.service.stream"):
        state.install_trained(labeler, rate, first, out, 0, ns)
    (line,) = [r.getMessage() for r in caplog.records if "labeler ready" in r.getMessage()]
    assert ("through the init window's model" in line) == (labeled_start == "model"), line


def test_a_subject_of_too_few_markers_is_named_in_the_log(rng, caplog):
    """A stream whose labels give a subject fewer markers than the presence check needs logs
    it once, at training (that subject is never labeled: not silent)."""
    import logging

    caplog.set_level(logging.WARNING, logger="labeler_service.service.stream")
    names = ["A:m0", "A:m1", "A:m2", "B:p", "B:q"]
    _train(names, "labeler", rng)
    assert "stream vol: subject B has 2 markers, fewer than the 3" in caplog.text
    assert "subject A" not in caplog.text
