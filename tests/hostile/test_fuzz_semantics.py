"""Hypothesis fuzz of stream semantics (issue 12, item 8): ``seq``, ``t`` and labels, not only
the decoder (tests/service/test_protocol.py fuzzes decoding).

1. The restart rule (:class:`~labeler_service.service.continuity.Continuity`): isolated spoofed
   frames with any ``seq`` and any finite ``t`` never cost a genuine frame and never start a
   run; a restarted sender is adopted after ``confirm`` frames; gaps stay clipped.
2. The server under random frames (streams, seq, t, labels, points): every frame is either
   accepted or counted under a reason, no worker dies, the metric series stay bounded.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from hostile.helpers import run
from hostile.helpers import settings as service_settings
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from labeler_service.service.continuity import Continuity
from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport

U64 = 2**64 - 1
finite_t = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(st.tuples(st.integers(1, 3), st.booleans()), min_size=5, max_size=60),
    spoofs=st.lists(st.tuples(st.integers(0, U64), finite_t), min_size=60, max_size=60),
    seq0=st.integers(0, 2**40),
    t0=st.floats(0, 1e6),
)
def test_isolated_spoofed_frames_never_cost_a_genuine_frame(steps, spoofs, seq0, t0):
    c = Continuity(max_seq_step=100, max_time_step_s=1.0, confirm=3)
    seq, t = seq0, t0
    assert c.check(seq, t).reason is None
    for k, (ds, spoof_here) in enumerate(steps):
        if spoof_here:  # one spoofed frame between two genuine ones
            s_seq, s_t = spoofs[k]
            v = c.check(s_seq, s_t)
            assert not v.new_run
            if v.reason is None:  # plausible by chance: it continues the run, gap clipped
                assert 0 <= v.gap < 100
                seq, t = s_seq, s_t
        seq, t = seq + ds, t + ds / 120
        v = c.check(seq, t)
        if v.reason is not None:
            # only a spoof that landed just ahead of the genuine run can make it "late"
            assert v.reason in ("late", "duplicate")
            seq, t = c.last_seq, c.last_t
        else:
            assert not v.new_run
            assert 0 <= v.gap < 100


@settings(max_examples=200, deadline=None)
@given(
    history=st.lists(st.tuples(st.integers(0, U64), finite_t), max_size=20),
    restart_seq=st.integers(0, 2**62),
    restart_t=finite_t,
    confirm=st.integers(1, 5),
)
def test_a_restarted_sender_is_adopted_after_confirm_frames(history, restart_seq, restart_t,
                                                            confirm):  # fmt: skip
    c = Continuity(max_seq_step=100, max_time_step_s=1.0, confirm=confirm)
    for s, t in history:
        v = c.check(s, t)
        assert v.gap < 100
    last = c.last_seq
    if last is not None and abs(restart_seq - last) <= 100 + confirm:
        restart_seq = last + 1000  # a restart, not late frames of the current run
    verdicts = [c.check(restart_seq + k, restart_t + k / 100) for k in range(confirm + 3)]
    accepted = [v.reason is None for v in verdicts]
    # accepted from the confirm-th frame on (or at once when it continues the current run)
    assert all(accepted[confirm - 1 :])
    assert sum(v.new_run for v in verdicts) <= 1
    assert c.last_seq == restart_seq + confirm + 2


NAMES = [f"S{s}:m{i}" for s in range(2) for i in range(4)]

frame_st = st.builds(
    lambda stream, seq, t, n, labeled, seed: (stream, seq, t, n, labeled, seed),
    stream=st.sampled_from(["a", "b", "c", "x1", "x2", "x3"]),
    seq=st.one_of(st.integers(0, 40), st.integers(0, U64)),
    t=st.one_of(st.floats(0, 1), finite_t),
    n=st.integers(0, 12),
    labeled=st.sampled_from(["none", "good", "junk"]),
    seed=st.integers(0, 2**16),
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow],
    phases=[Phase.explicit, Phase.reuse, Phase.generate],
)  # fmt: skip
@given(st.lists(frame_st, min_size=1, max_size=80))
def test_random_frames_are_counted_and_never_kill_a_worker(frames):
    payloads = []
    for stream, seq, t, n, labeled, seed in frames:
        r = np.random.default_rng(seed)
        pts = r.normal(scale=300.0, size=(n, 3)).astype(np.float32)
        if labeled == "good":
            labels = [NAMES[i % len(NAMES)] for i in range(n)]
        elif labeled == "junk":
            labels = [f"j{seed}:{i}" if i % 3 else None for i in range(n)]
        else:
            labels = None
        payloads.append(encode_frame(stream, seq, t, pts, labels))

    async def go():
        mem = MemoryTransport()
        cfg = service_settings(labeler="baseline", max_streams=2, max_markers=6,
                               streams=[{"name": "a"}])  # fmt: skip
        async with Server(cfg, [mem]) as srv:
            for p in payloads:
                mem.inject(p)
            for _ in range(50):
                await asyncio.sleep(0.01)
                if not any(len(q) for q in srv._queues.values()):
                    break
            await asyncio.sleep(0.05)
            workers = list(srv._workers.values())
            assert all(not w.done() for w in workers)
            assert len(srv.streams) <= 1 + 2  # configured + max_streams
            m = srv.metrics
            assert m.drops("internal") == 0
            # stream names are not metric labels beyond the slots: series stay bounded
            names = {k[1][0] for k in m._children if k[1]}
            assert names <= set(srv.streams) | {""}

    run(go())


@pytest.mark.parametrize("run", [5, 99, 100])
def test_a_sender_restarted_after_a_short_run_is_a_new_run_not_late_frames(run):
    """A run of ``run`` frames, then the sender starts again from ``seq`` 0 and ``t`` 0: its
    frames repeat ``seq`` the run accepted, so they are a restart, not late frames (a hostile
    run restarting every 100 frames had every later frame dropped as ``late``, silently)."""
    c = Continuity(max_seq_step=100, max_time_step_s=1.0, confirm=3)
    for k in range(run):
        assert c.check(k, k / 120).reason is None
    verdicts = [c.check(k, k / 120) for k in range(run)]
    assert [v.reason for v in verdicts[:2]] == ["duplicate", "duplicate"]
    assert verdicts[2].new_run and all(v.reason is None for v in verdicts[2:])
    # restarting again and again costs the same two frames each time (the frames dropped
    # while a new run was confirmed are its own: counted as never seen, each restart lost two
    # more than the last, 1,190 of 3,600 frames in 30 s)
    for _ in range(30):
        reasons = [c.check(k, k / 120).reason for k in range(run)]
        assert reasons[:2] == ["duplicate", "duplicate"] and set(reasons[2:]) == {None}
    # a frame missing from the run, arriving late, is still late (it fills a hole)
    c = Continuity(max_seq_step=100, max_time_step_s=1.0, confirm=3)
    for k in (0, 1, 3, 4):
        c.check(k, k / 120)
    assert c.check(2, 2 / 120).reason == "late"
