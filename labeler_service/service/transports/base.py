"""The transport interface: a source of raw messages and a sink for outgoing ones.

A transport is an async context manager (it owns sockets and tasks) with

* ``messages()`` — an async iterator of :class:`Incoming` (raw payload, receipt time, where it
  came from). Decoding and validation belong to the server (``protocol.decode``), once.
* ``send(stream, kind, payload, retain=False)`` — publish one encoded message of ``kind``
  (``labeled``, ``model``, ``status``) for ``stream``. ``retain=True`` keeps the latest payload
  per (stream, kind) and replays it to late subscribers (MQTT retained flag; UDP on
  registration) and after reconnects.
* ``drop_counts()`` — cumulative counts of what the transport dropped itself, by
  ``(stream, reason)`` (e.g. ``("", "rx_overflow")``); the server adds the increments to
  ``mocap_dropped_total`` once a second (no per-frame cost).
* ``subscribe(reply_to, stream)`` — registers the sender of a ``subscribe`` message (UDP);
  a transport without subscriptions raises :class:`~labeler_service.errors.ProtocolError`
  (reason ``type``), which the server counts like any rejected message.
* ``address`` — the ``(host, port)`` the transport serves on (UDP: the bound socket; MQTT: the
  broker), for the ``ready`` line of ``serve``.

A failed ``send`` raises :class:`~labeler_service.errors.TransportError` (counted as
``send_error``) or :class:`~labeler_service.errors.ProtocolError` (``output_oversize``).

:class:`~labeler_service.service.transports.memory.MemoryTransport` implements it without sockets
for
pipeline and server tests (after httpx ``MockTransport``).
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

T = TypeVar("T")


@dataclass(slots=True)
class Incoming:
    """One received message before decoding."""

    payload: bytes
    recv_ns: int  # time.time_ns() at receipt
    transport: str  # "udp", "mqtt", "memory"
    reply_to: Any = None  # UDP: sender address (for subscribe); else None
    stream: str | None = None  # MQTT: the topic's stream (must match the payload's)


#: The server's pre-filter of raw incoming frames: ``(stream, payload) -> queue key`` (None:
#: drop the frame unread as ``unknown_stream``). Transports that can peek a frame's header
#: before decoding it (UDP) use it; the others ignore it.
Admission = Callable[[str, bytes], "str | None"]


class Transport(Protocol):
    """Everything the server uses of a transport (see the module docstring)."""

    name: str
    #: set by the server before ``__aenter__``; None admits everything
    admission: Admission | None

    async def __aenter__(self) -> Transport: ...

    async def __aexit__(self, *exc: object) -> None: ...

    def messages(self) -> AsyncIterator[Incoming]: ...

    async def send(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> None: ...

    def subscribe(
        self, reply_to: Any, stream: str, token: bytes | None = None, request_bytes: int = 0
    ) -> None: ...

    def drop_counts(self) -> dict[tuple[str, str], int]: ...

    @property
    def address(self) -> tuple[str, int]: ...

    def trouble(self) -> str | None:
        """What keeps the transport from carrying frames now, with the fix to look for (the
        broker unreachable); None when it works. Logged with the periodic line and counted in
        ``mocap_transport_up``."""
        ...

    @property
    def receive_buffer_bytes(self) -> int | None:
        """The kernel receive buffer the transport's socket got; None when it has none of its
        own (the broker's client)."""
        ...


class DropOldestQueue(Generic[T]):
    """A bounded FIFO for real-time data: when full, ``put`` discards the oldest item.

    ``put`` never blocks and returns the discarded item (or ``None``) so the caller can count
    it; ``dropped`` counts them all. ``get`` waits for an item; ``get_or_wake`` also returns
    ``None`` once :meth:`wake` was called while the queue was empty (the stream's worker is
    woken to install a boot result between frames).
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self.maxsize = maxsize
        self.dropped = 0
        self._items: deque[T] = deque()
        self._event = asyncio.Event()
        self._woken = False

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: T) -> T | None:
        old = None
        if len(self._items) >= self.maxsize:
            old = self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._event.set()
        return old

    async def get(self) -> T:
        while not self._items:
            self._event.clear()
            await self._event.wait()
        return self._items.popleft()

    def wake(self) -> None:
        """Makes the next :meth:`get_or_wake` that finds the queue empty return ``None``."""
        self._woken = True
        self._event.set()

    async def get_or_wake(self) -> T | None:
        """The oldest item (waiting for one), or ``None`` when :meth:`wake` was called and no
        item is there (items first: a frame already waiting is served before the wake)."""
        while not self._items:
            if self._woken:
                self._woken = False
                return None
            self._event.clear()
            await self._event.wait()
        return self._items.popleft()

    def get_nowait(self) -> T | None:
        return self._items.popleft() if self._items else None


class FairQueue(Generic[T]):
    """A bounded queue shared by several sources, fair between them (the UDP receive queue).

    Items are put with a ``key`` (the stream a datagram is for, ``""`` for everything the
    receiver could not or would not attribute: unknown streams, subscribe requests). ``get``
    serves the keys round-robin, one item each, oldest first within a key, so a backlog of one
    key (a flood) delays another key's items by at most one item per other key. When the queue
    holds ``maxsize`` items, ``put`` drops the oldest item of the **largest** key: a flood of
    junk or of one stream evicts its own items, never the few of a quiet stream. ``put``
    returns ``(key, item)`` of the dropped item (or ``None``); ``dropped`` counts them all.
    Same interface as :class:`DropOldestQueue` otherwise.
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self.maxsize = maxsize
        self.dropped = 0
        self._buckets: dict[str, deque[T]] = {}
        self._order: deque[str] = deque()  # keys with items, in round-robin order
        self._n = 0
        self._event = asyncio.Event()

    def __len__(self) -> int:
        return self._n

    def depth(self, key: str) -> int:
        """Items queued under ``key``."""
        b = self._buckets.get(key)
        return len(b) if b is not None else 0

    def put(self, item: T, key: str = "") -> tuple[str, T] | None:
        b = self._buckets.get(key)
        if b is None:
            b = self._buckets[key] = deque()
            self._order.append(key)
        b.append(item)
        self._n += 1
        old = None
        if self._n > self.maxsize:
            big = max(self._order, key=lambda k: len(self._buckets[k]))
            victim = self._buckets[big]
            old = (big, victim.popleft())
            self._n -= 1
            self.dropped += 1
            if not victim:
                del self._buckets[big]
                self._order.remove(big)
        self._event.set()
        return old

    def _pop(self) -> T:
        key = self._order.popleft()
        b = self._buckets[key]
        item = b.popleft()
        self._n -= 1
        if b:
            self._order.append(key)
        else:
            del self._buckets[key]
        return item

    async def get(self) -> T:
        while not self._n:
            self._event.clear()
            await self._event.wait()
        return self._pop()

    def get_nowait(self) -> T | None:
        return self._pop() if self._n else None


async def cancel_and_wait(tasks: Iterable[asyncio.Task]) -> None:
    """Cancels every task, then waits until all have ended (their exceptions are dropped)."""
    tasks = list(tasks)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


async def iterate_queue(queue: DropOldestQueue[T] | FairQueue[T]) -> AsyncIterator[T]:
    while True:
        yield await queue.get()
