"""Server logic over the in-memory transport: start-up modes, drops by reason, backpressure,
status, shutdown, and a fuzz of the ingest loop."""

from __future__ import annotations

import asyncio

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service.helpers import SlowLabeler, frames_of, moving_clusters, run, stream_payloads, until

from labeler_service.labeling.registry import make_labeler
from labeler_service.labeling.templates import LabelerModel, load_model, save_model
from labeler_service.labeling.training import train_subject
from labeler_service.service.protocol import LabeledMsg, ModelMsg, StatusMsg, decode, encode_frame
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.service.transports.memory import MemoryTransport


def _settings(**over):
    base = {"labeler": "baseline", "metrics_port": None, "warmup": True, "queue_size": 256}
    base.update(over)
    return load_settings(**base)


async def _feed(mem, payloads, pause=0.0):
    for p in payloads:
        mem.inject(p)
        await asyncio.sleep(pause)


async def _labeled(mem, n, timeout=30.0):
    out = []
    while len(out) < n:
        msg = decode(await mem.next_sent("labeled", timeout))
        out.append(msg)
    return out


@pytest.mark.parametrize("thread", [False, True], ids=["inline", "labeling-thread"])
def test_stream_starts_from_labeled_init_frames_and_labels_correctly(rng, thread):
    cap = moving_clusters(rng, subjects=3, markers=5, frames=120)
    frames = frames_of(cap, np.random.default_rng(3))
    payloads = [
        encode_frame("default", f, f / cap.rate, p, [cap.labels[i] for i in t] if f < 30 else None)
        for f, (p, t) in enumerate(frames)
    ]

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(labeling_thread=thread), [mem]) as srv:
            await _feed(mem, payloads, pause=0.001)
            got = await _labeled(mem, 90)
            models = [decode(p) for s, k, p, _ in mem.sent if k == "model"]
            first_model = next(i for i, x in enumerate(mem.sent) if x[1] == "model")
            first_labeled = next(i for i, x in enumerate(mem.sent) if x[1] == "labeled")
            return srv.metrics.snapshot(), got, models, first_model < first_labeled

    snap, got, models, model_first = run(go())
    assert model_first, "the model message must precede the first labeled frame"
    model = models[0]
    assert isinstance(model, ModelMsg) and len(model.names) == 15
    assert [s[0] for s in model.subjects] == ["S0", "S1", "S2"]
    assert [m.seq for m in got] == list(range(30, 120))
    correct = 0
    for m in got:
        pts, truth = frames[m.seq]
        for j, name in enumerate(model.names):
            if m.state[j] == 1:
                i = np.flatnonzero((pts == m.positions[j]).all(axis=1))
                correct += int(cap.labels[truth[i[0]]] == name)
    assert correct == 90 * 15  # clean, well-separated clusters: the baseline is perfect
    assert snap["streams"]["default"]["frames_out"] == 90
    assert snap["drops"] == {}


def test_stream_starts_from_a_model_file(tmp_path, rng):
    cap = moving_clusters(rng, subjects=2, markers=5, frames=60)
    subjects = []
    for s in cap.subjects:
        cols = cap.subject_columns(s)
        markers = [cap.labels[c].split(":")[1] for c in cols]
        subjects.append(train_subject(s, markers, cap.positions[:, cols], cap.rate))
    path = tmp_path / "model.json"
    save_model(LabelerModel(rate=cap.rate, subjects=subjects), path)
    calls = []

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        calls.append((marker_names, rate, model))
        return make_labeler("baseline", marker_names=marker_names, rate=rate, model=model)

    async def go():
        mem = MemoryTransport()
        s = _settings(streams=[{"name": "vol", "model": str(path)}])
        async with Server(s, [mem], factory=factory) as srv:
            model = decode(mem.retained[("vol", "model")])
            mem.inject(encode_frame("vol", 0, 0.0, cap.positions[0][::-1].copy()))
            got = await _labeled(mem, 1)
            return srv, model, got

    srv, model, got = run(go())
    # calls[0]: the synthetic warm-up labeler; the file is read once, the model passed on
    assert calls[-1][:2] == ((), cap.rate) and calls[-1][2] == load_model(path)
    assert model.names == cap.labels and model.rate == cap.rate
    assert got[0].seq == 0 and got[0].positions.shape == (10, 3)


def test_malformed_messages_are_counted_by_reason_and_the_stream_survives(rng):
    cap = moving_clusters(rng, frames=80)
    good = stream_payloads(cap, rng, init=20)
    bad = {
        "not_msgpack": b"\xc1\xc1",
        "version": msgpack.packb({"v": 9, "stream": "default", "seq": 1, "t": 0, "points": b""}),
        "non_finite": encode_frame("default", 10_000, 0.0, np.array([[np.nan, 0, 0]], np.float32)),
        "too_many_points": encode_frame("default", 10_001, 0.0, np.zeros((50, 3), np.float32)),
        "points": msgpack.packb({"v": 1, "seq": 1, "t": 0, "points": b"\x00" * 5}),
        "oversize": b"\x00" * 70_000,
    }

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(max_points=40), [mem]) as srv:
            await _feed(mem, good[:40], pause=0.001)
            for p in bad.values():
                mem.inject(p)
            await _feed(mem, good[40:], pause=0.001)
            got = await _labeled(mem, 60)
            return srv.metrics, got

    metrics, got = run(go())
    for reason in bad:
        assert metrics.drops(reason) == 1, reason
    assert [m.seq for m in got] == list(range(20, 80))
    assert all((m.state == 1).all() for m in got)  # labeling continued unharmed


def test_frames_received_while_the_service_starts_are_dropped_not_labeled_late(rng):
    """Unlabeled frames that arrived during the start (the warm-up takes seconds) are stale
    once the service reads them: dropped as ``starting``, not labeled seconds late (a hostile
    run: the start's frames came out with a latency p99 of 3.3 s while the log said they were
    dropped). Labeled ones are the stream's training window: kept, they train it, and the
    sender's frames after ``ready`` are labeled as usual."""
    cap = moving_clusters(rng, frames=60)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        for x in p[:20]:
            mem.inject(x)  # (queued before the server starts reading: 10 labeled, 10 not)
        async with Server(_settings(), [mem]) as srv:
            await _feed(mem, p[20:], pause=0.001)
            await until(lambda: srv.metrics.value("mocap_frames_out_total", stream="default")
                        == 40, "the frames after ready")  # fmt: skip
            return srv.metrics

    metrics = run(go())
    assert metrics.drops("starting") == 10
    assert metrics.value("mocap_frames_in_total", stream="default") == 50


def test_duplicate_and_late_seq_are_dropped_and_gaps_counted(rng):
    cap = moving_clusters(rng, frames=60)
    p = stream_payloads(cap, rng, init=10)
    # 19 again, 15 again (accepted already: duplicates), 21 late (a hole), gaps 20 and 24
    order = p[:20] + [p[19], p[15]] + p[22:24] + [p[21]] + p[25:]

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            await _feed(mem, order, pause=0.001)
            got = await _labeled(mem, 10 + 2 + 35)
            return srv.metrics, got

    metrics, got = run(go())
    assert metrics.drops("duplicate") == 2 and metrics.drops("late") == 1
    assert metrics.value("mocap_seq_gap_frames_total", stream="default") == 3
    assert [m.seq for m in got] == list(range(10, 20)) + [22, 23] + list(range(25, 60))


def test_a_restarted_sender_is_accepted_after_a_large_seq_jump_back(rng):
    cap = moving_clusters(rng, frames=40)
    first = stream_payloads(cap, rng, init=10, seq0=5000)
    again = stream_payloads(cap, rng, init=10, seq0=0)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            await _feed(mem, first + again, pause=0.001)
            got = await _labeled(mem, 30 + 30)  # the new run retrains from its init frames
            return srv.metrics, got

    metrics, got = run(go())
    # restart rule: the jump is suspect until 3 consecutive frames continue it (2 dropped)
    assert metrics.drops() == metrics.drops("seq_jump") == 2
    assert [m.seq for m in got[30:]] == list(range(10, 40))


def test_falling_behind_keeps_the_newest_frames_and_counts_drops(rng):
    cap = moving_clusters(rng, frames=200)
    p = stream_payloads(cap, rng, init=5)

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return SlowLabeler(marker_names, rate, delay_s=0.004)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(queue_size=4), [mem], factory=factory) as srv:
            await _feed(mem, p[:6], pause=0.01)  # init + first unlabeled (trains)
            await _labeled(mem, 1)
            mem.inject(b"")  # a reject in between must not disturb the queue
            for x in p[6:]:  # 194 frames in one burst, no yield in between
                mem.inject(x)
            depth = len(srv._queues["default"])
            got = await _labeled(mem, 4)  # at most queue_size remain after the burst
            await asyncio.sleep(0.1)
            return srv.metrics, got, depth

    metrics, got, depth = run(go())
    assert depth <= 4
    assert metrics.drops("queue_full") == 194 - 4
    assert [m.seq for m in got] == [196, 197, 198, 199]  # the newest survive


def test_unknown_streams_no_model_and_labeler_failures_are_counted(rng):
    cap = moving_clusters(rng, frames=40)
    p = stream_payloads(cap, rng, init=10)
    fails = {12, 13}

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return SlowLabeler(marker_names, rate, fail_on=fails)

    async def go():
        mem = MemoryTransport()
        s = _settings(allow_new_streams=False, warmup=False,
                      streams=[{"name": "default"}, {"name": "empty"}])  # fmt: skip
        async with Server(s, [mem], factory=factory) as srv:
            mem.inject(encode_frame("other", 0, 0.0, np.zeros((1, 3), np.float32)))
            mem.inject(encode_frame("empty", 0, 0.0, np.zeros((1, 3), np.float32)))
            await _feed(mem, p, pause=0.001)
            got = await _labeled(mem, 30 - len(fails))
            return srv.metrics, got

    metrics, got = run(go())
    assert metrics.drops("unknown_stream") == 1
    assert metrics.drops("no_model") == 1
    assert metrics.drops("labeler_error") == 2
    assert got[-1].seq == 39


def test_a_stream_whose_every_frame_fails_turns_lost_and_says_why(rng, caplog):
    """The labeler raises on every frame from some point on: each frame is counted
    (labeler_error), and after ``health_window_s`` of nothing but failures the status turns
    ``lost`` with one log line naming the error (it stayed ``online`` while publishing
    nothing)."""
    import logging

    cap = moving_clusters(rng, frames=150)
    p = stream_payloads(cap, rng, init=10)

    class Breaks:
        def __init__(self, inner):
            self.inner, self.calls = inner, 0

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def process(self, points, t, labels=None):
            self.calls += 1
            if self.calls > 60:
                raise RuntimeError("scripted: the labeler broke")
            return self.inner.process(points, t, labels)

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return Breaks(make_labeler("baseline", marker_names=marker_names, rate=rate))

    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, health_window_s=0.2), [mem],
                          factory=factory) as srv:  # fmt: skip
            await _feed(mem, p, pause=1 / 120)
            await until(lambda: srv.metrics.value("mocap_frames_in_total", stream="default")
                        >= 140, "every frame in")  # fmt: skip
            states = [decode(x).state for s, k, x, _ in mem.sent if k == "status"]
            return srv.metrics, states

    metrics, states = run(go())
    assert metrics.drops("labeler_error") >= 80
    assert states[-2:] == ["online", "lost"], states
    assert "each one failed (last: RuntimeError: scripted: the labeler broke): status lost" in (
        caplog.text
    )


@pytest.mark.parametrize("clock", ["frozen", "backwards", "frozen seq"])
def test_a_sender_whose_clock_stops_turns_lost_and_says_why_then_online_again(rng, caplog, clock):
    """After 80 good frames the sender's ``seq`` counts on but ``t`` stays put (or runs back)
    for 60 frames:
    every frame is dropped as a jump. After ``health_window_s`` of that the status turns
    ``lost`` with one line saying the frames' t does not advance (it stayed ``online``, the
    labeled fraction stale at its last value); a sender back to a sane clock is labeled again,
    the fraction climbs back through its average, and the stream reads ``online``."""
    import logging

    cap = moving_clusters(rng, frames=200)
    frames = frames_of(cap, np.random.default_rng(4))
    stuck = 79 / cap.rate
    payloads = []
    for f, (pts, truth) in enumerate(frames[:80]):
        labels = [cap.labels[i] for i in truth] if f < 10 else None
        payloads.append(encode_frame("default", f, f / cap.rate, pts, labels))
    for k in range(60):  # the sender repeats its last frame, seq counting on (or t)
        if clock == "frozen seq":
            payloads.append(encode_frame("default", 79, stuck + (k + 1) / cap.rate,
                                         frames[79][0], None))  # fmt: skip
            continue
        t = stuck if clock == "frozen" else stuck - (k + 1) / cap.rate
        payloads.append(encode_frame("default", 80 + k, t, frames[79][0], None))
    for f, (pts, _) in enumerate(frames[80:], start=80):  # a sane clock again: a new run
        payloads.append(encode_frame("default", 60 + f, 10.0 + f / cap.rate, pts, None))
    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, health_window_s=0.2), [mem]) as srv:
            await _feed(mem, payloads[:140], pause=1 / 120)
            await until(lambda: any(decode(x).state == "lost" for _, k, x, _ in mem.sent
                                    if k == "status"), "status lost")  # fmt: skip
            lost_fraction = srv.metrics.value("mocap_labeled_fraction", stream="default")
            await _feed(mem, payloads[140:], pause=1 / 120)
            await until(lambda: [decode(x).state for _, k, x, _ in mem.sent
                                 if k == "status"][-1] == "online", "online again")  # fmt: skip
            states = [decode(x).state for s, k, x, _ in mem.sent if k == "status"]
            return states, lost_fraction

    states, lost_fraction = run(go())
    lost = states.index("lost")
    assert "online" in states[:lost] and states[-1] == "online", states
    assert lost_fraction == 0.0
    assert "none continued the stream" in caplog.text
    assert "does not advance past the last accepted frame's" in caplog.text
    assert caplog.text.count("status lost") == 1


def test_a_sender_stamping_t_in_milliseconds_is_told_so(rng, caplog):
    """Frame times in ms (every step 8.3 "s" at 120 Hz): every frame after the first is a
    ``time_jump`` and the stream turns ``lost``; the log said seq and t "do not continue ...
    nor each other" though seq counted on, and never named the unit."""
    import logging

    cap = moving_clusters(rng, frames=80)
    payloads = [encode_frame("default", f, f * 1000.0 / cap.rate, pts, None)
                for f, (pts, _) in enumerate(frames_of(cap, np.random.default_rng(4)))]  # fmt: skip
    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, health_window_s=0.2), [mem]) as srv:
            await _feed(mem, payloads, pause=1 / 120)
            await until(lambda: any(decode(x).state == "lost" for _, k, x, _ in mem.sent
                                    if k == "status"), "status lost")  # fmt: skip
            return srv.metrics.drops("time_jump", "default")

    assert run(go()) >= 60
    assert "t advances 8.33333 per frame" in caplog.text and "is t in milliseconds?" in caplog.text


def test_a_second_sender_on_one_stream_is_named_in_the_log(rng, caplog):
    """Two replays sending to one stream (their seq and t far apart): the second one's frames
    are dropped (``second_sender``) while the first sends, and the log names both senders;
    once the first has been quiet for ``silent_after_s``, the stream takes the second's frames
    (a new run) and says so. Before, the log said only ``seq_jump``."""
    import logging

    cap = moving_clusters(rng, frames=120)
    first = stream_payloads(cap, rng, init=10)
    second = [encode_frame("default", 5000 + f, 100.0 + f / cap.rate, pts, None)
              for f, (pts, _) in enumerate(frames_of(cap, np.random.default_rng(5)))]  # fmt: skip
    caplog.set_level(logging.INFO, logger="labeler_service.service.server")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, silent_after_s=0.2), [mem]) as srv:
            for k in range(60):
                mem.inject(first[k], reply_to=("10.0.0.1", 4001))
                mem.inject(second[k], reply_to=("10.0.0.2", 4002))
                await asyncio.sleep(1 / 120)
            for k in range(60, 120):
                mem.inject(second[k], reply_to=("10.0.0.2", 4002))
                await asyncio.sleep(1 / 120)
            await until(lambda: srv.metrics.value("mocap_frames_in_total", stream="default")
                        >= 60 + 20, "the second sender's frames in")  # fmt: skip
            return srv.metrics.drops("second_sender", "default")

    assert run(go()) >= 60
    assert "frames from a second sender (10.0.0.2:4002) dropped while 10.0.0.1:4001 sends" in (
        caplog.text
    )
    assert "frames now come from 10.0.0.2:4002 (before: 10.0.0.1:4001)" in caplog.text


def _steady_and_bursts(rng, bursts_first: bool) -> tuple[list[int], int, object]:
    """A 120 Hz sender's 240 frames (10.0.0.1:4001) and, from 10.0.0.9:9, bursts of three
    far-off frames every 0.5 s (``bursts_first``: one burst before the steady sender's first
    frame too): the seqs published, the ``second_sender`` drops and the stream's sender."""
    cap = moving_clusters(rng, frames=240)
    steady = stream_payloads(cap, rng, init=10)
    far = np.full((4, 3), 9.0, np.float32)
    burst = iter(
        [encode_frame("default", 10**9 + k, 5000.0 + k / cap.rate, far, None) for k in range(60)]
    )
    intruder = ("10.0.0.9", 9)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False), [mem]) as srv:
            if bursts_first:
                for _ in range(3):
                    mem.inject(next(burst), reply_to=intruder)
                await asyncio.sleep(0.05)
            for k in range(240):
                mem.inject(steady[k], reply_to=("10.0.0.1", 4001))
                if k % 60 == 30:
                    for _ in range(3):
                        mem.inject(next(burst), reply_to=intruder)
                await asyncio.sleep(1 / 120)
            await until(lambda: srv.metrics.value("mocap_frames_out_total", stream="default")
                        >= 200, "the steady sender's frames out")  # fmt: skip
            seqs = [decode(p).seq for _, kind, p, _ in mem.sent if kind == "labeled"]
            return (
                seqs,
                srv.metrics.drops("second_sender", "default"),
                srv.streams["default"].sender,
            )

    return run(go())


def test_bursts_from_a_second_sender_do_not_take_a_sending_stream_over(rng):
    """Three frames in a row that continue each other are a new run by the restart rule: a
    second sender's burst of three every 0.5 s took a live stream over (its points published
    as the stream's frames, the stream's own labels 0.47 correct for 6 s). While the stream's
    sender sends, another sender's frames are dropped before the rule sees them."""
    seqs, dropped, sender = _steady_and_bursts(rng, bursts_first=False)
    assert dropped == 12 and max(seqs) < 10**9  # no burst frame published
    assert sender == ("10.0.0.1", 4001)


def test_a_burst_sender_that_got_the_stream_first_does_not_keep_a_steady_one_out(rng):
    """The bursts reach an idle stream first and become its sender: the steady sender's
    frames, many more, take the stream back through the restart rule (a review found every
    frame of a 120 Hz replay dropped as ``second_sender`` behind bursts every 0.5 s)."""
    seqs, _, sender = _steady_and_bursts(rng, bursts_first=True)
    assert sender == ("10.0.0.1", 4001)
    assert sum(s < 10**9 for s in seqs) >= 200 and max(seqs[-100:]) < 10**9


def test_a_second_sender_a_few_frames_behind_is_named_and_the_stream_turns_lost(rng, caplog):
    """Two replays started 40 frames apart: the second one's frames are ``late`` (seq behind
    by less than ``max_seq_step``) and dropped, while the first sends and after it stopped;
    the log names the second sender, and once nothing but its frames arrives the status turns
    ``lost`` (it stayed ``online``, silently, with nothing published)."""
    import logging

    cap = moving_clusters(rng, frames=160)
    first = stream_payloads(cap, rng, init=10)
    second = stream_payloads(cap, np.random.default_rng(6), init=0)
    caplog.set_level(logging.INFO, logger="labeler_service.service.server")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, health_window_s=0.2), [mem]):
            for k in range(120):
                mem.inject(first[k], reply_to=("10.0.0.1", 4001))
                if k >= 40:
                    mem.inject(second[k - 40], reply_to=("10.0.0.2", 4002))
                await asyncio.sleep(1 / 120)
            for k in range(80, 120):  # the first stopped; the second goes on, 40 behind
                mem.inject(second[k], reply_to=("10.0.0.2", 4002))
                await asyncio.sleep(1 / 120)
            await until(lambda: any(decode(x).state == "lost" for _, k, x, _ in mem.sent
                                    if k == "status"), "status lost")  # fmt: skip

    run(go())
    assert "frames from a second sender (10.0.0.2:4002) dropped while 10.0.0.1:4001 sends" in (
        caplog.text
    )
    assert "none continued the stream" in caplog.text


def test_status_is_retained_booting_until_labeled_then_offline_and_tasks_end(rng):
    """A configured stream without a model has no labeler until its labeled init frames have
    trained one: it reads ``booting`` (ready, nobody labeled yet), not ``online``, and turns
    ``online`` once they did; the log line names the configured streams ("no streams yet"
    was printed while they waited for their first frame)."""
    cap = moving_clusters(rng, subjects=2, markers=4, frames=60)
    frames = frames_of(cap, np.random.default_rng(3))
    payloads = [
        encode_frame("a", f, f / cap.rate, p, [cap.labels[i] for i in t] if f < 20 else None)
        for f, (p, t) in enumerate(frames)
    ]

    async def go():
        mem = MemoryTransport()
        srv = Server(_settings(streams=[{"name": "a"}, {"name": "b"}]), [mem])
        async with srv:
            ready = {s: decode(mem.retained[(s, "status")]).state for s in ("a", "b")}
            line = srv.metrics.log_line(srv._log_streams())
            tasks = list(srv._tasks)
            assert srv.ready.is_set()
            await _feed(mem, payloads, pause=0.001)
            await _labeled(mem, 40)
            labeled = {s: decode(mem.retained[(s, "status")]).state for s in ("a", "b")}
        offline = {s: decode(mem.retained[(s, "status")]).state for s in ("a", "b")}
        states = [decode(p).state for s, k, p, _ in mem.sent if k == "status" and s == "a"]
        return ready, line, labeled, offline, states, tasks, mem

    ready, line, labeled, offline, states, tasks, mem = run(go())
    assert ready == {"a": "booting", "b": "booting"}
    assert "no streams yet" not in line
    assert "[a] no frames yet status=booting" in line and "[b] no frames yet" in line, line
    assert labeled == {"a": "online", "b": "booting"}
    assert offline == {"a": "offline", "b": "offline"}
    assert states == ["starting", "booting", "online", "offline"]
    assert all(t.done() for t in tasks) and mem.closed


def test_warmup_runs_before_ready_and_send_failures_are_counted(rng):
    calls = []

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        calls.append(marker_names)
        return make_labeler("baseline", marker_names=marker_names, rate=rate)

    cap = moving_clusters(rng, frames=30)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=True), [mem], factory=factory) as srv:
            assert len(calls) == 1  # the synthetic warm-up labeler, before ready
            mem.fail_sends = True
            await _feed(mem, p, pause=0.001)
            await until(lambda: srv.metrics.drops("send_error") >= 20, "20 failed sends")
            return srv.metrics

    metrics = run(go())
    assert metrics.drops("send_error") >= 20  # 20 labeled frames (+ model messages)
    assert metrics.value("mocap_frames_out_total", stream="default") == 0


def test_model_message_repeats_every_second(rng):
    cap = moving_clusters(rng, frames=20)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(model_repeat_s=0.1), [mem]):
            await _feed(mem, p, pause=0.001)
            await _labeled(mem, 10)
            n = len(mem.sent)
            # no new frame comes in: only the repeat task can send the model again
            await until(lambda: [k for _, k, _, _ in mem.sent[n:]].count("model") >= 5,
                        "five repeated model messages")  # fmt: skip
        return [decode(x) for _, k, x, _ in mem.sent[n:] if k == "model"]

    repeats = run(go())
    assert all(isinstance(m, ModelMsg) and len(m.names) == 12 for m in repeats)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=64), st.builds(
    lambda seq, n, stream: encode_frame(stream, seq, seq / 100.0, np.ones((n, 3), np.float32)),
    st.integers(0, 2**64 - 1), st.integers(0, 5), st.sampled_from(["default", "x", "y"]),
)), max_size=40))  # fmt: skip
def test_fuzz_server_loop_survives_anything_and_keeps_labeling(garbage):
    cap = moving_clusters(np.random.default_rng(0), frames=30)
    p = stream_payloads(cap, np.random.default_rng(1), init=10, stream="fuzzed")

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            for g in garbage:
                mem.inject(g)
            await _feed(mem, p, pause=0.0005)
            got = await _labeled(mem, 20)
            return srv, got

    srv, got = run(go(), timeout=60)
    assert srv.metrics.drops("internal") == 0
    fuzzed = [m for m in got if m.stream == "fuzzed"]
    assert [m.seq for m in fuzzed][-1] == 29


@pytest.mark.parametrize("kind", ["labeled", "model", "status"])
def test_outgoing_kinds_sent_to_the_service_are_rejected(kind):
    from labeler_service.service.protocol import encode_labeled, encode_model, encode_status

    payload = {
        "labeled": encode_labeled(
            "s", 1, 1, 0.0, np.zeros((1, 3)), np.ones(1), np.zeros((0, 3)), None, 1, 1.0
        ),  # fmt: skip
        "model": encode_model("s", 1, ("a:x",), (("a", 0, 1),), 100.0),
        "status": encode_status("s", "online"),
    }[kind]

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            mem.inject(payload)
            await until(lambda: srv.metrics.drops(), "the reject")
            return srv.metrics.drops("type")

    assert run(go()) == 1
    assert isinstance(decode(payload), LabeledMsg | ModelMsg | StatusMsg)


def test_prometheus_endpoint_serves_the_counters(rng):
    import urllib.request

    cap = moving_clusters(rng, frames=30)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(metrics_port=0), [mem]) as srv:
            await _feed(mem, p + [b"junk"], pause=0.001)
            await _labeled(mem, 20)
            await asyncio.sleep(0.05)
            url = f"http://127.0.0.1:{srv.metrics_port}/metrics"
            text = await asyncio.to_thread(
                lambda: urllib.request.urlopen(url, timeout=5).read().decode()
            )
            line = srv.metrics.log_line()
        return text, line

    text, line = run(go())
    assert 'mocap_frames_in_total{stream="default"} 30.0' in text
    assert 'mocap_frames_out_total{stream="default"} 20.0' in text
    assert 'mocap_dropped_total{reason="not_msgpack",stream=""} 1.0' in text
    assert "mocap_labeling_seconds_bucket" in text and "mocap_ready 1.0" in text
    assert "[default] in=30 out=20" in line and "not_msgpack=1" in line


def test_a_full_transport_inbox_is_counted_as_rx_overflow():
    async def go():
        mem = MemoryTransport(maxsize=4)
        async with Server(_settings(warmup=False), [mem]) as srv:
            for _ in range(10):  # no yield: the ingest task cannot drain in between
                mem.inject(b"")
            await until(lambda: srv.metrics.drops("not_msgpack") >= 4, "the decoder's rejects")
        return srv.metrics

    metrics = run(go())
    assert metrics.drops("rx_overflow") == 6
    assert metrics.drops("not_msgpack") == 4  # the newest four reached the decoder


@pytest.mark.parametrize("thread", [False, True], ids=["inline", "labeling-thread"])
def test_labeling_thread_setting_moves_labeling_off_the_event_loop(rng, thread):
    import threading

    seen: list[str] = []

    class _Where(SlowLabeler):
        def process(self, points, t, labels=None):
            seen.append(threading.current_thread().name)
            return super().process(points, t, labels)

    def factory(kind, *, marker_names=(), rate, config=None, model=None, boot=False):
        return _Where(marker_names, rate)

    cap = moving_clusters(rng, frames=30)
    p = stream_payloads(cap, rng, init=10)

    async def go():
        mem = MemoryTransport()
        s = _settings(labeling_thread=thread, warmup=False)
        async with Server(s, [mem], factory=factory):
            await _feed(mem, p, pause=0.001)
            await _labeled(mem, 20)
        return threading.current_thread().name

    loop_thread = run(go())
    assert len(seen) == 30
    # the first unlabeled frame trains (a worker thread either way); the rest: see the setting
    after = seen[11:]
    if thread:
        assert all(n.startswith("label-default") for n in after), set(after)
    else:
        assert all(n == loop_thread for n in after), set(after)


@pytest.mark.parametrize("init", [5, 30])
def test_a_thin_labeled_start_is_logged_with_what_it_costs(rng, init, caplog):
    """An online stream trained from fewer labeled init frames than the labeler re-forms
    (``restructure_max_train_frames``) says so at training: its structure is re-formed in the
    frame path (tens of ms when it changes), and more init frames avoid it; 30 frames: silent."""
    import logging

    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")
    cap = moving_clusters(rng, subjects=2, markers=5, frames=60)
    payloads = stream_payloads(cap, np.random.default_rng(3), init)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(labeler="online", warmup=False), [mem]):
            await _feed(mem, payloads, pause=0.001)
            await _labeled(mem, 60 - init)

    run(go())
    thin = "labeled init frames: the labeler re-forms this thin structure" in caplog.text
    from labeler_service.labeling.config import LabelerConfig

    assert thin == (init < LabelerConfig().restructure_max_train_frames), caplog.text


def test_unlabeled_frames_with_nothing_to_start_from_name_the_two_fixes(caplog):
    """Unlabeled frames of an unlisted stream (``replay --init-frames 0`` to a service without
    that stream's model) went as ``unknown_stream`` in the periodic line's count only, and
    the subscriber blamed the stream name. Now the log names the stream and both fixes (a
    model for it, or labeled init frames first); a listed stream without a model (``no_model``)
    says the same."""
    import logging
    import socket

    caplog.set_level(logging.WARNING, logger="labeler_service.service.server")
    pts = np.zeros((4, 3), np.float32)

    async def go():
        s = _settings(warmup=False, streams=[{"name": "listed"}], udp={"port": 0})
        async with Server(s) as srv:
            host, port = srv.transports[0].address
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                for k in range(3):
                    sock.sendto(encode_frame("nomodel", k, k / 100, pts), (host, port))
                    sock.sendto(encode_frame("listed", k, k / 100, pts), (host, port))
            await until(lambda: srv.metrics.drops("unknown_stream") >= 3
                        and srv.metrics.drops("no_model") >= 3, "the drops")  # fmt: skip

    run(go())
    said = [r.getMessage() for r in caplog.records]
    for name in ("nomodel", "listed"):
        line = [m for m in said if f"stream {name}: unlabeled frames" in m]
        assert len(line) == 1, said
        assert f'name = "{name}" and model = "MODEL.json"' in line[0]
        assert "boot = true at the top of the settings, outside any table" in line[0]
        assert "replay --init-frames 50" in line[0]
    assert any(m.startswith("udp: frames dropped unread (unknown_stream)") for m in said)


def test_a_stream_whose_sender_stops_turns_idle_then_online_again(rng, caplog):
    """The sender stops mid-stream: after ``silent_after_s`` without a frame the status turns
    ``idle`` (announced, logged with the last sender, the labeled fraction 0); the same take
    sent again from another port (a restarted sender) is taken without a "second sender"
    line (the first is quiet) and the status reads ``online`` again. Before, the stream read
    ``online`` with its last labeled fraction for as long as the service ran. The periodic
    log line counts the points left unlabeled per frame."""
    import logging

    cap = moving_clusters(rng, frames=120)
    first = stream_payloads(cap, rng, init=10)
    again = stream_payloads(cap, np.random.default_rng(5), init=10, seq0=5000)
    caplog.set_level(logging.INFO, logger="labeler_service.service.server")

    def states(mem):
        return [decode(x).state for _, k, x, _ in mem.sent if k == "status"]

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, silent_after_s=0.3, log_interval_s=0.2),
                          [mem]) as srv:  # fmt: skip
            for p in first[:80]:
                mem.inject(p, reply_to=("10.0.0.1", 4001))
                await asyncio.sleep(1 / 120)
            await until(lambda: states(mem)[-1:] == ["idle"], "idle")
            idle_fraction = srv.metrics.value("mocap_labeled_fraction", stream="default")
            for p in again[:60]:
                mem.inject(p, reply_to=("10.0.0.1", 4002))
                await asyncio.sleep(1 / 120)
            await until(lambda: states(mem)[-1:] == ["online"], "online again")
            return states(mem), idle_fraction

    seen, idle_fraction = run(go())
    assert seen.index("online") < seen.index("idle") < len(seen) - 1, seen
    assert idle_fraction == 0.0
    assert "no frame for" in caplog.text and "(the last from 10.0.0.1:4001): status idle" in (
        caplog.text
    )
    assert "status idle; its labeler is kept for the sender's return" in caplog.text
    assert "second sender" not in caplog.text
    assert "frames now come from 10.0.0.1:4002 (before: 10.0.0.1:4001)" in caplog.text
    assert "unlabeled=" in caplog.text and "/frame status=" in caplog.text


def test_an_idle_stream_that_never_had_a_labeler_says_so(rng, caplog):
    """Unlabeled frames only, no model: the idle line does not promise a labeler it never
    had (it said "its labeler is kept for the sender's return")."""
    import logging

    cap = moving_clusters(rng, frames=40)
    caplog.set_level(logging.INFO, logger="labeler_service.service.server")

    async def go(init: int, frames: int):  # then a pause
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, silent_after_s=0.3), [mem]):
            for p in stream_payloads(cap, rng, init=init)[:frames]:
                mem.inject(p, reply_to=("10.0.0.1", 4001))
                await asyncio.sleep(1 / 120)
            await until(lambda: "status idle" in caplog.text, "idle")

    run(go(0, 30))
    no_labeler = "it has no labeler yet (no model, and no labeled init frames kept)"
    assert f"status idle; {no_labeler}" in caplog.text
    assert "kept for the sender's return" not in caplog.text
    caplog.clear()
    run(go(20, 20))  # labeled init frames only: they are kept, and it says so
    assert "status idle; its 20 labeled init frames are kept: its labeler is trained when the " in (
        caplog.text
    ), caplog.text
    assert no_labeler not in caplog.text


def test_a_slow_sender_is_not_idle_between_its_frames(rng):
    """Frames at 4 Hz (``t`` 0.25 s apart, sent 0.25 s apart) with ``silent_after_s`` = 0.2:
    the stream waits three frame periods before it reads ``idle``, so the status does not turn
    over at every frame (at a rate slower than 1 / ``silent_after_s`` every frame did)."""
    cap = moving_clusters(rng, frames=30)
    frames = frames_of(cap, np.random.default_rng(4))
    payloads = [encode_frame("default", f, f * 0.25, pts,
                             [cap.labels[i] for i in truth] if f < 10 else None)
                for f, (pts, truth) in enumerate(frames[:22])]  # fmt: skip

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(warmup=False, silent_after_s=0.2), [mem]):
            await _feed(mem, payloads, pause=0.25)
            await asyncio.sleep(0.1)
            return [decode(x).state for _, k, x, _ in mem.sent if k == "status"]

    states = run(go())
    assert "idle" not in states, states


def test_configured_streams_jobs_go_before_those_of_streams_opened_by_name():
    """The background slots' classes (``Background.run(priority=)``): a configured stream's
    boot, training or handover before a job of a stream any sender opened by name."""
    from types import SimpleNamespace

    from labeler_service.service.server import _priority

    assert _priority(SimpleNamespace(configured=True)) < _priority(
        SimpleNamespace(configured=False)
    )


def test_a_broken_model_file_fails_before_any_transport_binds(tmp_path):
    """``serve`` with a stream whose model file is broken bound its UDP port first, then
    failed: a supervisor saw the port taken before the error. The model is read first."""
    from labeler_service.errors import ModelError

    bad = tmp_path / "m.json"
    bad.write_text('{"rate": 100.0, "subjects": [{"name": "P", "markers": ["a"]}]}')
    mem = MemoryTransport()
    settings = _settings(warmup=False, streams=[{"name": "vol", "model": str(bad)}])

    async def go():
        async with Server(settings, [mem]):
            pass

    with pytest.raises(ModelError):
        run(go())
    assert not mem.entered


def test_serve_compiles_the_kernels_in_a_child_process(caplog, monkeypatch):
    """The first ``serve`` after an install compiled the kernels in its own process and kept
    about 1 GB resident for its life (280 MB after a start from the cache): ``serve`` sets
    ``compile_apart``, which runs the start's warm-ups in a child first, so the service loads
    them from numba's cache. Servers built directly (these tests) warm up in process."""
    import logging

    from labeler_service.cli import serve as serve_cli
    from labeler_service.service.server import compile_apart

    caplog.set_level(logging.INFO, logger="labeler_service.service.server")
    run(compile_apart(_settings(warmup=True)))
    assert "found in the cache by a child process" in caplog.text, caplog.text
    assert "failed" not in caplog.text
    assert Server.compile_apart is False
    seen = []

    class Probe(Server):  # what `serve` starts: records the flag and stops there
        async def __aenter__(self):
            seen.append(self.compile_apart)
            raise RuntimeError("probe")

    import labeler_service.service.server as server_module

    monkeypatch.setattr(server_module, "Server", Probe)
    with pytest.raises(RuntimeError, match="probe"):
        run(serve_cli.serve(_settings(warmup=False)))
    assert seen == [True]
