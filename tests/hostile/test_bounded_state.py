"""Class 2 of issue 12: state that grows without bound.

Unknown stream names do not become metric series, junk cannot hold stream slots, idle
unconfigured streams expire (their labeler cached, so they resume without labels), init frames
are capped in markers and bytes, training runs off the loop with a budget and does not hold up
shutdown. Asserted on structures (series, slots, buffers), not on RSS.
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
from hostile.helpers import collect, moving_clusters, payloads, run, settings
from service.helpers import SlowLabeler

from labeler_service.service.protocol import decode, encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport


def _scene(frames=120, seed=7):
    return moving_clusters(np.random.default_rng(seed), subjects=2, markers=6, frames=frames)


def _pts(n=12, seed=0):
    return np.random.default_rng(seed).normal(scale=300.0, size=(n, 3)).astype(np.float32)


async def _drain(srv, timeout=20.0):
    async with asyncio.timeout(timeout):
        while any(len(q) for q in srv._queues.values()) or srv.background.running:
            await asyncio.sleep(0.02)
    await asyncio.sleep(0.05)


def test_unknown_stream_names_do_not_become_metric_series():
    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", streams=[{"name": "main"}])
        async with Server(cfg, [mem]) as srv:
            before = srv.metrics.series()
            for k in range(2000):  # unlabeled frames: they can never start a stream
                mem.inject(encode_frame(f"junk{k}", 0, 0.0, _pts()))
            await _drain(srv)
            assert srv.metrics.drops("unknown_stream") == 2000
            assert set(srv.streams) == {"main"}
            assert srv.metrics.series() - before <= 2  # one aggregate series, not 2,000
            text = srv.metrics.registry.get_sample_value(
                "mocap_dropped_total", {"stream": "", "reason": "unknown_stream"}
            )
            assert text == 2000

    run(go())


def test_junk_names_cannot_hold_every_slot_from_a_real_stream():
    cap = _scene()
    real = payloads(cap, np.random.default_rng(0), 20, stream="real")

    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", max_streams=4, streams=[])
        async with Server(cfg, [mem]) as srv:
            for k in range(15):  # one labeled junk datagram per name: never starts a stream
                mem.inject(encode_frame(f"junk{k}", 0, 0.0, _pts(), ["j:a"] * 12))
            await _drain(srv)
            assert len(srv.streams) <= 4
            for p in real:
                mem.inject(p)
                await asyncio.sleep(0.0005)
            msgs = await collect(srv, mem, "real")
            assert len(msgs) == cap.n_frames - 20
            assert len(srv.streams) <= 4
            assert srv.metrics.drops("unknown_stream", "real") == 0

    run(go())


def test_idle_unconfigured_streams_expire_and_resume_from_the_cached_labeler():
    cap = _scene(frames=200)
    first = payloads(cap, np.random.default_rng(0), 20, stream="dyn", frames=range(0, 100))
    # comes back later without any labels (seq/t continue)
    back = payloads(cap, np.random.default_rng(1), 0, stream="dyn", seq0=100,
                    t0=100 / cap.rate, frames=range(100, 200))  # fmt: skip

    async def go():
        mem = MemoryTransport()
        cfg = settings(stream_idle_s=1.0, streams=[{"name": "kept"}], stream_cache_size=2)
        async with Server(cfg, [mem]) as srv:
            for p in first:
                mem.inject(p)
                await asyncio.sleep(0.0005)
            async with asyncio.timeout(20):  # trained (the worker drains its queue)
                while not (srv.streams["dyn"].started and not len(srv._queues["dyn"])):
                    await asyncio.sleep(0.01)
            series_with = srv.metrics.series()
            async with asyncio.timeout(10):  # idle > stream_idle_s: the expire task removes it
                while "dyn" in srv.streams:
                    await asyncio.sleep(0.05)
            assert "kept" in srv.streams  # configured streams never expire
            assert "dyn" in srv.cache
            assert srv.metrics.series() < series_with
            n_before = len([1 for s, k, _, _ in mem.sent if k == "labeled"])
            for p in back:
                mem.inject(p)
                await asyncio.sleep(0.0005)
            msgs = await collect(srv, mem, "dyn")
            resumed = msgs[n_before:]
            assert len(resumed) == 100
            observed = np.mean([np.mean(m.state == 1) for m in resumed])
            assert observed > 0.9  # labels resumed without any init frame
            assert srv.metrics.drops("no_model") == 0

    run(go())


def test_init_frames_are_capped_in_markers_and_bytes():
    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", max_markers=50, max_init_bytes=20_000)
        async with Server(cfg, [mem]) as srv:
            # 5 frames x 40 distinct labels: from the 2nd frame on the stream would exceed 50
            for k in range(5):
                labels = [f"s{k}:m{i}" for i in range(40)]
                mem.inject(encode_frame("default", k, k / 100, _pts(40, k), labels))
            await _drain(srv)
            st = srv.streams["default"]
            assert srv.metrics.drops("marker_cap") == 4
            assert len(st._init_labels) <= 50
            # bytes: frames of 200 points (2.4 kB of points each) until 20 kB are buffered
            for k in range(5, 40):
                labels = ["s0:m0"] * 200
                mem.inject(encode_frame("default", k, k / 100, _pts(200, k), labels))
            await _drain(srv)
            assert srv.metrics.drops("init_overflow") > 0
            assert st._init_bytes <= 20_000

    run(go())


class _StuckTraining(SlowLabeler):
    """Training (the first unlabeled frame) takes far longer than the budget."""

    started = threading.Event()

    def process(self, points, t, labels=None):
        if labels is None and not getattr(self, "_trained", False):
            self.started.set()
            time.sleep(3.0)
            self._trained = True
        return super().process(points, t, labels)


def test_markers_per_subject_are_capped():
    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", max_markers=100, max_markers_per_subject=30)
        async with Server(cfg, [mem]) as srv:
            # one subject of 40 markers: over the per-subject cap (the stream cap allows it)
            mem.inject(encode_frame("default", 0, 0.0, _pts(40, 0), [f"a:m{i}" for i in range(40)]))
            # 2 subjects of 20, then 15 more of the first: 35 > 30
            mem.inject(encode_frame("default", 1, 0.01, _pts(40, 1),
                                    [f"s{i % 2}:m{i}" for i in range(40)]))  # fmt: skip
            mem.inject(encode_frame("default", 2, 0.02, _pts(15, 2),
                                    [f"s0:x{i}" for i in range(15)]))  # fmt: skip
            await _drain(srv)
            st = srv.streams["default"]
            assert srv.metrics.drops("marker_cap") == 2
            assert len(st._init_labels) == 40 and st._init_subjects == {"s0": 20, "s1": 20}

    run(go())


def test_training_over_budget_is_abandoned_reported_and_does_not_hold_shutdown():
    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return _StuckTraining(marker_names, rate)

    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", train_budget_s=0.3)
        srv = Server(cfg, [mem], factory=factory)
        async with srv:
            for k in range(5):
                mem.inject(encode_frame("default", k, k / 100, _pts(), ["a:m"] * 12))
            mem.inject(encode_frame("default", 5, 0.05, _pts()))
            async with asyncio.timeout(10):
                while srv.metrics.drops("training_failed") == 0:
                    await asyncio.sleep(0.05)
            states = [decode(p).state for s, k, p, _ in mem.sent if k == "status"]
            assert states[-1] == "training_failed"
            assert srv.streams["default"].labeler is None
        # shutdown did not wait for the abandoned job: its daemon thread is still sleeping
        stuck = [t for t in threading.enumerate() if t.name == "train-default"]
        return stuck

    stuck = run(go(), timeout=30)
    assert stuck and all(t.daemon and t.is_alive() for t in stuck)


def test_streams_that_come_and_go_leave_no_tasks_or_series_behind():
    async def go():
        mem = MemoryTransport()
        cfg = settings(labeler="baseline", max_streams=3, streams=[{"name": "main"}])
        async with Server(cfg, [mem]) as srv:
            for k in range(600):  # each labeled junk name takes a slot, evicting the oldest
                mem.inject(encode_frame(f"j{k}", 0, 0.0, _pts(), ["j:a"] * 12))
                if k % 50 == 0:
                    await asyncio.sleep(0)
            await _drain(srv)
            assert len(srv.streams) <= 1 + 3
            assert len(srv._tasks) < 300
            assert len(srv._queues) == len(srv.streams) == len(srv._workers)
            names = {k[1][0] for k in srv.metrics._children if k[1]}
            assert names <= set(srv.streams) | {""}

    run(go())


def test_a_removed_stream_releases_its_init_buffer_at_once():
    """Frames buffered by a stream that never trains are dropped when it expires, whoever
    still refers to its state; no finished task is kept (its traceback would hold it)."""

    async def go():
        mem = MemoryTransport()
        async with Server(settings(stream_idle_s=0.4), [mem]) as srv:
            for k in range(30):
                labels = [f"b:m{i}" for i in range(20)]
                mem.inject(encode_frame("buf", k, k / 100, _pts(20, k), labels))
            await _drain(srv)
            state = srv.streams["buf"]
            assert len(state.init_frames) == 30
            async with asyncio.timeout(10):
                while "buf" in srv.streams:
                    await asyncio.sleep(0.05)
            # released by the removal itself, before the cancelled worker has even ended
            assert state.init_frames == [] and state._init_bytes == 0
            assert state.labeler is None
            for _ in range(5):  # the ended tasks' done callbacks run
                await asyncio.sleep(0)
            assert all(not t.done() for t in srv._tasks)

    run(go())
