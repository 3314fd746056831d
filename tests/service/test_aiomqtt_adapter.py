"""Guard of ``service/transports/_aiomqtt_adapter.py``: the aiomqtt/paho internals it relies on.

If one of these fails after an upgrade, aiomqtt or paho changed what the adapter reads; fix the
adapter (or pin the old release) before anything else. The installed aiomqtt must be one of
the tested minor versions, and pyproject's pin must say the same.
"""

from __future__ import annotations

import asyncio
import re
import tomllib
from collections import deque
from pathlib import Path

import aiomqtt
import paho.mqtt.client as paho_mqtt
import pytest
from service.helpers import run

from labeler_service.errors import TransportError
from labeler_service.service.settings import MqttSettings
from labeler_service.service.transports import _aiomqtt_adapter as adapter
from labeler_service.service.transports.mqtt import ReconnectingClient

ROOT = Path(__file__).resolve().parents[2]


def _minor(version: str) -> str:
    return ".".join(version.split(".")[:2])


def test_installed_aiomqtt_is_a_tested_minor_and_pyproject_pins_exactly_those():
    assert _minor(aiomqtt.__version__) in adapter.TESTED_MINORS, (
        f"aiomqtt {aiomqtt.__version__} is untested: check the adapter, then add its minor"
    )
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    (pin,) = [d for d in deps if d.startswith("aiomqtt")]
    lo, hi = re.fullmatch(r"aiomqtt>=(\d+\.\d+),<(\d+\.\d+)", pin).groups()
    major, lo_minor = lo.split(".")
    hi_major, hi_minor = hi.split(".")
    assert hi_major == major
    assert (
        tuple(f"{major}.{m}" for m in range(int(lo_minor), int(hi_minor))) == adapter.TESTED_MINORS
    )


def test_the_private_attributes_the_adapter_reads_are_there():
    async def go():
        client = aiomqtt.Client("127.0.0.1", 1)
        paho = client.__dict__.get("_client")
        assert isinstance(paho, paho_mqtt.Client), "aiomqtt.Client._client is gone"
        assert isinstance(paho.__dict__.get("_out_packet"), deque), "paho _out_packet changed"
        assert isinstance(client.__dict__.get("_disconnected"), asyncio.Future)
        for name in ("socket", "loop_read", "publish"):
            assert callable(getattr(paho, name))
        adapter.check_client(client)  # and the run-time check agrees

    run(go())


def test_check_client_names_what_is_missing():
    async def go():
        client = aiomqtt.Client("127.0.0.1", 1)
        del client.__dict__["_disconnected"]
        with pytest.raises(TransportError, match="_disconnected"):
            adapter.check_client(client)

    run(go())


def test_aiomqtt_hands_received_messages_to_the_queue_types_put_nowait():
    """The forwarding queue relies on aiomqtt's receive callback calling ``put_nowait``."""
    got = []

    async def go():
        client = aiomqtt.Client(
            "127.0.0.1", 1, queue_type=adapter.forwarding_queue(lambda m, ns: got.append((m, ns)))
        )
        msg = paho_mqtt.MQTTMessage(topic=b"mocap/s/unlabeled")
        msg.payload = b"x"
        client._client.on_message(client._client, None, msg)
        assert len(client.messages) == 0  # nothing queued in aiomqtt

    run(go())
    assert len(got) == 1 and got[0][0].payload == b"x" and got[0][1] > 0


@pytest.mark.broker
def test_batch_reader_and_publish_nowait_against_a_real_broker(broker):
    """Through the batch reader every message of a burst arrives, in order; QoS-0 publishes
    return without awaiting and stop at the outgoing bound."""
    settings = MqttSettings(host=broker.host, port=broker.port)
    received: list[bytes] = []

    async def go():
        sub = ReconnectingClient(
            settings, "guard-sub", ["guard/t"], lambda m, ns: received.append(m.payload)
        )
        pub = ReconnectingClient(settings, "guard-pub", [], lambda m, ns: None)
        tasks = [asyncio.create_task(c.run()) for c in (sub, pub)]
        try:
            async with asyncio.timeout(10):
                await sub.connected.wait()
                await pub.connected.wait()
            assert pub.client is not None
            for i in range(50):
                assert adapter.publish_nowait(
                    pub.client, "guard/t", b"%d" % i, retain=False, max_outgoing=10_000
                )
            async with asyncio.timeout(10):
                while len(received) < 50:
                    await asyncio.sleep(0.01)
            # the bound: with max_outgoing=0 nothing is queued
            assert not adapter.publish_nowait(
                pub.client, "guard/t", b"no", retain=False, max_outgoing=0
            )
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    run(go())
    assert received == [b"%d" % i for i in range(50)]
