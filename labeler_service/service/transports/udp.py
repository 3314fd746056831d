"""UDP with non-blocking sockets on the asyncio loop: the service endpoint and a client endpoint.

The service binds one socket (loopback by default). Frames arrive from any sender; outgoing
messages go to the fixed ``publish_to`` destinations and to subscribers that registered with a
``subscribe`` datagram (renewed at least every ``subscriber_ttl_s``). Retained payloads (model,
status) are sent to a subscriber when it registers, so a late subscriber decodes at once; the
server repeats the model message every second anyway.

**Subscriber confirmation** (anti-reflection): UDP source addresses can be forged, so an address
is sent nothing larger than what it sent until it proves it receives at that address. A
``subscribe`` from an unknown address is answered with a ``challenge`` (a stateless 8-byte token,
an HMAC of address, stream and a time window under a per-process secret) only when the request
is at least as large as the challenge (our client pads it); the subscriber echoes the token in
its next ``subscribe`` and is then registered (a wrong or stale token gets a fresh challenge,
so a subscriber that expired during a stall re-confirms by itself). Refusals raise
:class:`~labeler_service.errors.ProtocolError` with their own reasons: ``subscribe_short``,
``subscribe_token`` (wrong or stale token), ``subscribe_host_limit`` (more than
``max_subscribers_per_host`` confirmed per source IP), ``subscribe_full`` (``max_subscribers``).

**Receive queue and pre-filter**: each datagram is classified before decoding. With the
server's ``admission`` set, a frame's stream is read from its header
(:func:`~labeler_service.service.protocol.peek_frame_stream`) and the server answers with the
receive-queue key (the stream's name) or None: the datagram is then dropped unread and counted
as ``unknown_stream`` (a flood for unknown streams costs a few microseconds per datagram).
Everything else (not a frame, not peekable) is queued under ``""`` and decoded in full. The
queue (:class:`~labeler_service.service.transports.base.FairQueue`) serves the keys
round-robin and, when full, drops the oldest datagram of the largest key (``rx_overflow``).
The kernel buffer asked for is ``socket_buffer_bytes``; where Linux clamps it to
``net.core.rmem_max`` the socket retries with ``SO_RCVBUFFORCE`` (CAP_NET_ADMIN) and a buffer
still below the request is logged at start-up (:attr:`UdpTransport.receive_buffer_bytes`).

**Kernel drops**: on Linux the socket asks for ``SO_RXQ_OVFL``; every datagram then carries the
count of datagrams the kernel dropped on this socket because its receive buffer was full, which
:meth:`UdpTransport.drop_counts` reports as ``kernel_rx_overflow``. Elsewhere that loss is not
visible to the service (docs/service.md, "Security and limits").

A datagram is at most 65 507 bytes (:data:`~labeler_service.service.settings.UDP_MAX_PAYLOAD`);
larger
outgoing payloads raise :class:`~labeler_service.errors.ProtocolError` (``oversize``) and are
counted by the caller. A datagram the kernel refuses (send buffer full, unreachable) is counted
per stream and destination; :meth:`UdpTransport.drop_counts` hands these and the receive
queue's overflow to the server's metrics.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import os
import socket
import struct
import sys
import time
from collections.abc import AsyncIterator, Callable

from labeler_service.errors import ConfigError, ProtocolError
from labeler_service.service.protocol import TOKEN_BYTES, encode_challenge, peek_frame_stream
from labeler_service.service.settings import UDP_MAX_PAYLOAD, UdpSettings
from labeler_service.service.transports.base import (
    Admission,
    DropOldestQueue,
    FairQueue,
    Incoming,
    iterate_queue,
)

log = logging.getLogger(__name__)
Addr = tuple[str, int]

#: Linux ``SO_RXQ_OVFL`` (socket(7)); Python's socket module does not export it.
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_OVFL_SPACE = socket.CMSG_SPACE(4) if hasattr(socket, "CMSG_SPACE") else 0
#: Linux ``SO_RCVBUFFORCE``/``SO_SNDBUFFORCE`` (socket(7)): exceed ``net.core.rmem_max`` /
#: ``wmem_max`` with CAP_NET_ADMIN (root); Python does not export them.
_FORCE = {socket.SO_RCVBUF: 33, socket.SO_SNDBUF: 32} if sys.platform.startswith("linux") else {}
#: A received datagram's queue key, or None to drop it unread (see :class:`_Socket`).
Classify = Callable[[bytes], "str | None"]


def parse_hostport(dest: str) -> Addr:
    host, _, port = dest.rpartition(":")
    return host.strip("[]"), int(port)


class _Socket:
    """A non-blocking UDP socket read with ``loop.add_reader``.

    Every readiness event drains *all* pending datagrams into the bounded queue, so when the
    service falls behind the backlog lands in our drop-oldest queues (counted) instead of
    piling up unseen in the kernel buffer (asyncio's DatagramTransport reads one datagram per
    loop iteration).
    """

    def __init__(
        self,
        queue: DropOldestQueue[Incoming] | FairQueue[Incoming],
        name: str,
        buffer: int,
        classify: Classify | None = None,
    ) -> None:
        self.queue = queue
        self.name = name
        #: with a :class:`FairQueue`: each datagram's key; ``None`` drops it before decoding
        #: (counted in ``prefiltered``)
        self.classify = classify
        self.prefiltered = 0
        #: ICMP "port unreachable" reports (connected sockets: nothing listens at the peer),
        #: read by a receive or a send; the kernel keeps one pending, so it is a lower bound
        self.refused = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        #: what the kernel granted (``getsockopt``; Linux reports twice the usable bytes)
        self.receive_buffer, self.buffer_clamped = _tune(self.sock, buffer)
        self._loop: asyncio.AbstractEventLoop | None = None
        #: datagrams the kernel dropped on this socket (SO_RXQ_OVFL); None: not available
        self.kernel_dropped: int | None = None
        self._ovfl = False
        if _OVFL_SPACE and hasattr(self.sock, "recvmsg"):
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self._ovfl = True
                self.kernel_dropped = 0
            except OSError:  # not Linux: the gap is documented
                pass

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.sock.fileno(), self._readable)

    def _readable(self) -> None:
        if self._ovfl:
            self._readable_msg()
            return
        recv = self.sock.recvfrom
        for _ in range(100_000):
            try:
                data, addr = recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                # ICMP port unreachable after a send to a vanished peer (connected sockets):
                # an error report, not a lost datagram; not fatal
                self.refused += 1
                return
            except OSError:  # another ICMP error report
                return
            self._put(data, addr)

    def _put(self, data: bytes, addr: Addr) -> None:
        classify = self.classify
        if classify is None:
            self.queue.put(Incoming(data, time.time_ns(), self.name, addr))
            return
        key = classify(data)
        if key is None:
            self.prefiltered += 1
            return
        self.queue.put(Incoming(data, time.time_ns(), self.name, addr), key)  # type: ignore[call-arg]

    def _readable_msg(self) -> None:
        """As :meth:`_readable`, with ``recvmsg`` to read the SO_RXQ_OVFL drop counter."""
        recv = self.sock.recvmsg
        put = self._put
        dropped = self.kernel_dropped
        try:
            for _ in range(100_000):
                try:
                    data, anc, _, addr = recv(65536, _OVFL_SPACE)
                except (BlockingIOError, InterruptedError):
                    return
                except ConnectionRefusedError:  # an ICMP error report (see _readable)
                    self.refused += 1
                    return
                except OSError:
                    return
                for level, kind, cdata in anc:
                    if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(cdata) >= 4:
                        dropped = struct.unpack("=I", cdata[:4])[0]
                put(data, addr)
        finally:
            self.kernel_dropped = dropped

    def sendto(self, payload: bytes, addr: Addr | None) -> bool:
        try:
            if addr is None:
                self.sock.send(payload)
            else:
                self.sock.sendto(payload, addr)
        except ConnectionRefusedError:  # the pending report of an earlier datagram
            self.refused += 1
            return False
        except OSError:  # buffer full, unreachable: UDP is best effort (callers count it)
            return False
        return True

    def close(self) -> None:
        if self._loop is not None:
            self._loop.remove_reader(self.sock.fileno())
            self._loop = None
        self.sock.close()


def _tune(sock: socket.socket, size: int) -> tuple[int, bool]:
    """Asks for ``size``-byte kernel buffers; where the OS clamps them (``net.core.rmem_max``)
    retries with ``SO_RCVBUFFORCE`` (Linux, CAP_NET_ADMIN). Returns the receive buffer the
    kernel reports and whether it is below ``size`` (clamped)."""
    got = {}
    for opt in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, opt, size)
        have = sock.getsockopt(socket.SOL_SOCKET, opt)
        force = _FORCE.get(opt)
        if have < size and force is not None:
            with contextlib.suppress(OSError):  # EPERM without CAP_NET_ADMIN
                sock.setsockopt(socket.SOL_SOCKET, force, size)
            have = sock.getsockopt(socket.SOL_SOCKET, opt)
        got[opt] = have
    rcv = got[socket.SO_RCVBUF]
    return rcv, rcv < size


class UdpTransport:
    """The service's UDP endpoint (see the module docstring)."""

    name = "udp"

    def __init__(self, settings: UdpSettings, queue_size: int = 1024) -> None:
        self.settings = settings
        self._queue: FairQueue[Incoming] = FairQueue(queue_size)
        self._sock: _Socket | None = None
        #: the server's admission of a frame for ``stream`` (its raw bytes too): the receive
        #: queue's key, or None to drop it unread as ``unknown_stream`` (see the module
        #: docstring); unset: one key for everything
        self.admission: Admission | None = None
        self._static = [parse_hostport(d) for d in settings.publish_to]
        # subscriber address -> (stream or "*", last renewal, monotonic s)
        self.subscribers: dict[Addr, tuple[str, float]] = {}
        self.retained: dict[tuple[str, str], bytes] = {}
        self._send_failed: dict[str, int] = {}  # stream -> datagrams the kernel refused
        self._secret = os.urandom(16)  # challenge tokens: valid for this process only
        self.challenges_sent = 0

    @property
    def address(self) -> Addr:
        """The bound ``(host, port)`` (port 0 in the settings picks a free one)."""
        if self._sock is None:
            raise RuntimeError("UdpTransport is not open")
        return self._sock.sock.getsockname()[:2]

    def trouble(self) -> str | None:
        """None: a bound socket has no connection to lose (refused sends are ``send_error``)."""
        return None

    def drop_counts(self) -> dict[tuple[str, str], int]:
        """Cumulative drops inside the transport by ``(stream, reason)``: ``rx_overflow`` (the
        receive queue was full, the oldest datagram went) and ``send_error`` (datagrams the
        kernel refused, per destination)."""
        # one series: per-stream keys would outlive the streams (slots come and go)
        out = {("", "rx_overflow"): self._queue.dropped}
        out.update({(s, "send_error"): n for s, n in self._send_failed.items()})
        if self._sock is not None:
            out[("", "unknown_stream")] = self._sock.prefiltered
            if self._sock.kernel_dropped is not None:
                out[("", "kernel_rx_overflow")] = self._sock.kernel_dropped
        return out

    @property
    def receive_buffer_bytes(self) -> int:
        """The kernel receive buffer the socket got (as ``getsockopt`` reports it)."""
        return self._sock.receive_buffer if self._sock is not None else 0

    def _classify(self, data: bytes) -> str | None:
        admission = self.admission
        if admission is None:
            return ""
        name = peek_frame_stream(data)
        if name is None:  # not a frame, or not one the peek reads: decoded in full
            return ""
        return admission(name, data)

    async def __aenter__(self) -> UdpTransport:
        want = self.settings.socket_buffer_bytes
        sock = _Socket(self._queue, self.name, want, self._classify)
        try:
            sock.sock.bind((self.settings.host, self.settings.port))
        except OSError as exc:
            sock.close()
            raise ConfigError(
                f"udp: cannot bind {self.settings.host}:{self.settings.port}: {exc}"
            ) from exc
        if sock.buffer_clamped:
            log.warning(
                "udp: receive buffer of %d bytes requested (udp.socket_buffer_bytes), the OS "
                "gave %d: raise net.core.rmem_max or run with CAP_NET_ADMIN; bursts larger "
                "than the buffer are dropped by the kernel (kernel_rx_overflow)",
                want, sock.receive_buffer,
            )  # fmt: skip
        sock.start()
        self._sock = sock
        log.info("udp: listening on %s:%d", *self.address)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)

    def _token(self, addr: Addr, stream: str, window: int) -> bytes:
        msg = f"{addr[0]}|{addr[1]}|{stream}|{window}".encode()
        return hmac.new(self._secret, msg, hashlib.sha256).digest()[:TOKEN_BYTES]

    def _window(self) -> int:
        return int(time.monotonic() // max(self.settings.subscriber_ttl_s, 1.0))

    def token_for(self, addr: Addr, stream: str) -> bytes:
        """The challenge token ``addr`` must echo now (tests; in-process trusted callers)."""
        return self._token(addr, stream, self._window())

    def subscribe(
        self, addr: Addr, stream: str, token: bytes | None = None, request_bytes: int = 0
    ) -> None:
        """Registers or renews a subscriber (see the module docstring for the confirmation);
        new ones receive the retained payloads at once."""
        known = self.subscribers.get(addr)
        if known is not None and known[0] == stream:
            self.subscribers[addr] = (stream, time.monotonic())  # renewal
            return
        w = self._window()
        if token is None or not any(
            hmac.compare_digest(token, self._token(addr, stream, x)) for x in (w, w - 1)
        ):
            challenge = encode_challenge(stream, self._token(addr, stream, w))
            if request_bytes < len(challenge):
                raise ProtocolError(
                    f"udp: subscribe from {addr[0]}:{addr[1]} of {request_bytes} bytes is "
                    f"smaller than the challenge ({len(challenge)}): not answered",
                    "subscribe_short",
                )
            self._sendto(stream, challenge, addr)  # a fresh one (a stale token: expired)
            self.challenges_sent += 1
            if token is not None:
                raise ProtocolError(
                    f"udp: subscribe from {addr[0]}:{addr[1]} echoed a wrong or stale token; "
                    "challenged again",
                    "subscribe_token",
                )
            return
        self._expire()
        host = addr[0]
        per_host = sum(1 for a in self.subscribers if a[0] == host and a != addr)
        if per_host >= self.settings.max_subscribers_per_host:
            raise ProtocolError(
                f"udp: {per_host} subscribers from {host} already, {addr[1]} refused",
                "subscribe_host_limit",
            )
        is_new = known is None
        if is_new and len(self.subscribers) >= self.settings.max_subscribers:
            raise ProtocolError(f"udp: subscriber limit reached, {addr} refused", "subscribe_full")
        self.subscribers[addr] = (stream, time.monotonic())
        if is_new:
            log.info("udp: subscriber %s:%d for stream %s", addr[0], addr[1], stream)
            for (s, _), payload in list(self.retained.items()):
                if stream in ("*", s):
                    self._sendto(s, payload, addr)

    def _expire(self) -> None:
        cutoff = time.monotonic() - self.settings.subscriber_ttl_s
        for addr, (_, last) in list(self.subscribers.items()):
            if last < cutoff:
                del self.subscribers[addr]
                log.info("udp: subscriber %s:%d expired", addr[0], addr[1])

    def _sendto(self, stream: str, payload: bytes, addr: Addr) -> None:
        assert self._sock is not None
        if not self._sock.sendto(payload, addr):
            self._send_failed[stream] = self._send_failed.get(stream, 0) + 1

    async def send(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> None:
        if self._sock is None:
            raise RuntimeError("UdpTransport is not open")
        if len(payload) > UDP_MAX_PAYLOAD:
            raise ProtocolError(
                f"udp: {kind} message of {len(payload)} bytes exceeds {UDP_MAX_PAYLOAD}",
                "oversize",
            )
        if retain:
            self.retained[(stream, kind)] = payload
        for addr in self._static:
            self._sendto(stream, payload, addr)
        if kind == "model":
            self._expire()  # once a second is often enough
        for addr, (want, _) in self.subscribers.items():
            if want == "*" or want == stream:
                self._sendto(stream, payload, addr)


class UdpClient:
    """A client endpoint: sends to ``remote`` and receives what comes back to its port.

    Used by ``replay`` (send frames) and ``subscribe`` (register, then receive labeled frames).
    """

    name = "udp"

    def __init__(self, host: str, port: int, queue_size: int = 4096, buffer: int = 4 << 20):
        self.remote = (host, port)
        self._queue: DropOldestQueue[Incoming] = DropOldestQueue(queue_size)
        self._buffer = buffer
        self._sock: _Socket | None = None

    @property
    def received_dropped(self) -> int:
        return self._queue.dropped

    @property
    def refused(self) -> int:
        """ICMP "connection refused" reports so far: nothing listens at ``remote`` (each is
        a datagram that went nowhere; a lower bound, the kernel keeps one pending)."""
        return self._sock.refused if self._sock is not None else 0

    def trouble(self) -> None:
        """None: UDP has no connection to lose (nothing listening shows in :attr:`refused`)."""
        return None

    async def __aenter__(self) -> UdpClient:
        sock = _Socket(self._queue, self.name, self._buffer)
        try:
            sock.sock.connect(self.remote)
        except OSError as exc:
            sock.close()
            raise ConfigError(
                f"udp: cannot reach {self.remote[0]}:{self.remote[1]}: {exc}"
            ) from exc
        sock.start()
        self._sock = sock
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def send(self, payload: bytes) -> bool:
        """Sends one datagram; False when the kernel refused it (the caller counts it)."""
        if self._sock is None:
            raise RuntimeError("UdpClient is not open")
        if len(payload) > UDP_MAX_PAYLOAD:
            raise ProtocolError(f"udp: message of {len(payload)} bytes is too large", "oversize")
        return self._sock.sendto(payload, None)

    def messages(self) -> AsyncIterator[Incoming]:
        return iterate_queue(self._queue)
