"""Class 4 and 9 of issue 12 over real loopback UDP: subscribe amplification, subscriber
lock-out, and datagrams the kernel dropped.

Until a subscriber echoes the service's challenge token, nothing larger than its request is
sent to its address (forged source addresses cannot be used for reflection); confirmed
subscribers are capped per source host, each refusal under its own reason; the kernel's
receive-buffer drops are read from SO_RXQ_OVFL where Linux gives them.
"""

from __future__ import annotations

import asyncio
import socket
import sys

import numpy as np
import pytest
from hostile.helpers import moving_clusters, payloads, run
from hostile.helpers import settings as service_settings

from labeler_service.service.protocol import (
    ChallengeMsg,
    _pack,
    decode,
    encode_subscribe,
)
from labeler_service.service.server import Server
from labeler_service.service.transports.base import DropOldestQueue
from labeler_service.service.transports.udp import _Socket
from labeler_service.tools.subscribe import Subscriber


def _settings(**over):
    base = {"labeler": "baseline", "udp": {"port": 0, "max_subscribers_per_host": 4}}
    base.update(over)
    return service_settings(**base)


def _raw_client(host="127.0.0.1"):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((host, 0))
    s.setblocking(False)
    return s


async def _recv_all(s: socket.socket, wait: float = 0.3) -> list[bytes]:
    await asyncio.sleep(wait)
    out = []
    while True:
        try:
            out.append(s.recv(65536))
        except BlockingIOError:
            return out


def _stream_frames(n=80, init=10, stream="vol"):
    cap = moving_clusters(np.random.default_rng(0), subjects=2, markers=6, frames=n)
    return payloads(cap, np.random.default_rng(1), init, stream=stream)


def test_an_unconfirmed_subscriber_gets_nothing_larger_than_its_request():
    frames = _stream_frames()

    async def go():
        async with Server(_settings()) as srv:
            addr = srv.transports[0].address
            bare = _pack({"v": 1, "type": "subscribe", "stream": "*"})  # 28 bytes, no pad
            padded = encode_subscribe("*")
            a, b = _raw_client(), _raw_client()
            a.sendto(bare, addr)
            b.sendto(padded, addr)
            feeder = _raw_client()
            for p in frames:  # labeled frames flow meanwhile
                feeder.sendto(p, addr)
                await asyncio.sleep(0.001)
            got_a, got_b = await _recv_all(a), await _recv_all(b)
            for s in (a, b, feeder):
                s.close()
            return srv.metrics, bare, padded, got_a, got_b

    metrics, bare, padded, got_a, got_b = run(go())
    assert len(bare) <= 28 and got_a == []  # too small to be answered: no reflection
    assert metrics.drops("subscribe_short") == 1
    assert len(got_b) == 1  # only the challenge, never a frame
    assert len(got_b[0]) <= len(padded)
    assert isinstance(decode(got_b[0]), ChallengeMsg)


def test_a_wrong_token_is_challenged_again_and_our_subscriber_confirms_and_receives():
    frames = _stream_frames(n=120)

    async def go():
        async with Server(_settings()) as srv:
            addr = srv.transports[0].address
            liar = _raw_client()
            liar.sendto(encode_subscribe("*", b"12345678"), addr)
            async with Subscriber(f"udp://{addr[0]}:{addr[1]}") as sub:
                await asyncio.sleep(0.2)  # subscribe -> challenge -> echo
                feeder = _raw_client()
                for p in frames:
                    feeder.sendto(p, addr)
                    await asyncio.sleep(0.001)
                await asyncio.sleep(0.3)
                got = sub.drain()
            got_liar = await _recv_all(liar, 0.05)
            liar.close()
            feeder.close()
            return srv.metrics, got, got_liar

    metrics, got, got_liar = run(go())
    assert metrics.drops("subscribe_token") == 1
    # a wrong token gets a fresh challenge (no larger than the request), never a frame
    assert len(got_liar) == 1 and isinstance(decode(got_liar[0]), ChallengeMsg)
    assert len(got) == 110  # every labeled frame after the init window


def test_one_host_cannot_lock_out_another_subscriber():
    async def go():
        async with Server(_settings(udp={"port": 0, "max_subscribers": 8,
                                         "max_subscribers_per_host": 4})) as srv:  # fmt: skip
            t = srv.transports[0]
            addr = t.address
            socks = [_raw_client() for _ in range(16)]
            for s in socks:  # subscribe, read the challenge, echo it: real, confirmed
                s.sendto(encode_subscribe("*"), addr)
            await asyncio.sleep(0.2)
            for s in socks:
                for p in await _recv_all(s, 0):
                    m = decode(p)
                    if isinstance(m, ChallengeMsg):
                        s.sendto(encode_subscribe("*", m.token), addr)
            await asyncio.sleep(0.2)
            from_one = len(t.subscribers)
            other = _raw_client("127.0.0.2")
            other.sendto(encode_subscribe("*"), addr)
            await asyncio.sleep(0.1)
            (challenge,) = await _recv_all(other, 0)
            other.sendto(encode_subscribe("*", decode(challenge).token), addr)
            await asyncio.sleep(0.1)
            hosts = {a[0] for a in t.subscribers}
            for s in [*socks, other]:
                s.close()
            return srv.metrics, from_one, hosts

    metrics, from_one, hosts = run(go())
    assert from_one == 4
    assert metrics.drops("subscribe_host_limit") == 12
    assert hosts == {"127.0.0.1", "127.0.0.2"}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SO_RXQ_OVFL is Linux only")
def test_kernel_receive_buffer_drops_are_counted():
    async def go():
        q = DropOldestQueue(100_000)
        sock = _Socket(q, "udp", 65536)
        sock.sock.bind(("127.0.0.1", 0))
        assert sock.kernel_dropped == 0
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        dest = sock.sock.getsockname()
        sent = 0
        for _ in range(3000):  # nobody reads: the receive buffer overflows
            try:
                sender.sendto(b"x" * 1000, dest)
                sent += 1
            except OSError:
                pass
        sender.sendto(b"last", dest)  # a datagram after the drops carries the counter
        await asyncio.sleep(0.05)
        sock._readable()
        got = len(q)
        dropped = sock.kernel_dropped
        sender.close()
        sock.close()
        return sent + 1, got, dropped

    sent, got, dropped = run(go())
    assert dropped > 0
    assert got + dropped == sent


def test_a_subscriber_that_expired_during_a_stall_confirms_again():
    frames = _stream_frames(n=60)

    async def go():
        cfg = _settings(udp={"port": 0, "subscriber_ttl_s": 1.0})
        async with Server(cfg) as srv:
            t = srv.transports[0]
            addr = t.address
            async with Subscriber(f"udp://{addr[0]}:{addr[1]}") as sub:
                sub.renew_s = 0.2
                await asyncio.sleep(0.3)
                assert len(t.subscribers) == 1
                t.subscribers.clear()  # as if expired during a stall; its token is stale now
                t._secret = b"another secret!!"
                await asyncio.sleep(0.6)
                feeder = _raw_client()
                for p in frames:
                    feeder.sendto(p, addr)
                    await asyncio.sleep(0.001)
                await asyncio.sleep(0.3)
                got = sub.drain()
                feeder.close()
            return got, srv.metrics.drops("subscribe_token")

    got, stale = run(go())
    assert stale >= 1
    assert len(got) == 50


def test_a_full_subscriber_table_refuses_a_newcomer_under_its_own_reason():
    """With ``max_subscribers = 2``, a third confirmed subscriber (another host) is refused and
    counted as ``subscribe_full``; the two already confirmed keep their places."""

    async def confirm(s: socket.socket, addr) -> None:
        s.sendto(encode_subscribe("*"), addr)
        for p in await _recv_all(s, 0.2):
            m = decode(p)
            if isinstance(m, ChallengeMsg):
                s.sendto(encode_subscribe("*", m.token), addr)
        await asyncio.sleep(0.2)

    async def go():
        udp = {"port": 0, "max_subscribers": 2, "max_subscribers_per_host": 4}
        async with Server(_settings(udp=udp)) as srv:
            t = srv.transports[0]
            socks = [_raw_client(h) for h in ("127.0.0.1", "127.0.0.2", "127.0.0.3")]
            try:
                for s in socks:
                    await confirm(s, t.address)
                return srv.metrics.drops("subscribe_full"), {a[0] for a in t.subscribers}
            finally:
                for s in socks:
                    s.close()

    full, hosts = run(go())
    assert full >= 1
    assert hosts == {"127.0.0.1", "127.0.0.2"}
