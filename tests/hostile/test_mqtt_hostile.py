"""Class 5 of issue 12 against a real Mosquitto: retained spoofing and the broker ACL.

1. Any client that replaces the service's retained model or status (or clears it) is answered by
   the service re-publishing its own: a late subscriber still decodes with the right names.
2. The shipped broker set-up (docker/mosquitto.acl + users from scripts/make-broker-users.sh):
   anonymous clients are refused, replay may only publish unlabeled frames, subscribers only
   read, and the service works end to end with its own account.
"""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path

import aiomqtt
import numpy as np
import pytest
from hostile.helpers import moving_clusters, run
from hostile.helpers import settings as service_settings

from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.service.protocol import encode_model, encode_status
from labeler_service.service.server import Server
from labeler_service.testing.broker import LocalBroker, mosquitto_binary
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import READY, Subscriber

pytestmark = pytest.mark.broker
ROOT = Path(__file__).resolve().parents[2]


def _need_mosquitto():
    if mosquitto_binary() is None:
        pytest.skip("mosquitto binary not found (make test installs it; apt install mosquitto)")


def _mqtt_settings(broker, user=None, password=None, **over):
    mqtt = {"enabled": True, "host": broker.host, "port": broker.port,
            "reconnect_min_s": 0.1, "reconnect_max_s": 0.5}  # fmt: skip
    if user:
        mqtt.update(username=user, password=password)
    base = {"labeler": "baseline", "udp": {"enabled": False}, "mqtt": mqtt,
            "streams": [{"name": "vol"}]}  # fmt: skip
    base.update(over)
    return service_settings(**base)


async def _rogue_publish(broker, topic, payload, user=None, password=None):
    async with aiomqtt.Client(broker.host, broker.port, identifier="rogue", username=user,
                              password=password) as c:  # fmt: skip
        await c.publish(topic, payload, qos=1, retain=True)


def _scene_frames(frames=120):
    cap = moving_clusters(np.random.default_rng(0), subjects=2, markers=5, frames=frames)
    return cap, corrupt(cap, CorruptionSpec(protect_frames=20, seed=3))


def test_the_service_reasserts_its_retained_model_and_status(broker):
    cap, frames = _scene_frames()

    async def go():
        async with Server(_mqtt_settings(broker)) as srv:
            async with open_sender(f"{broker.url}/vol") as (send, stream):
                await replay(frames, send, stream=stream, init_frames=20, speed=0)
            async with asyncio.timeout(10):
                while "vol" not in srv._published_model:
                    await asyncio.sleep(0.05)
            fake = encode_model("vol", 99, ("x:a", "x:b"), (("x", 0, 2),), 100.0)
            await _rogue_publish(broker, "mocap/vol/model", fake)
            await _rogue_publish(broker, "mocap/vol/status", encode_status("vol", "offline"))
            await asyncio.sleep(1.5)  # the service re-publishes (at most twice a second)
            async with Subscriber(f"{broker.url}/vol") as late:
                async with asyncio.timeout(5):
                    while "vol" not in late.models or "vol" not in late.status:
                        await asyncio.sleep(0.02)
                names, status = late.models["vol"].names, late.status["vol"]
            await asyncio.sleep(1.1)  # transport drops reach the metrics once a second
            return names, status, srv.metrics.drops("retained_spoofed", "vol")

    names, status, spoofed = run(go(), timeout=60)
    assert names == tuple(sorted(cap.labels))
    # the service's own status, not the rogue's "offline": the sender stopped over 1 s ago
    assert status == "idle"
    assert spoofed >= 2


@pytest.fixture
def acl_broker(tmp_path):
    """Mosquitto with the shipped ACL and users made by the shipped script."""
    _need_mosquitto()
    secrets = tmp_path / "secrets"
    subprocess.run(["sh", str(ROOT / "scripts" / "make-broker-users.sh"), str(secrets)],
                   check=True, capture_output=True)  # fmt: skip
    b = LocalBroker(tmp_path)
    conf = b.conf.read_text().replace("allow_anonymous true\n", "")
    conf += (f"allow_anonymous false\npassword_file {secrets / 'passwd'}\n"
             f"acl_file {ROOT / 'docker' / 'mosquitto.acl'}\n")  # fmt: skip
    b.conf.write_text(conf)
    b.start()
    pw = {u: (secrets / f"{u}.password").read_text() for u in ("labeler", "replay", "subscriber")}
    try:
        yield b, pw
    finally:
        b.close()


def test_make_broker_users_keeps_existing_passwords(tmp_path):
    _need_mosquitto()
    script = str(ROOT / "scripts" / "make-broker-users.sh")
    subprocess.run(["sh", script, str(tmp_path)], check=True, capture_output=True)
    first = (tmp_path / "labeler.password").read_text()
    subprocess.run(["sh", script, str(tmp_path)], check=True, capture_output=True)
    assert (tmp_path / "labeler.password").read_text() == first
    assert len(first) >= 32
    assert (tmp_path / "labeler.password").stat().st_mode & 0o077 == 0
    assert ".gitignore" and "/docker/secrets/" in (ROOT / ".gitignore").read_text()


def test_the_broker_acl_lets_each_role_do_only_its_job(acl_broker):
    broker, pw = acl_broker
    cap, frames = _scene_frames()
    url = f"mqtt://{broker.host}:{broker.port}/vol"

    def as_user(u):
        return url.replace("mqtt://", f"mqtt://{u}:{pw[u]}@")

    async def go():
        # anonymous: refused
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(broker.host, broker.port, identifier="anon") as c:
                await c.publish("mocap/vol/unlabeled", b"x")
        cfg = _mqtt_settings(broker, "labeler", pw["labeler"])
        async with Server(cfg) as srv:
            async with Subscriber(as_user("subscriber")) as sub:
                assert await sub.wait_status("vol", READY, 5.0)
                async with open_sender(as_user("replay")) as (send, stream):
                    await replay(frames, send, stream=stream, init_frames=20, speed=2.0)
                got = []
                async with asyncio.timeout(10):
                    async for r in sub.frames():
                        got.append(r)
                        if r.msg.seq == 119:
                            break
                # a subscriber (and replay) publishing a retained model: the broker drops it
                fake = encode_model("vol", 99, ("x:a",), (("x", 0, 1),), 100.0)
                for u in ("subscriber", "replay"):
                    await _rogue_publish(broker, "mocap/vol/model", fake, u, pw[u])
                    await _rogue_publish(broker, "mocap/vol/labeled", b"junk", u, pw[u])
                await asyncio.sleep(0.5)
                rejected = sub.stats.rejected
            async with Subscriber(as_user("subscriber")) as late:
                async with asyncio.timeout(5):
                    while "vol" not in late.models:
                        await asyncio.sleep(0.02)
                names = late.models["vol"].names
            return got, rejected, names, srv.metrics

    got, rejected, names, metrics = run(go(), timeout=90)
    assert [r.msg.seq for r in got] == list(range(20, 120))  # the service works as "labeler"
    assert rejected == 0  # no junk "labeled" message reached the subscriber
    assert names == tuple(sorted(cap.labels))  # the fake retained model never landed
    assert metrics.drops("retained_spoofed") == 0


def test_the_services_own_last_will_is_no_spoof(caplog):
    """Mosquitto publishes every client's will at a clean shutdown: the service then read its
    own ``offline`` will on its status topic as another client's, counted it in
    ``retained_spoofed`` (one per stream and broker restart) and logged a warning. Its own will
    is re-published over quietly now; another client's ``offline`` still counts."""
    import logging

    from labeler_service.service.settings import MqttSettings
    from labeler_service.service.transports.mqtt import MqttTransport

    caplog.set_level(logging.INFO, logger="labeler_service.service.transports.mqtt")

    async def go():
        tr = MqttTransport(MqttSettings(enabled=True), ["vol"])
        sent = []

        async def publish(topic, payload, qos=0, retain=False):
            sent.append((topic, payload, retain))
            return True

        tr.clients["vol"].publish = publish  # (no broker: what would be re-published)
        ours = encode_status("vol", "online")
        tr.retained[("vol", "status")] = ours
        tr._check_retained("vol", "status", tr._wills["vol"])
        await asyncio.sleep(0.7)
        will_spoofs = dict(tr.spoofed)
        tr._check_retained("vol", "status", encode_status("vol", "offline"))
        await asyncio.sleep(0.7)
        return will_spoofs, dict(tr.spoofed), sent, ours

    will_spoofs, spoofs, sent, ours = run(go(), timeout=20)
    assert will_spoofs == {}
    assert spoofs == {"vol": 1}
    assert [(t, p, r) for t, p, r in sent] == [("mocap/vol/status", ours, True)] * 2
    assert "last will" in caplog.text and caplog.text.count("replaced by another client") == 1
