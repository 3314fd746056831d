"""The clients say when the service is gone: ``subscribe`` warns when labeled frames stop (and
resume) and reports status changes; ``replay`` counts datagrams refused by the kernel (ICMP
port unreachable: nothing listens) as failed."""

from __future__ import annotations

import socket

import numpy as np
from service.helpers import moving_clusters, run, until

from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import Subscriber


def _settings():
    return load_settings(labeler="baseline", metrics_port=None, warmup=False, udp={"port": 0})


def _dead_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    return port


def _replay_to_a_dead_port(n_frames: int, speed: float):
    cap = moving_clusters(np.random.default_rng(0), frames=n_frames, rate=200.0)
    frames = corrupt(cap, CorruptionSpec(seed=1))

    async def go():
        async with open_sender(f"udp://127.0.0.1:{_dead_port()}/x") as (send, stream):
            return await replay(frames, send, stream=stream, init_frames=5, speed=speed)

    return run(go())


def test_replay_to_a_port_where_nothing_listens_counts_the_frames_as_failed(caplog):
    stats = _replay_to_a_dead_port(30, 1.0)
    assert stats.failed >= 20 and stats.sent + stats.failed == 30
    warned = [r for r in caplog.records if "connection refused" in r.getMessage()]
    assert len(warned) == 1  # once per episode, not per frame


def test_replay_as_fast_as_possible_to_a_dead_port_counts_no_frame_sent_after_a_refusal():
    """At ``--speed 0`` the kernel's refusals arrive after some sends, not one per datagram:
    every other send read one, so half the frames were called sent. A send within
    ``REFUSED_S`` of a refusal counts as failed: only frames before the first report remain."""
    stats = _replay_to_a_dead_port(200, 0.0)
    assert stats.sent + stats.failed == 200
    assert stats.sent <= 5, stats


def test_subscribe_without_a_service_warns_that_nothing_listens():
    async def go():
        async with Subscriber(f"udp://127.0.0.1:{_dead_port()}/v", silence_s=0.2) as sub:
            await until(lambda: sub.silent, "the silence warning", timeout=5)
            return list(sub.warnings)

    warnings = run(go())
    assert len(warnings) == 1 and "connection refused" in warnings[0]


def test_subscribe_blames_refusals_only_when_they_came_after_the_last_frame():
    """The service died (refusals), came back and sent frames, then its stream ended: the
    silence after that was put down to "nothing listens there (connection refused)", the
    earlier outage's refusals counted against it (a hostile run's ``kill -9`` and restart)."""
    from labeler_service.service.protocol import encode_labeled, encode_model
    from labeler_service.service.transports.base import Incoming

    port = _dead_port()

    async def go():
        async with Subscriber(f"udp://127.0.0.1:{port}/v", silence_s=0.2, renew_s=0.05) as sub:
            await until(lambda: sub.silent, "the silence warning", timeout=5)
            assert "connection refused" in sub.warnings[-1]
            assert sub._udp is not None
            n = sub._udp.refused  # the outage goes on: more refusals after the warning
            await until(lambda: sub._udp.refused > n, "another refusal", timeout=5)
            back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the service is back
            back.bind(("127.0.0.1", port))
            try:
                names = ("A:m0", "A:m1")
                sub._handle(Incoming(encode_model("v", 1, names, (("A", 0, 2),), 120.0), 0, "udp"))
                pos = np.zeros((2, 3), np.float32)
                sub._handle(Incoming(encode_labeled("v", 1, 0, 0.0, pos, np.ones(2, np.uint8),
                                                    np.zeros((0, 3), np.float32), None, 0, 0.0),
                                     0, "udp"))  # fmt: skip
                assert not sub.silent
                await until(lambda: sub.silent, "the next silence", timeout=5)
            finally:
                back.close()
            return list(sub.warnings)

    warnings = run(go())
    assert "connection refused" not in warnings[-1], warnings
    assert "no labeled frames" in warnings[-1]


def test_subscribe_reports_silence_resumption_and_the_services_offline_status(rng):
    cap = moving_clusters(rng, frames=120, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=10, seed=2))

    async def go():
        srv = Server(_settings())
        await srv.__aenter__()
        host, port = srv.transports[0].address
        url = f"udp://{host}:{port}/v"
        async with Subscriber(url, silence_s=0.3) as sub:
            try:
                await until(lambda: srv.transports[0].subscribers, "the registration")
                async with open_sender(url) as (send, stream):
                    await replay(frames, send, stream=stream, init_frames=10, speed=2.0)
                    await until(lambda: sub.silent, "the silence warning", timeout=5)
                    before = sub.stats.frames
                    await replay(frames, send, stream=stream, init_frames=0, speed=2.0,
                                 seq0=120, max_frames=20)  # fmt: skip
                    await until(lambda: not sub.silent, "the frames again", timeout=5)
                    assert sub.stats.frames > before
            finally:
                await srv.__aexit__(None, None, None)  # publishes offline, then closes
            await until(lambda: sub.silent, "the silence after the service left", timeout=5)
            return list(sub.warnings)

    warnings = run(go())
    # no model: booting until the labeled init frames have trained the stream's labeler
    assert (
        "stream v is booting (no one labeled yet: it boots its performers from a model, or "
        "waits for labeled init frames" in warnings[0]
    )
    assert "stream v is online" in warnings[1]
    assert "no labeled frames" in warnings[2] and "frames again" in warnings[3]
    assert any("stream v is offline" in w for w in warnings[4:])
    assert "no labeled frames" in warnings[-1]


def test_subscribe_says_why_a_stream_nobody_is_labeled_in_yet_is_lost():
    """A stream that has labeled nothing and reads ``lost`` (a recovery boot that finds no
    one): the subscriber says that nothing was labeled yet and the likely reasons, not only
    'lost'; a stream that had labeled markers and turns lost gets the plain line; ``booting``
    (a model stream before its first boot) says what it means."""
    from labeler_service.service.protocol import encode_labeled, encode_model, encode_status
    from labeler_service.service.transports.base import Incoming

    sub = Subscriber("udp://127.0.0.1:9/v", silence_s=1.0)

    def feed(payload: bytes) -> None:
        sub._handle(Incoming(payload, 0, "udp"))

    names = ("A:m0", "A:m1")
    feed(encode_model("v", 1, names, (("A", 0, 2),), 120.0))
    feed(encode_status("v", "booting"))
    assert sub.warnings[-1].endswith("stream v is booting (booting its performers from the "
                                     "model: no one labeled yet)"), sub.warnings[-1]  # fmt: skip
    feed(encode_status("v", "lost"))
    assert "stream v is lost (no marker labeled yet: the service is booting" in sub.warnings[-1]
    pos = np.zeros((2, 3), np.float32)
    for seq, state in ((0, [0, 0]), (1, [1, 0])):
        feed(encode_labeled("v", 1, seq, seq / 120, pos, np.array(state, np.uint8),
                            np.zeros((0, 3), np.float32), None, 0, 0.0))  # fmt: skip
    feed(encode_status("v", "online"))
    feed(encode_status("v", "lost"))
    assert sub.warnings[-1].endswith("stream v is lost"), sub.warnings[-1]


def test_subscribe_says_a_booting_stream_without_a_model_waits_for_labeled_init_frames():
    """A configured stream without a model reads ``booting`` until its labeled init frames
    have trained its labeler (it read ``online`` from the start). No model message came, and a
    model stream's comes with its first frames (`make demo` said "waiting for labeled init
    frames" of a stream that boots from a model), so the subscriber names both."""
    from labeler_service.service.protocol import encode_status
    from labeler_service.service.transports.base import Incoming

    sub = Subscriber("udp://127.0.0.1:9/v", silence_s=1.0)
    sub._handle(Incoming(encode_status("v", "booting"), 0, "udp"))
    want = "stream v is booting (no one labeled yet: it boots its performers from a model, or "
    assert sub.warnings[-1].endswith(want + "waits for labeled init frames to train its "
                                     "labeler)"), sub.warnings[-1]  # fmt: skip


def test_a_stream_turning_online_is_logged_as_news_not_as_a_warning(caplog):
    """``online`` at INFO (the viewer logged every start as a WARNING); ``lost`` still warns."""
    import logging

    from labeler_service.service.protocol import encode_status
    from labeler_service.service.transports.base import Incoming

    caplog.set_level(logging.INFO, logger="labeler_service.tools.subscribe")
    sub = Subscriber("udp://127.0.0.1:9/v", silence_s=1.0)
    for state in ("online", "lost"):
        sub._handle(Incoming(encode_status("v", state), 0, "udp"))
    levels = {r.getMessage().split("stream v is ")[1].split()[0]: r.levelno for r in caplog.records}
    assert levels == {"online": logging.INFO, "lost": logging.WARNING}, levels


def test_subscribe_to_a_stream_name_the_service_does_not_have_says_so():
    """A typo in the stream name (``/cour`` for ``court``): the service answers but announces
    no such stream; the silence warning asks whether the name is right."""
    settings = load_settings(labeler="baseline", metrics_port=None, warmup=False,
                             udp={"port": 0}, streams=[{"name": "court"}])  # fmt: skip

    async def go():
        async with Server(settings) as srv:
            host, port = srv.transports[0].address
            async with Subscriber(f"udp://{host}:{port}/cour", silence_s=0.3) as sub:
                await until(lambda: sub.silent, "the silence warning", timeout=5)
                return list(sub.warnings)

    warnings = run(go())
    assert any("announced no stream 'cour'" in w and "name right" in w for w in warnings), warnings


def test_subscribe_says_what_training_failed_means():
    """``training_failed`` (a labeled start whose training raised, e.g. bare marker names on a
    ``labeled_start = "model"`` stream, or ran over ``train_budget_s``) points to the service
    log and says the stream waits for new labeled init frames, not the bare state alone."""
    from labeler_service.service.protocol import encode_status
    from labeler_service.service.transports.base import Incoming

    sub = Subscriber("udp://127.0.0.1:9/v", silence_s=1.0)
    sub._handle(Incoming(encode_status("v", "training_failed"), 0, "udp"))
    assert (
        "stream v is training_failed (training on its labeled init frames failed"
        in (sub.warnings[-1])
    )
    assert "the service log says why" in sub.warnings[-1]


def _subscriber_warnings(frames, *, joins_after: bool, speed: float) -> list[str]:
    """The warnings of a subscriber (silence after 0.3 s) around one replay of ``frames`` to a
    baseline service: started before the replay (the silence warning first, then the frames)
    or after it (``joins_after``: the stream announced, its sender idle)."""

    async def go():
        async with Server(_settings()) as srv:
            host, port = srv.transports[0].address
            url = f"udp://{host}:{port}/v"

            async def send_take():
                async with open_sender(url) as (send, stream):
                    await replay(frames, send, stream=stream, init_frames=10, speed=speed)

            if joins_after:
                await send_take()
            async with Subscriber(url, silence_s=0.3) as sub:
                await until(lambda: sub.silent, "the silence warning", timeout=5)
                if not joins_after:
                    await send_take()
                    await until(lambda: not sub.silent, "the first frames", timeout=5)
                return list(sub.warnings)

    return run(go())


def test_the_first_frames_after_a_silence_at_the_start_are_not_called_a_resumption(rng):
    """A subscriber started before the stream warned of the silence, then said "labeled
    frames again" at the first frame it ever got; it says "first labeled frames" now."""
    cap = moving_clusters(rng, frames=60, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=10, seed=2))
    warnings = _subscriber_warnings(frames, joins_after=False, speed=2.0)
    first = [w for w in warnings if "labeled frames" in w and " after " in w]
    assert first and "first labeled frames (stream v)" in first[0], warnings
    assert not any("frames again" in w for w in warnings), warnings


def test_a_subscriber_joining_an_idle_online_stream_asks_about_the_sender(rng):
    """A subscriber that joins a stream announced ``online`` whose sender is between two takes
    was told the stream "has not sent labeled frames yet"; it says the status it heard and
    asks whether the sender is sending."""
    cap = moving_clusters(rng, frames=40, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=10, seed=2))
    warnings = _subscriber_warnings(frames, joins_after=True, speed=4.0)
    said = [w for w in warnings if "no labeled frames for" in w]
    assert said and "says the stream is online, but no frame came" in said[0], warnings


def test_subscribe_over_mqtt_to_a_stream_nobody_serves_names_the_stream_list():
    """Over MQTT the service subscribes only to the streams its settings list: a replay and a
    subscriber on ``/volume1`` against a service with only ``default`` got "no answer from the
    service yet: is it running?" - it was running (the docs' own MQTT example, before it set
    ``MOCAP_STREAMS``). The reason now names the stream list."""
    import asyncio
    import contextlib

    sub = Subscriber("mqtt://127.0.0.1:1883/volume1", silence_s=0.05)  # (not entered: no broker)

    async def go():
        sub._last_frame -= 1.0
        with contextlib.suppress(TimeoutError):  # (the watch runs until cancelled)
            await asyncio.wait_for(sub._watch(), 0.5)
        return list(sub.warnings)

    warnings = run(go())
    assert len(warnings) == 1 and "no answer from the service yet" in warnings[0]
    assert (
        "serves only the streams its settings list: is 'volume1' in its [[streams]]"
        in (warnings[0])
    )
