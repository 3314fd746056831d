"""Every drop reason is counted where operators read it: the server's ``mocap_dropped_total``.

The protocol's reject reasons go through a running server one message each; the service's own
reasons that no other test triggers (``init_overflow``, ``output_oversize``, ``internal``) get
a test here; and a census checks that every reason the code declares is read back by some
service test, so a new reason cannot ship uncounted.
"""

from __future__ import annotations

import re
from pathlib import Path

import msgpack
import numpy as np
from service.helpers import SlowLabeler, moving_clusters, run, stream_payloads, until

from labeler_service.service.metrics import SERVICE_DROP_REASONS
from labeler_service.service.protocol import REJECT_REASONS, decode, encode_subscribe
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.service.transports.memory import MemoryTransport
from labeler_service.tools.replay import open_sender


def _settings(**over):
    base = {"labeler": "baseline", "metrics_port": None, "warmup": False, "queue_size": 256}
    base.update(over)
    return load_settings(**base)


def _frame(**over):
    m = {"v": 1, "type": "frame", "stream": "default", "seq": 1, "t": 0.0,
         "points": np.zeros((2, 3), np.float32).tobytes()}  # fmt: skip
    m.update(over)
    return msgpack.packb(m, use_bin_type=True)


BAD = {
    "oversize": b"\x00" * 70_000,
    "not_msgpack": b"\xc1",
    "not_map": msgpack.packb([1, 2, 3]),
    "version": _frame(v=2),
    "type": _frame(type="bogus"),
    "stream": _frame(stream="a/b"),
    "seq": _frame(seq=-1),
    "time": _frame(t=float("nan")),
    "points": _frame(points=b"\x00" * 13),
    "non_finite": _frame(points=np.array([[0, np.nan, 0]], np.float32).tobytes()),
    "out_of_range": _frame(points=np.array([[0, 3.4e38, 0]], np.float32).tobytes()),
    "too_many_points": _frame(points=np.zeros((25, 3), np.float32).tobytes()),
    "labels": _frame(labels=["a:x"]),
    "field": _frame(sent=-5),
}


def test_every_protocol_reject_reason_is_counted_by_the_server(rng):
    assert set(BAD) == set(REJECT_REASONS)
    cap = moving_clusters(rng, frames=30)
    good = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(max_points=20), [mem]) as srv:
            for p in good[:15]:
                mem.inject(p)
            for p in BAD.values():
                mem.inject(p)
            for p in good[15:]:
                mem.inject(p)
            got = [decode(await mem.next_sent("labeled", 30.0)) for _ in range(20)]
            return srv.metrics, got

    metrics, got = run(go())
    for reason in BAD:
        assert metrics.drops(reason) == 1, reason
    assert metrics.drops() == len(BAD)
    assert [m.seq for m in got] == list(range(10, 30))  # the stream went on


def test_init_frames_beyond_the_buffer_are_counted_as_init_overflow(rng):
    cap = moving_clusters(rng, frames=20)
    p = stream_payloads(cap, rng, init=12)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(max_init_frames=8), [mem]) as srv:
            for x in p:
                mem.inject(x)
            got = [decode(await mem.next_sent("labeled", 30.0)) for _ in range(8)]
            return srv.metrics, got

    metrics, got = run(go())
    assert metrics.drops("init_overflow", stream="default") == 12 - 8
    assert metrics.drops() == 12 - 8
    assert [m.seq for m in got] == list(range(12, 20))  # started from the 8 it kept


def test_a_labeled_frame_too_large_for_a_datagram_is_counted_as_output_oversize(rng):
    """6000 markers make a labeled frame of ~78 kB: UDP refuses it, the server counts it."""
    names = tuple(f"S:m{i}" for i in range(6000))

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return SlowLabeler(names, rate)

    cap = moving_clusters(rng, frames=20)
    p = stream_payloads(cap, rng, init=5)

    async def go():
        async with Server(_settings(udp={"port": 0}), factory=factory) as srv:
            udp = srv.transports[0]
            host, port = udp.address
            async with open_sender(f"udp://{host}:{port}") as (send, _):
                for x in p:
                    await send(x)
                await until(lambda: srv.metrics.drops("output_oversize") >= 15,
                            "15 oversize outputs")  # fmt: skip
            return srv.metrics

    metrics = run(go())
    assert metrics.drops("output_oversize", stream="default") == 15
    assert metrics.value("mocap_frames_out_total", stream="default") == 0


class _BrokenSubscribe(MemoryTransport):
    """A transport whose subscriber registry fails unexpectedly (not a ProtocolError)."""

    def subscribe(self, addr, stream):
        raise RuntimeError("registry is broken")


def test_an_unexpected_error_while_handling_a_message_is_counted_as_internal(rng):
    cap = moving_clusters(rng, frames=30)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = _BrokenSubscribe()
        async with Server(_settings(), [mem]) as srv:
            for x in p[:15]:
                mem.inject(x)
            mem.inject(encode_subscribe("*"), reply_to=("127.0.0.1", 9))
            for x in p[15:]:
                mem.inject(x)
            got = [decode(await mem.next_sent("labeled", 30.0)) for _ in range(20)]
            return srv.metrics, got

    metrics, got = run(go())
    assert metrics.drops("internal") == 1 and metrics.drops() == 1
    assert got[-1].seq == 29  # the ingest loop survived


def test_every_declared_drop_reason_is_read_back_by_a_service_test():
    """A census: each reason in REJECT_REASONS and SERVICE_DROP_REASONS appears as
    ``drops("<reason>"`` in some test under tests/service or tests/hostile (a new reason
    needs a test)."""
    tests = Path(__file__).parents[1]
    files = [*(tests / "service").glob("test_*.py"), *(tests / "hostile").glob("test_*.py")]
    text = "\n".join(p.read_text(encoding="utf-8") for p in files)
    read = set(re.findall(r"drops\(\s*\"([a-z_]+)\"", text)) | set(BAD)
    # reasons a parametrized hostile test reads through ``drops(reason)``
    read |= set(re.findall(r"\(\"[^\"]*\", [^()]*, \"([a-z_]+)\"\)", text))
    # the kernel's receive-buffer drops: read at the socket (SO_RXQ_OVFL) by
    # tests/hostile/test_udp_hostile.py; overflowing a kernel buffer through a whole server is
    # too timing-dependent for a unit test
    read.add("kernel_rx_overflow")
    missing = (set(REJECT_REASONS) | set(SERVICE_DROP_REASONS)) - read
    assert not missing, f"drop reasons no service test reads: {sorted(missing)}"


def test_a_stream_falling_behind_says_so_before_it_drops(rng, caplog):
    """A stream whose frames wait in its queue (here a labeler of 30 ms a frame, fed 40 frames
    at once; in a hostile run a neighbour stream of 2,000 points a frame) published frames
    0.7 s late with no drop and no word but ``degraded``. Past ``behind_warn_s`` the log says
    it is falling behind, with the labeling time, points and queue."""
    import logging

    cap = moving_clusters(rng, frames=45)
    names = cap.labels

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return SlowLabeler(names, rate, delay_s=0.03)

    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")

    async def go(warn_s):
        mem = MemoryTransport()
        settings = _settings(behind_warn_s=warn_s)
        async with Server(settings, [mem], factory=factory) as srv:
            for x in stream_payloads(cap, rng, init=5):
                mem.inject(x)
            out = lambda: srv.metrics.value("mocap_frames_out_total", stream="default")  # noqa: E731
            await until(lambda: out() + srv.metrics.drops() >= 40, "40 labeled or dropped")
            return out()

    assert run(go(0.25)) >= 35  # the last frames wait ~1.2 s
    said = [r.getMessage() for r in caplog.records if "falling behind: a frame" in r.getMessage()]
    assert said, caplog.text
    assert re.search(r"published \d+ ms after it arrived \(labeling \d+\.\d ms for its \d+ "
                     r"points; \d+ frames queued; 1 streams share", said[0]), said[0]  # fmt: skip
    caplog.clear()
    assert run(go(5.0)) >= 35  # nothing waits that long: no word
    assert "falling behind" not in caplog.text
