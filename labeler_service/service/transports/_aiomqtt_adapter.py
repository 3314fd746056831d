"""The only module that touches aiomqtt's internals, for the three things its public API lacks.

aiomqtt (tested: :data:`TESTED_MINORS`, pinned in ``pyproject.toml``) is used through its
public API everywhere else: ``Client(...)`` with ``queue_type`` (our forwarding queue below),
``publish``, ``subscribe``, ``messages`` and :class:`aiomqtt.MqttError`. Three latency needs have
no public spelling:

1. **Batch reads.** aiomqtt's socket reader calls paho's ``loop_read`` once per readiness event,
   and paho reads one packet per call: while the service is busy labeling, a backlog waits in
   TCP buffers, out of reach of our drop-oldest queues. :func:`install_batch_reader` replaces
   the reader with one that loops while the socket stays readable. Needs ``Client._client``
   (the paho client) and ``Client._disconnected`` (the future aiomqtt's reader fails on a
   broken connection, as aiomqtt's own reader does).
2. **Fire-and-forget QoS-0 publish.** ``Client.publish`` waits for the write (up to its
   timeout) when paho could not write at once; the labeling loop must never wait on the broker.
   :func:`publish_nowait` hands the message to paho's outgoing queue and returns.
3. **The outgoing bound.** aiomqtt's ``max_queued_outgoing_messages`` bounds paho's QoS > 0
   messages only; QoS-0 packets queue without limit in paho's ``_out_packet``.
   :func:`publish_nowait` refuses a message when that queue holds ``max_outgoing`` packets.

Incoming messages need no private access: aiomqtt's public ``queue_type`` argument takes our
:func:`forwarding_queue`, whose ``put_nowait`` hands every message to the transport at once
(with its receipt time) instead of queueing it to be handed out one per loop iteration.

``tests/service/test_aiomqtt_adapter.py`` is the guard: it fails loudly, naming the attribute,
when an aiomqtt or paho release changes any of this. :func:`check_client` makes the same check
at every connect, so a mismatched install fails with a clear
:class:`~labeler_service.errors.TransportError` instead of silently losing the batching.
"""

from __future__ import annotations

import asyncio
import select
import ssl
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import aiomqtt
import paho.mqtt.client as paho_mqtt

from labeler_service.errors import TransportError

#: aiomqtt minor versions this adapter was tested with (``pyproject.toml`` pins the same).
TESTED_MINORS: tuple[str, ...] = ("2.5",)


def check_client(client: aiomqtt.Client) -> None:
    """Raises :class:`TransportError` naming what is missing when ``client`` lacks the internals
    this module relies on (an untested aiomqtt or paho release)."""
    problems = []
    paho = client.__dict__.get("_client")
    if not isinstance(paho, paho_mqtt.Client):
        problems.append("Client._client is not a paho.mqtt.client.Client")
    else:
        if not isinstance(paho.__dict__.get("_out_packet"), deque):
            problems.append("paho Client._out_packet is not a deque")
        for name in ("socket", "loop_read", "publish"):
            if not callable(getattr(type(paho), name, None)):
                problems.append(f"paho Client.{name}() is missing")
    if not isinstance(client.__dict__.get("_disconnected"), asyncio.Future):
        problems.append("Client._disconnected is not an asyncio.Future")
    if problems:
        raise TransportError(
            f"aiomqtt {aiomqtt.__version__} is not supported by the MQTT transport "
            f"(tested: {', '.join(TESTED_MINORS)}): {'; '.join(problems)}"
        )


def forwarding_queue(
    on_message: Callable[[aiomqtt.Message, int], None],
) -> type[asyncio.Queue[aiomqtt.Message]]:
    """A ``queue_type`` for ``aiomqtt.Client`` that queues nothing: each message aiomqtt
    receives goes straight to ``on_message(message, time.time_ns())``.

    ``client.messages`` then never yields; iterating it only waits for the disconnect (it
    raises :class:`aiomqtt.MqttError` then), which is what the reconnect loop needs.
    """

    class ForwardingQueue(asyncio.Queue[aiomqtt.Message]):
        def put_nowait(self, item: aiomqtt.Message) -> None:
            on_message(item, time.time_ns())

    return ForwardingQueue


def install_batch_reader(client: aiomqtt.Client) -> None:
    """Makes one socket readiness event read *every* MQTT packet already received (item 1 of
    the module docstring). Call right after connecting."""
    paho: paho_mqtt.Client = client._client
    disconnected: asyncio.Future[Any] = client._disconnected
    sock = paho.socket()
    if sock is None:  # the connection died already: aiomqtt reports it to the reconnect loop
        return
    fd = sock.fileno()
    loop = asyncio.get_running_loop()

    def drain() -> None:
        try:
            for _ in range(10_000):
                paho.loop_read()
                raw = paho.socket()
                if raw is None:
                    return
                if isinstance(raw, ssl.SSLSocket) and raw.pending() > 0:
                    continue  # TLS: decrypted bytes already buffered
                if not select.select([fd], [], [], 0)[0]:
                    return
        except Exception as exc:  # a broken connection: let aiomqtt see it, as its reader does
            if not disconnected.done():
                disconnected.set_exception(exc)

    loop.remove_reader(fd)
    loop.add_reader(fd, drain)


def publish_nowait(
    client: aiomqtt.Client, topic: str, payload: bytes, *, retain: bool, max_outgoing: int
) -> bool:
    """Queues one QoS-0 message in paho without waiting for the write (items 2 and 3); False
    when ``max_outgoing`` packets are already waiting or paho refuses it."""
    paho: paho_mqtt.Client = client._client
    if len(paho._out_packet) >= max_outgoing:
        return False
    info = paho.publish(topic, payload, qos=0, retain=retain)
    return info.rc == paho_mqtt.MQTT_ERR_SUCCESS
