"""MQTT through aiomqtt: the service transport and the tools' client, both reconnecting.

Topics (``topic_prefix`` defaults to ``mocap``): ``mocap/<stream>/unlabeled`` (in),
``mocap/<stream>/labeled`` (out, QoS 0), ``mocap/<stream>/model`` (out, retained),
``mocap/<stream>/status`` (out, retained; the connection's last will sets it to ``offline``).

MQTT allows one last will per connection, so the service opens one connection per configured
stream, each with the will on its own status topic. Reconnection lives outside the client
(aiomqtt's recipe): :class:`ReconnectingClient` runs ``async with Client(...)`` in a loop with
exponential backoff (``reconnect_min_s`` doubling to ``reconnect_max_s``), re-subscribes and
re-publishes the retained payloads after every (re)connect. While the broker is down, labeled
frames for MQTT are counted as ``send_error`` and UDP keeps flowing.

aiomqtt is used through its public API; the three latency needs it has no public spelling for
(batch reads, fire-and-forget QoS-0 publish, the QoS-0 outgoing bound) live in
:mod:`._aiomqtt_adapter`, with a guard test.

Retained spoofing: with ``reassert_retained`` (default) each stream's connection also subscribes
to its own ``model`` and ``status`` topics; a retained payload there that is not the service's
own (another client published it, or cleared it) is counted (``retained_spoofed``) and the
service's payload re-published (at most twice a second per topic). The broker ACL
(docker/mosquitto.acl) keeps other clients from publishing there in the first place.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import os
import socket
import ssl
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import aiomqtt

from labeler_service.errors import ProtocolError, TransportError
from labeler_service.service.protocol import encode_status
from labeler_service.service.settings import MqttSettings
from labeler_service.service.transports import _aiomqtt_adapter as adapter
from labeler_service.service.transports.base import (
    Admission,
    DropOldestQueue,
    Incoming,
    cancel_and_wait,
    iterate_queue,
)

log = logging.getLogger(__name__)


#: Outgoing QoS-0 messages queued in paho (not yet written to the socket) at most.
MAX_OUTGOING = 256


def topic(prefix: str, stream: str, kind: str) -> str:
    return f"{prefix}/{stream}/{kind}"


def _tls(settings: MqttSettings) -> aiomqtt.TLSParameters | None:
    if not settings.tls:
        return None
    return aiomqtt.TLSParameters(
        ca_certs=str(settings.ca_file) if settings.ca_file else None,
        certfile=str(settings.cert_file) if settings.cert_file else None,
        keyfile=str(settings.key_file) if settings.key_file else None,
        cert_reqs=ssl.CERT_NONE if settings.tls_insecure else ssl.CERT_REQUIRED,
    )


class ReconnectingClient:
    """One MQTT connection kept alive: connect, subscribe, hand messages over, reconnect.

    ``on_message(message, recv_ns)`` is called for every message; ``on_connect(client)`` after
    every (re)connect and subscription (re-publish retained state there). ``publish`` returns
    False while disconnected instead of waiting (the caller counts it).
    """

    def __init__(
        self,
        settings: MqttSettings,
        identifier: str,
        topics: list[str],
        on_message: Callable[[aiomqtt.Message, int], None],
        on_connect: Callable[[aiomqtt.Client], Awaitable[None]] | None = None,
        will: aiomqtt.Will | None = None,
    ) -> None:
        self.settings = settings
        self.identifier = identifier
        self.topics = topics
        self.on_message = on_message
        self.on_connect = on_connect
        self.will = will
        self.client: aiomqtt.Client | None = None
        self.connected = asyncio.Event()
        self.connects = 0
        self.failures = 0
        self.last_error = ""  # the last connection failure, for :meth:`trouble`
        self._down_since = time.monotonic()  # not connected since (start, or the last drop)

    @property
    def broker(self) -> str:
        return f"{self.settings.host}:{self.settings.port}"

    def trouble(self) -> str | None:
        """What keeps this connection down, with the fix to look for; None while connected.
        One sentence for the service's log and the tools' errors and warnings alike."""
        if self.connected.is_set():
            return None
        down = time.monotonic() - self._down_since
        tries = f"{self.failures} attempt{'s' if self.failures != 1 else ''}"
        last = f"; last: {self.last_error}" if self.last_error else ""
        return (
            f"not connected to the MQTT broker at {self.broker} for {down:.1f} s ({tries}{last}): "
            "is a broker (mosquitto) running there, and are its host and port right?"
        )

    def _make(self) -> aiomqtt.Client:
        s = self.settings
        client = aiomqtt.Client(
            s.host,
            s.port,
            username=s.username,
            password=s.password.get_secret_value() if s.password else None,
            identifier=self.identifier,
            will=self.will,
            keepalive=s.keepalive_s,
            tls_params=_tls(s),
            tls_insecure=s.tls_insecure if s.tls else None,
            timeout=5.0,
            # small frames must not wait for Nagle + delayed ACK (~40 ms on Linux)
            socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),),
            # every received message goes straight to on_message (with its receipt time)
            queue_type=adapter.forwarding_queue(self.on_message),
        )
        adapter.check_client(client)
        return client

    async def run(self) -> None:
        """Runs until cancelled; never raises for broker trouble."""
        backoff = self.settings.reconnect_min_s
        while True:
            try:
                async with self._make() as client:
                    adapter.install_batch_reader(client)
                    for t in self.topics:
                        await client.subscribe(t, qos=0)
                    if self.on_connect is not None:
                        await self.on_connect(client)
                    self.client = client
                    self.connected.set()
                    self.connects += 1
                    backoff = self.settings.reconnect_min_s
                    log.info("mqtt %s: connected to %s:%d", self.identifier, self.settings.host,
                             self.settings.port)  # fmt: skip
                    # Python 3.11's wait_for (inside aiomqtt's subscribe/publish) can swallow
                    # a cancel that lands as it completes; messages already flow (retained
                    # ones arrive with the SUBACK), so a caller may have cancelled us by now
                    task = asyncio.current_task()
                    if task is not None and task.cancelling():
                        raise asyncio.CancelledError
                    # messages reach on_message through the forwarding queue as they are
                    # read; iterating only waits for the disconnect (it raises MqttError)
                    async for _ in client.messages:
                        pass
            except aiomqtt.MqttError as exc:
                task = asyncio.current_task()
                if task is not None and task.cancelling():
                    # cancelled while disconnecting: aiomqtt's __aexit__ may turn the
                    # CancelledError into an MqttError; never reconnect after a cancel
                    raise asyncio.CancelledError from exc
                self.failures += 1
                self.last_error = str(exc)
                level = logging.WARNING if self.failures <= 3 or self.connects else logging.DEBUG
                log.log(level, "mqtt %s: broker %s: %s; retrying in %.1f s", self.identifier,
                        self.broker, exc, backoff)  # fmt: skip
            finally:
                self.client = None
                if self.connected.is_set():
                    self._down_since = time.monotonic()
                self.connected.clear()
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, self.settings.reconnect_max_s)

    async def publish(self, t: str, payload: bytes, retain: bool = False, qos: int = 0) -> bool:
        """Publishes one message; False when it cannot go out.

        QoS 0 is fire-and-forget: handed to paho's outgoing queue without waiting for the
        write (aiomqtt would wait for it, up to the timeout, on a connection that just died:
        the labeling loop must never wait on the broker). That queue is bounded by
        ``MAX_OUTGOING``; beyond it messages are dropped. QoS > 0 waits for the broker's
        acknowledgement, at most 1 s.
        """
        client = self.client
        if client is None:
            return False
        if qos == 0:
            return adapter.publish_nowait(
                client, t, payload, retain=retain, max_outgoing=MAX_OUTGOING
            )
        try:
            await client.publish(t, payload, qos=qos, retain=retain, timeout=1.0)
        except aiomqtt.MqttError:
            return False
        return True


class MqttTransport:
    """The service's MQTT transport: one :class:`ReconnectingClient` per configured stream."""

    name = "mqtt"
    #: the broker delivers whole messages per topic: nothing to pre-filter
    admission: Admission | None = None
    receive_buffer_bytes: int | None = None

    def __init__(self, settings: MqttSettings, streams: list[str], queue_size: int = 1024):
        self.settings = settings
        self.streams = list(streams)
        self._queue: DropOldestQueue[Incoming] = DropOldestQueue(queue_size)
        self.retained: dict[tuple[str, str], bytes] = {}
        self.clients: dict[str, ReconnectingClient] = {}
        self._tasks: list[asyncio.Task] = []
        # retained spoofing (module docstring): what we published lately, per (stream, kind)
        self._recent: dict[tuple[str, str], collections.deque[bytes]] = {}
        self._reasserting: set[tuple[str, str]] = set()
        self._last_reassert: dict[tuple[str, str], float] = {}
        self.spoofed: dict[str, int] = {}
        pid = os.getpid()
        prefix = settings.topic_prefix
        watch = ("model", "status") if settings.reassert_retained else ()
        #: each stream's last will (its ``offline`` status): the broker publishes it when the
        #: connection drops, also at a clean broker shutdown; it is ours, not a spoof
        self._wills: dict[str, bytes] = {}
        for s in self.streams:
            self._wills[s] = encode_status(s, "offline")
            self.clients[s] = ReconnectingClient(
                settings,
                identifier=f"{settings.client_id_prefix}-{s}-{pid}",
                topics=[topic(prefix, s, "unlabeled")] + [topic(prefix, s, k) for k in watch],
                on_message=self._receiver(s),
                on_connect=self._republisher(s),
                will=aiomqtt.Will(topic(prefix, s, "status"), self._wills[s], qos=1, retain=True),
            )

    def _receiver(self, stream: str) -> Callable[[aiomqtt.Message, int], None]:
        def receive(message: aiomqtt.Message, recv_ns: int) -> None:
            payload = message.payload
            if not isinstance(payload, bytes | bytearray):
                payload = str(payload if payload is not None else "").encode()
            kind = str(message.topic).rpartition("/")[2]
            if kind in ("model", "status"):
                self._check_retained(stream, kind, bytes(payload))
                return
            self._queue.put(Incoming(bytes(payload), recv_ns, self.name, None, stream))

        return receive

    def _check_retained(self, stream: str, kind: str, payload: bytes) -> None:
        key = (stream, kind)
        ours = self.retained.get(key)
        if ours is None or payload == ours or payload in self._recent.get(key, ()):
            return  # nothing of ours yet, or our own message coming back
        own_will = kind == "status" and payload == self._wills.get(stream)
        if not own_will:  # (our will, fired by the broker as it shut down: no spoof, no alarm)
            self.spoofed[stream] = self.spoofed.get(stream, 0) + 1
        if key not in self._reasserting:
            self._reasserting.add(key)
            self._tasks.append(
                asyncio.create_task(
                    self._reassert(stream, kind, own_will), name=f"mqtt-reassert-{stream}"
                )
            )

    async def _reassert(self, stream: str, kind: str, will: bool = False) -> None:
        key = (stream, kind)
        try:
            wait = self._last_reassert.get(key, 0.0) + 0.5 - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            self._last_reassert[key] = time.monotonic()
            payload = self.retained.get(key)
            if payload is None:
                return
            if will:
                log.info("mqtt: the broker published stream %s's last will (offline: the "
                         "connection dropped); re-publishing its status",
                         stream)  # fmt: skip
            else:
                log.warning("mqtt: the retained %s of stream %s was replaced by another client; "
                            "re-publishing ours", kind, stream)  # fmt: skip
            await self.clients[stream].publish(
                topic(self.settings.topic_prefix, stream, kind), payload, qos=1, retain=True
            )
        finally:
            self._reasserting.discard(key)
            self._tasks = [t for t in self._tasks if not t.done()]

    def _republisher(self, stream: str) -> Callable[[aiomqtt.Client], Awaitable[None]]:
        async def republish(client: aiomqtt.Client) -> None:
            for (s, kind), payload in list(self.retained.items()):
                if s == stream:
                    await client.publish(
                        topic(self.settings.topic_prefix, s, kind), payload, qos=1, retain=True
                    )

        return republish

    def drop_counts(self) -> dict[tuple[str, str], int]:
        """Cumulative drops inside the transport by ``(stream, reason)``: ``rx_overflow`` (the
        receive queue was full, the oldest message went). A failed labeled publish raises
        (the server counts ``send_error``); model and status are retained here and re-published
        after a reconnect, so a failed publish of those loses nothing."""
        out = {("", "rx_overflow"): self._queue.dropped}
        out.update({(s, "retained_spoofed"): n for s, n in self.spoofed.items()})
        return out

    @property
    def address(self) -> tuple[str, int]:
        """The broker's ``(host, port)``."""
        return (self.settings.host, self.settings.port)

    def subscribe(
        self, reply_to: Any, stream: str, token: bytes | None = None, request_bytes: int = 0
    ) -> None:
        """Always refuses: MQTT clients subscribe at the broker (``subscribe`` is UDP only)."""
        raise ProtocolError("mqtt: subscribe is UDP only (use the broker's topics)", "type")

    async def wait_connected(self, timeout: float) -> bool:
        """True when every stream's connection is up within ``timeout`` seconds."""
        try:
            async with asyncio.timeout(timeout):
                for c in self.clients.values():
                    await c.connected.wait()
        except TimeoutError:
            return False
        return True

    def trouble(self) -> str | None:
        """The first stream connection's :meth:`ReconnectingClient.trouble` (how many of the
        streams' connections are down when more than one is); None while all are up."""
        down = [t for c in self.clients.values() if (t := c.trouble()) is not None]
        if not down:
            return None
        n = len(self.clients)
        return down[0] + (f" ({len(down)} of {n} stream connections down)" if n > 1 else "")

    async def __aenter__(self) -> MqttTransport:
        for s, c in self.clients.items():
            self._tasks.append(asyncio.create_task(c.run(), name=f"mqtt-{s}"))
        # a short grace period so "starting" reaches the broker; no hard dependency on it
        await self.wait_connected(2.0)
        for task in self._tasks:
            if task.done() and not task.cancelled() and task.exception() is not None:
                tasks, self._tasks = self._tasks, []
                await cancel_and_wait(tasks)
                raise TransportError(f"mqtt: {task.exception()}") from task.exception()
        return self

    async def __aexit__(self, *exc: object) -> None:
        tasks, self._tasks = self._tasks, []
        await cancel_and_wait(tasks)

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)

    async def send(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> None:
        client = self.clients.get(stream)
        if client is None:
            return  # a UDP-only stream (not configured for MQTT)
        if retain:
            if self.retained.get((stream, kind)) == payload and kind == "model":
                return  # unchanged and retained by the broker already
            self.retained[(stream, kind)] = payload
            self._recent.setdefault((stream, kind), collections.deque(maxlen=4)).append(payload)
        ok = await client.publish(
            topic(self.settings.topic_prefix, stream, kind),
            payload,
            retain=retain,
            qos=1 if kind == "status" else 0,
        )
        if not ok and kind == "labeled":
            raise TransportError(f"mqtt: not connected to {self.settings.host}:"
                                 f"{self.settings.port}")  # fmt: skip


class MqttEndpoint:
    """The tools' side (replay, subscribe): one reconnecting connection to a broker.

    ``publish(kind, payload)`` sends on ``<prefix>/<stream>/<kind>``; ``messages()`` yields what
    arrives on ``topics`` with the topic's stream in ``Incoming.stream``.
    """

    name = "mqtt"

    def __init__(
        self,
        settings: MqttSettings,
        stream: str,
        topics: list[str] | None = None,
        identifier: str | None = None,
        queue_size: int = 8192,
    ) -> None:
        self.settings = settings
        self.stream = stream
        self._queue: DropOldestQueue[Incoming] = DropOldestQueue(queue_size)
        self.client = ReconnectingClient(
            settings,
            identifier or f"mocap-tool-{os.getpid()}-{id(self):x}",
            topics or [],
            self._receive,
        )
        self._task: asyncio.Task | None = None

    def _receive(self, message: aiomqtt.Message, recv_ns: int) -> None:
        payload = message.payload
        if not isinstance(payload, bytes | bytearray):
            return
        parts = str(message.topic).split("/")
        stream = parts[-2] if len(parts) >= 3 else None
        self._queue.put(Incoming(bytes(payload), recv_ns, self.name, None, stream))

    @property
    def received_dropped(self) -> int:
        return self._queue.dropped

    async def __aenter__(self) -> MqttEndpoint:
        self._task = asyncio.create_task(self.client.run(), name=f"mqtt-{self.client.identifier}")
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            await cancel_and_wait([self._task])
            self._task = None

    def trouble(self) -> str | None:
        """:meth:`ReconnectingClient.trouble` of the one connection."""
        return self.client.trouble()

    async def wait_connected(self, timeout: float) -> bool:
        try:
            async with asyncio.timeout(timeout):
                await self.client.connected.wait()
        except TimeoutError:
            return False
        return True

    async def publish(self, kind: str, payload: bytes) -> bool:
        return await self.client.publish(
            topic(self.settings.topic_prefix, self.stream, kind), payload
        )

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)
