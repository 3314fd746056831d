"""The service against a real Mosquitto (fixture ``broker``): frames in and out over MQTT,
retained model/status, the last will, and a broker stop/restart."""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from service.helpers import SlowLabeler, moving_clusters, run, stream_payloads, until

from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import READY, Subscriber

pytestmark = pytest.mark.broker


def _settings(broker, udp: bool = False, **over):
    base = {
        "labeler": "baseline", "metrics_port": None, "queue_size": 256,
        "udp": {"enabled": udp, "port": 0},
        "mqtt": {"enabled": True, "host": broker.host, "port": broker.port,
                 "reconnect_min_s": 0.1, "reconnect_max_s": 0.5},
        "streams": [{"name": "vol"}],
    }  # fmt: skip
    base.update(over)
    return load_settings(**base)


def test_frames_in_and_out_over_mqtt_with_retained_model_and_status(broker, rng):
    cap = moving_clusters(rng, subjects=2, markers=5, frames=120, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=20, seed=3))

    async def go():
        async with Server(_settings(broker)) as srv:
            async with Subscriber(f"{broker.url}/vol") as sub:
                assert await sub.wait_status("vol", READY, 30.0)
                async with open_sender(f"{broker.url}/vol") as (send, stream):
                    stats = await replay(frames, send, stream=stream, init_frames=20, speed=2.0)
                got = []
                async with asyncio.timeout(30):
                    async for r in sub.frames():
                        got.append(r)
                        if r.msg.seq == 119:
                            break
            # a late subscriber: model and status are retained by the broker
            async with Subscriber(f"{broker.url}/vol") as late:
                assert await late.wait_status("vol", "online", 30.0)
                async with asyncio.timeout(30):
                    while "vol" not in late.models:
                        await asyncio.sleep(0.01)
                late_names = late.models["vol"].names
            metrics = srv.metrics
        async with Subscriber(f"{broker.url}/vol") as after:
            assert await after.wait_status("vol", "offline", 30.0)
        return stats, got, late_names, metrics

    stats, got, late_names, metrics = run(go())
    assert stats.failed == 0
    assert [r.msg.seq for r in got] == list(range(20, 120))
    assert late_names == got[0].names == tuple(sorted(cap.labels))
    assert all((r.msg.state == 1).all() for r in got)
    assert metrics.drops() == 0


def test_last_will_marks_the_stream_offline_when_the_service_dies(broker):
    env = dict(os.environ, MOCAP_LABELER="baseline", MOCAP_UDP__ENABLED="false",
               MOCAP_METRICS_PORT="0", MOCAP_MQTT__ENABLED="true",
               MOCAP_MQTT__PORT=str(broker.port), MOCAP_STREAMS='[{"name": "vol"}]')  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "labeler_service.cli.main", "serve", "--log-level", "WARNING"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip

    async def go():
        async with Subscriber(f"{broker.url}/vol") as sub:
            assert await sub.wait_status("vol", READY, 30.0)
            proc.kill()  # no goodbye: only the broker's last will can say offline
            return await sub.wait_status("vol", "offline", 10.0)

    try:
        assert run(go())
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def test_broker_restart_labeled_frames_resume_and_udp_keeps_flowing(broker, rng):
    """Event-driven: each phase waits for what it needs (how fast MQTT resumes is measured by
    benchmarks/broker_restart.py, acceptance < 5 s, not asserted here)."""
    cap = moving_clusters(rng, subjects=2, markers=5, frames=400, rate=100.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=20, seed=4))

    async def go():
        async with Server(_settings(broker, udp=True)) as srv:
            host, port = srv.transports[0].address
            async with (
                Subscriber(f"{broker.url}/vol") as mq,
                Subscriber(f"udp://{host}:{port}/vol") as ud,
                open_sender(f"udp://{host}:{port}/vol") as (send, stream),
            ):
                feeder = asyncio.create_task(
                    replay(frames, send, stream=stream, init_frames=20, speed=1.0, loops=50)
                )
                await until(lambda: mq.stats.frames >= 20, "labeled frames over MQTT")
                broker.stop()
                udp_at_stop = ud.stats.frames
                send_errors = srv.metrics.drops("send_error")
                # the service notices the broker is gone: its MQTT sends fail, counted
                await until(lambda: srv.metrics.drops("send_error") > send_errors,
                            "failed MQTT sends while the broker is down")  # fmt: skip
                # UDP keeps flowing while the broker is down
                await until(lambda: ud.stats.frames >= udp_at_stop + 50, "UDP frames")
                mqtt_at_restart = mq.stats.frames
                broker.start()
                await until(lambda: mq.stats.frames > mqtt_at_restart, "MQTT frames after the "
                            "restart", timeout=60.0)  # fmt: skip
                resumed = mq.stats.frames - mqtt_at_restart
                feeder.cancel()
                await asyncio.gather(feeder, return_exceptions=True)
            return resumed, srv.metrics

    resumed, metrics = run(go(), timeout=180.0)
    assert resumed > 0
    assert metrics.drops("send_error") > 0  # MQTT sends failed while down, counted


def test_topic_and_payload_stream_must_agree(broker):
    from labeler_service.service.protocol import encode_frame

    async def go():
        async with Server(_settings(broker)) as srv:
            async with open_sender(f"{broker.url}/vol") as (send, _):
                await send(encode_frame("other", 0, 0.0, np.zeros((1, 3), np.float32)))
            async with asyncio.timeout(30):
                while srv.metrics.drops("stream_mismatch") == 0:
                    await asyncio.sleep(0.02)
            return srv.metrics.drops("stream_mismatch")

    assert run(go()) == 1


def _online_for(secured, mqtt: dict, url: str, client=None) -> tuple[bool, bool]:
    """A service on ``secured`` (``mqtt``: its extra MQTT settings): (a subscriber at ``url``
    sees it online, a plain anonymous subscriber is refused)."""

    async def go():
        s = load_settings(labeler="baseline", metrics_port=None, udp={"enabled": False},
                          streams=[{"name": "vol"}],
                          mqtt={"enabled": True, "host": secured.host, "port": secured.port,
                                **mqtt})  # fmt: skip
        async with Server(s):
            async with Subscriber(url, mqtt=client) as good:
                ok = await good.wait_status("vol", READY, 30.0)
            async with Subscriber(f"{secured.url}/vol") as plain:
                refused = not await plain.wait_status("vol", READY, 1.5)
        return ok, refused

    return run(go())


def test_credentials_are_required_and_used(tmp_path):
    import shutil

    from labeler_service.testing.broker import LocalBroker, mosquitto_binary

    if mosquitto_binary() is None or shutil.which("mosquitto_passwd") is None:
        pytest.skip("mosquitto / mosquitto_passwd not found (apt install mosquitto)")
    with LocalBroker(tmp_path, users={"labeler": "s3cret"}) as secured:
        url = f"mqtt://labeler:s3cret@{secured.host}:{secured.port}/vol"
        ok, refused = _online_for(secured, {"username": "labeler", "password": "s3cret"}, url)
    assert ok and refused


def _certificates(d):
    """A throw-away CA and a server certificate for 127.0.0.1 (openssl CLI)."""
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("openssl not found")

    def ssl(*args):
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=d)

    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=test-ca",
        "-keyout", "ca.key", "-out", "ca.pem")  # fmt: skip
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1", "-keyout",
        "server.key", "-out", "server.csr")  # fmt: skip
    (d / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n")
    ssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
        "-CAcreateserial", "-days", "1", "-extfile", "san.ext", "-out", "server.pem")  # fmt: skip
    return d / "ca.pem", d / "server.pem", d / "server.key"


def test_tls_connection_with_a_private_ca(tmp_path):
    from labeler_service.service.settings import MqttSettings
    from labeler_service.testing.broker import LocalBroker, mosquitto_binary

    if mosquitto_binary() is None:
        pytest.skip("mosquitto not found (apt install mosquitto)")
    ca, cert, key = _certificates(tmp_path)
    with LocalBroker(tmp_path, tls=(ca, cert, key)) as secured:
        url = f"mqtts://{secured.host}:{secured.port}/vol"
        # the plain subscriber has no TLS: refused
        ok, refused = _online_for(secured, {"tls": True, "ca_file": str(ca)}, url,
                                  client=MqttSettings(ca_file=ca))  # fmt: skip
    assert ok and refused


def _publish_burst(broker, topic, payloads):
    import paho.mqtt.client as paho

    c = paho.Client(paho.CallbackAPIVersion.VERSION2)
    c.connect(broker.host, broker.port)
    c.loop_start()
    infos = [c.publish(topic, p, qos=0) for p in payloads]
    for info in infos:
        info.wait_for_publish(5)
    c.loop_stop()
    c.disconnect()


class _Witness:
    """A plain MQTT client on the service's input topic: sets ``done`` once it has received
    ``n`` messages (then the broker has forwarded the burst to every subscriber)."""

    def __init__(self, broker, topic: str, n: int) -> None:
        import paho.mqtt.client as paho

        self.n, self.got, self.done = n, 0, threading.Event()
        self.subscribed = threading.Event()
        self.c = paho.Client(paho.CallbackAPIVersion.VERSION2)
        self.c.on_message = self._on_message
        self.c.on_subscribe = lambda *a: self.subscribed.set()
        self.c.connect(broker.host, broker.port)
        self.c.loop_start()
        self.c.subscribe(topic, qos=0)

    def _on_message(self, client, userdata, msg) -> None:
        self.last = msg.payload
        self.got += 1
        if self.got >= self.n:
            self.done.set()

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


class _GatedLabeler(SlowLabeler):
    """Blocks the event loop (inline labeling) on its second unlabeled frame until ``gate`` is
    set: the burst then piles up in the service's socket while the loop is busy."""

    def __init__(self, names, rate, gate: threading.Event) -> None:
        super().__init__(names, rate)
        self.gate, self.unlabeled = gate, 0

    def process(self, points, t, labels=None):
        if labels is None:
            self.unlabeled += 1
            if self.unlabeled == 2 and not self.gate.wait(60.0):
                raise RuntimeError("the burst never reached the witness")
        return super().process(points, t, labels)


def test_a_backlog_over_mqtt_lands_in_the_drop_oldest_queue(broker, rng):
    """When labeling is slow, frames queued in TCP must reach our queue (and be dropped there,
    counted) rather than wait in socket buffers: one readiness event reads every packet.

    No race with the clock: the labeler holds the loop until a witness subscriber has the whole
    burst, so the 98 frames after the first wait in the socket when the loop reads again."""
    cap = moving_clusters(rng, frames=105)
    payloads = stream_payloads(cap, rng, init=5, stream="vol")
    gate = threading.Event()
    made: list[_GatedLabeler] = []

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        made.append(_GatedLabeler(marker_names, rate, gate))
        return made[-1]

    async def go():
        witness = _Witness(broker, "mocap/vol/unlabeled", 105)  # 6 paced + the burst
        try:
            assert await asyncio.to_thread(witness.subscribed.wait, 10.0)
            s = _settings(broker, queue_size=4, warmup=False)
            async with Server(s, factory=factory) as srv:
                async with open_sender(f"{broker.url}/vol") as (send, _):
                    for i, p in enumerate(payloads[:6]):  # one at a time: none dropped
                        await send(p)
                        await until(
                            lambda i=i: (
                                srv.metrics.value("mocap_frames_in_total", stream="vol") > i
                                and not srv._queues["vol"]
                            ),
                            "a frame in",
                        )
                    # init frames + the first unlabeled (trains, in a worker thread) labeled
                    await until(
                        lambda: srv.metrics.value("mocap_frames_out_total", stream="vol") >= 1,
                        "the first frame",
                    )
                    relay = threading.Thread(target=lambda: witness.done.wait(60.0) and gate.set())
                    relay.start()
                    # 99 frames in one burst from another thread (this loop is held by the gate)
                    await asyncio.to_thread(_publish_burst, broker, "mocap/vol/unlabeled",
                                            payloads[6:])  # fmt: skip
                    await until(
                        lambda: srv.metrics.value("mocap_frames_in_total", stream="vol") >= 105,
                        "105 frames in",
                    )
                    await until(lambda: not srv._queues["vol"], "the queue drained")
                    await asyncio.to_thread(relay.join, 60.0)
                    labeled = made[-1].unlabeled
                return srv.metrics, labeled
        finally:
            witness.close()

    metrics, labeled = run(go(), timeout=120.0)
    dropped = metrics.drops("queue_full")
    assert dropped + labeled == 100  # every unlabeled frame: labeled or dropped, counted
    assert metrics.drops() == dropped
    assert dropped >= 85  # 98 piled up behind the held frame, queue_size 4: 94 if read at once


def test_replay_command_stream_option_sets_the_topic_too(broker, rng, tmp_path):
    """``replay --to mqtt://.../vol --stream other`` publishes on ``mocap/other/unlabeled``."""
    from labeler_service.capture import write_capture
    from labeler_service.cli.main import build_parser
    from labeler_service.cli.replay_capture import _main

    write_capture(moving_clusters(rng, frames=30), tmp_path / "scene.npz")
    argv = ["replay", str(tmp_path / "scene.npz"), "--to", f"{broker.url}/vol", "--stream",
            "other", "--init-frames", "10", "--speed", "0"]  # fmt: skip
    args = build_parser(argv).parse_args(argv)

    async def go():
        async with Server(_settings(broker, streams=[{"name": "other"}], warmup=False)) as srv:
            assert await _main(args) == 0
            async with asyncio.timeout(30):
                while srv.metrics.value("mocap_frames_in_total", stream="other") < 30:
                    await asyncio.sleep(0.02)
            return srv.metrics

    metrics = run(go())
    assert metrics.drops() == 0


def test_a_broker_out_of_reach_is_named_in_the_log_metrics_and_tools(broker, caplog):
    """The service started while no broker listened said ``ready: mqtt`` and went quiet
    after three ``[Errno 111] Connection refused`` lines naming only its client id; a
    subscriber blamed the service ("no answer from the service yet"). Now the log says which
    broker is out of reach and what to check (at ready and with every periodic line),
    ``mocap_transport_up{transport="mqtt"}`` is 0 until it connects, the subscriber and
    ``replay`` name the broker, and the service says when frames flow again."""
    import logging

    from labeler_service.errors import ConfigError

    broker.stop()
    where = f"MQTT broker at {broker.host}:{broker.port}"
    caplog.set_level(logging.INFO, logger="labeler_service.service.server")

    async def go():
        async with Server(_settings(broker, warmup=False, log_interval_s=0.5)) as srv:
            up = srv.metrics.value("mocap_transport_up", transport="mqtt")
            with pytest.raises(ConfigError, match=where):
                async with open_sender(f"{broker.url}/vol", connect_timeout=0.5):
                    pass
            async with Subscriber(f"{broker.url}/vol", silence_s=0.3) as sub:
                await until(lambda: sub.warnings, "a silence warning")
                said = sub.warnings[0]
            broker.start()
            await until(lambda: srv.metrics.value("mocap_transport_up", transport="mqtt") == 1,
                        "the connection up", timeout=60.0)  # fmt: skip
            return up, said

    up, said = run(go(), timeout=120.0)
    assert up == 0
    assert where in said and "is a broker (mosquitto) running there" in said, said
    down = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(m.startswith("mqtt: not connected to the " + where) for m in down), down
    assert "mqtt: carries frames again" in caplog.text


def test_the_broker_refuses_a_packet_above_the_shipped_limit(broker):
    """A 50 MB publish on a stream's input topic was read whole by the service before its size
    check (half the stream's frames dropped): the shipped broker config refuses packets above
    ``MAX_PACKET_BYTES``, and the test broker runs with the same limit."""
    import re
    from pathlib import Path

    from labeler_service.testing.broker import MAX_PACKET_BYTES

    shipped = (Path(__file__).parents[2] / "docker" / "mosquitto.conf").read_text()
    assert re.search(rf"^max_packet_size {MAX_PACKET_BYTES}$", shipped, re.M)
    topic = "mocap/big/unlabeled"
    witness = _Witness(broker, topic, 1)
    try:
        assert witness.subscribed.wait(5)
        import paho.mqtt.client as paho

        big = paho.Client(paho.CallbackAPIVersion.VERSION2)
        big.connect(broker.host, broker.port)
        big.loop_start()
        with contextlib.suppress(RuntimeError):  # (the broker drops the connection over it)
            big.publish(topic, b"x" * (2 * MAX_PACKET_BYTES), qos=0).wait_for_publish(5)
        big.loop_stop()
        big.disconnect()
        _publish_burst(broker, topic, [b"y" * 1000])
        assert witness.done.wait(5)
        time.sleep(0.2)
        assert witness.got == 1 and witness.last == b"y" * 1000
    finally:
        witness.close()
