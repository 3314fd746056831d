"""An in-memory transport: tests inject raw payloads and read what the server sent."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

from labeler_service.errors import ProtocolError, TransportError
from labeler_service.service.transports.base import (
    Admission,
    DropOldestQueue,
    Incoming,
    iterate_queue,
)


class MemoryTransport:
    """Implements the transport interface with two queues and no sockets.

    ``inject(payload)`` delivers a message as if it came from the network; everything the
    server sends lands in ``sent`` (a list of ``(stream, kind, payload, retain)``) and in the
    ``outbox`` queue, which tests await with :meth:`next_sent`. ``retained`` mirrors MQTT's
    retained messages; ``subscribers`` records ``subscribe`` messages as UDP would.
    """

    name = "memory"
    admission: Admission | None = None  # no raw datagrams to peek at
    receive_buffer_bytes: int | None = None

    def __init__(self, maxsize: int = 10_000) -> None:
        self._in: DropOldestQueue[Incoming] = DropOldestQueue(maxsize)
        self.outbox: asyncio.Queue[tuple[str, str, bytes, bool]] = asyncio.Queue()
        self.sent: list[tuple[str, str, bytes, bool]] = []
        self.retained: dict[tuple[str, str], bytes] = {}
        self.entered = False
        self.closed = False
        self.fail_sends = False  # tests: simulate a broken link
        self.down: str | None = None  # tests: what :meth:`trouble` says (a link that is down)
        self.subscribers: dict[object, str] = {}

    async def __aenter__(self) -> MemoryTransport:
        self.entered = True
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.closed = True

    def inject(self, payload: bytes, reply_to: object = None, stream: str | None = None) -> None:
        self._in.put(Incoming(payload, time.time_ns(), self.name, reply_to, stream))

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._in)

    @property
    def address(self) -> tuple[str, int]:
        return ("memory", 0)

    def subscribe(
        self, reply_to: object, stream: str, token: bytes | None = None, request_bytes: int = 0
    ) -> None:
        """Records a subscriber (the address a test passed to :meth:`inject`)."""
        if reply_to is None:
            raise ProtocolError("memory: subscribe needs a reply address", "type")
        self.subscribers[reply_to] = stream

    def trouble(self) -> str | None:
        """``down`` when set (a test's broken transport), else None."""
        return self.down

    def drop_counts(self) -> dict[tuple[str, str], int]:
        """Injected messages the full inbox discarded (``rx_overflow``), as UDP and MQTT do."""
        return {("", "rx_overflow"): self._in.dropped}

    async def send(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> None:
        if self.fail_sends:
            raise TransportError("memory transport: sends disabled")
        if retain:
            self.retained[(stream, kind)] = payload
        item = (stream, kind, payload, retain)
        self.sent.append(item)
        self.outbox.put_nowait(item)

    async def next_sent(self, kind: str | None = None, timeout: float = 5.0) -> bytes:
        """The next sent payload (of ``kind`` when given), waiting up to ``timeout`` seconds."""
        async with asyncio.timeout(timeout):
            while True:
                _, k, payload, _ = await self.outbox.get()
                if kind is None or k == kind:
                    return payload
