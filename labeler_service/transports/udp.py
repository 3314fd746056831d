"""UDP on asyncio ``DatagramProtocol``: the service endpoint and a small client endpoint.

The service binds one socket (loopback by default). Frames arrive from any sender; outgoing
messages go to the fixed ``publish_to`` destinations and to subscribers that registered with a
``subscribe`` datagram (renewed at least every ``subscriber_ttl_s``). Retained payloads (model,
status) are sent to a subscriber when it registers, so a late subscriber decodes at once; the
server repeats the model message every second anyway.

A datagram is at most 65 507 bytes (:data:`~labeler_service.config.UDP_MAX_PAYLOAD`); larger
outgoing payloads raise :class:`~labeler_service.errors.ProtocolError` (``oversize``) and are
counted by the caller.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import AsyncIterator

from labeler_service.config import UDP_MAX_PAYLOAD, UdpSettings
from labeler_service.errors import ProtocolError
from labeler_service.transports.base import DropOldestQueue, Incoming, iterate_queue

log = logging.getLogger(__name__)
Addr = tuple[str, int]


def parse_hostport(dest: str) -> Addr:
    host, _, port = dest.rpartition(":")
    return host.strip("[]"), int(port)


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, queue: DropOldestQueue[Incoming], name: str) -> None:
        self.queue = queue
        self.name = name
        self.errors = 0
        self.closed = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr: Addr) -> None:
        self.queue.put(Incoming(data, time.time_ns(), self.name, addr))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable from a vanished subscriber and the like: counted, not fatal
        self.errors += 1

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


def _tune(sock: socket.socket, size: int) -> None:
    for opt in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, size)
        except OSError:  # pragma: no cover - platform limits
            log.debug("could not set socket buffer %s to %d", opt, size)


class UdpTransport:
    """The service's UDP endpoint (see the module docstring)."""

    name = "udp"

    def __init__(self, settings: UdpSettings, queue_size: int = 1024) -> None:
        self.settings = settings
        self._queue: DropOldestQueue[Incoming] = DropOldestQueue(queue_size)
        self._transport: asyncio.DatagramTransport | None = None
        self._protocol: _Protocol | None = None
        self._static = [parse_hostport(d) for d in settings.publish_to]
        # subscriber address -> (stream or "*", last renewal, monotonic s)
        self.subscribers: dict[Addr, tuple[str, float]] = {}
        self.retained: dict[tuple[str, str], bytes] = {}
        self.send_errors = 0

    @property
    def address(self) -> Addr:
        """The bound ``(host, port)`` (port 0 in the settings picks a free one)."""
        if self._transport is None:
            raise RuntimeError("UdpTransport is not open")
        return self._transport.get_extra_info("sockname")[:2]

    @property
    def received_dropped(self) -> int:
        return self._queue.dropped

    async def __aenter__(self) -> UdpTransport:
        loop = asyncio.get_running_loop()
        self._transport, self._protocol = await loop.create_datagram_endpoint(
            lambda: _Protocol(self._queue, self.name),
            local_addr=(self.settings.host, self.settings.port),
        )
        _tune(self._transport.get_extra_info("socket"), self.settings.socket_buffer_bytes)
        log.info("udp: listening on %s:%d", *self.address)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._transport is not None:
            self._transport.close()
            assert self._protocol is not None
            await self._protocol.closed
            self._transport = None

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)

    def subscribe(self, addr: Addr, stream: str) -> None:
        """Registers or renews a subscriber; new ones receive the retained payloads at once."""
        is_new = addr not in self.subscribers
        if is_new and len(self.subscribers) >= self.settings.max_subscribers:
            self._expire()
            if len(self.subscribers) >= self.settings.max_subscribers:
                raise ProtocolError(f"udp: subscriber limit reached, {addr} refused", "field")
        self.subscribers[addr] = (stream, time.monotonic())
        if is_new:
            log.info("udp: subscriber %s:%d for stream %s", addr[0], addr[1], stream)
            for (s, _), payload in list(self.retained.items()):
                if stream in ("*", s):
                    self._sendto(payload, addr)

    def _expire(self) -> None:
        cutoff = time.monotonic() - self.settings.subscriber_ttl_s
        for addr, (_, last) in list(self.subscribers.items()):
            if last < cutoff:
                del self.subscribers[addr]
                log.info("udp: subscriber %s:%d expired", addr[0], addr[1])

    def _sendto(self, payload: bytes, addr: Addr) -> None:
        assert self._transport is not None
        try:
            self._transport.sendto(payload, addr)
        except OSError:
            self.send_errors += 1

    async def send(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> None:
        if self._transport is None:
            raise RuntimeError("UdpTransport is not open")
        if len(payload) > UDP_MAX_PAYLOAD:
            raise ProtocolError(
                f"udp: {kind} message of {len(payload)} bytes exceeds {UDP_MAX_PAYLOAD}",
                "oversize",
            )
        if retain:
            self.retained[(stream, kind)] = payload
        for addr in self._static:
            self._sendto(payload, addr)
        if kind == "model":
            self._expire()  # once a second is often enough
        for addr, (want, _) in self.subscribers.items():
            if want == "*" or want == stream:
                self._sendto(payload, addr)


class UdpClient:
    """A client endpoint: sends to ``remote`` and receives what comes back to its port.

    Used by ``replay`` (send frames) and ``subscribe`` (register, then receive labeled frames).
    """

    name = "udp"

    def __init__(self, host: str, port: int, queue_size: int = 4096, buffer: int = 4 << 20):
        self.remote = (host, port)
        self._queue: DropOldestQueue[Incoming] = DropOldestQueue(queue_size)
        self._buffer = buffer
        self._transport: asyncio.DatagramTransport | None = None
        self._protocol: _Protocol | None = None

    @property
    def received_dropped(self) -> int:
        return self._queue.dropped

    async def __aenter__(self) -> UdpClient:
        loop = asyncio.get_running_loop()
        self._transport, self._protocol = await loop.create_datagram_endpoint(
            lambda: _Protocol(self._queue, self.name), remote_addr=self.remote
        )
        _tune(self._transport.get_extra_info("socket"), self._buffer)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._transport is not None:
            self._transport.close()
            assert self._protocol is not None
            await self._protocol.closed
            self._transport = None

    def send(self, payload: bytes) -> None:
        if self._transport is None:
            raise RuntimeError("UdpClient is not open")
        if len(payload) > UDP_MAX_PAYLOAD:
            raise ProtocolError(f"udp: message of {len(payload)} bytes is too large", "oversize")
        self._transport.sendto(payload)

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)
