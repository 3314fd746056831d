"""The window start's handover (:mod:`labeler_service.service.handover`).

A stream whose labeled start runs through a window model labels with the plain labeler at
once; the window model trains off the loop, its labeler catches up on the frames labeled
meanwhile and replaces the plain one at a frame boundary. A new run, a recovery or a removed
stream abandon the handover (the plain labeler, or what replaced it, stays). No timing is
asserted: events (a job's end, a frame handled) decide when a test goes on.
"""

from __future__ import annotations

import asyncio
import os
import threading

import pytest
from service.helpers import run, until

from labeler_service.errors import LabelerError
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.labeling.labeler import Labeler
from labeler_service.scenes.corrupt import CorruptionSpec, StreamFrames, corrupt
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.service.continuity import Verdict
from labeler_service.service.handover import HANDOVER_LEFT_MAX, catch_up_plan
from labeler_service.service.protocol import FrameMsg, decode, encode_frame
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.service.stream import StreamState
from labeler_service.service.transports.memory import MemoryTransport

RATE = 120.0
INIT = 30


@pytest.fixture(scope="module")
def frames() -> StreamFrames:
    cap = simulate_scene(2, 8.0, "walk", seed=7, rate=RATE)
    return corrupt(cap, CorruptionSpec(protect_frames=INIT, seed=11))


def _settings(**kw):
    return load_settings(
        labeler="online", metrics_port=None, queue_size=4096,
        streams=[{"name": "vol", "labeled_start": "auto"}], **kw,
    )  # fmt: skip


def _labels(frames: StreamFrames, f: int) -> tuple[str | None, ...]:
    return tuple(frames.marker_names[m] if m >= 0 else None for m in frames.truth[f].tolist())


def _msg(frames: StreamFrames, f: int, labeled: bool = False, seq0: int = 0) -> FrameMsg:
    labels = _labels(frames, f) if labeled else None
    return FrameMsg("vol", seq0 + f, float(frames.times[f]), frames.points[f], labels)


def _started(frames: StreamFrames) -> tuple[StreamState, object]:
    """A stream trained as the server trains it (``train_staged``) and installed: the plain
    labeler labels, the handover waits for its job."""
    settings = _settings(warmup=False)
    st = StreamState("vol", settings, settings.streams[0])
    for f in range(INIT):
        st.buffer_init(_msg(frames, f, labeled=True))
    first = _msg(frames, INIT)
    lab, rate, out, ns, h = st.train_staged(st.take_init(), first)
    st.install_trained(lab, rate, first, out, 0, ns, h)
    assert isinstance(st.labeler, Labeler) and st.handover is h and h is not None
    assert st.handover_due()
    return st, h


def _job(st: StreamState, h) -> int:
    """Runs the handover's jobs as the server does (another while a time slice ends behind)."""
    fed = st.handover_job(h)
    while h.more:
        fed += st.handover_job(h)
    return fed


def _correct(frames: StreamFrames, f: int, msg, names) -> tuple[int, int]:
    """(correctly labeled visible true markers, visible true markers) of one output."""
    index = {n: j for j, n in enumerate(names)}
    observed = msg.state == 1
    ok = total = 0
    for i, m in enumerate(frames.truth[f].tolist()):
        if m < 0:
            continue
        total += 1
        hit = observed & (msg.positions == frames.points[f][i]).all(axis=1)
        ok += int(hit[index[frames.marker_names[m]]])
    return ok, total


def test_the_window_labeler_takes_over_at_a_frame_boundary(frames):
    st, h = _started(frames)
    model_before = st.model_id
    f = INIT + 1
    for _ in range(40):  # frames the plain labeler labels while the job would run
        assert st.process(_msg(frames, f), 0) is not None
        f += 1
    assert _job(st, h) > 0  # (the job: off the loop in the service)
    assert isinstance(h.labeler, BootingLabeler)
    assert not h.labeler.inline_boot and not h.labeler.inline_extend
    st.handover_done(h, True)
    assert not st.handover_due()
    out = st.process(_msg(frames, f), 0)  # the frame boundary that swaps
    assert out is not None
    assert st.labeler is h.labeler and st.handover is None and st.handovers == 1
    assert st.window_frames == INIT  # a recovery hands back to a window labeler
    assert st.model_id == model_before + 1  # the window model's bodies in the model message
    msg = decode(out.payload)
    assert msg.model == st.model_id
    ok = total = 0
    for g in range(f + 1, f + 60):
        msg = decode(st.process(_msg(frames, g), 0).payload)
        a, b = _correct(frames, g, msg, st.names)
        ok, total = ok + a, total + b
    assert ok >= 0.95 * total, (ok, total)


def test_too_many_frames_left_at_the_swap_go_back_off_the_loop(frames):
    st, h = _started(frames)
    f = INIT + 1
    _job(st, h)
    for _ in range(HANDOVER_LEFT_MAX + 3):  # the worker was busy: frames came before the swap
        st.process(_msg(frames, f), 0)
        f += 1
    st.handover_done(h, True)
    st.process(_msg(frames, f), 0)
    f += 1
    assert isinstance(st.labeler, Labeler) and st.handover is h  # not swapped on the frame path
    assert h.again and st.handover_due()
    _job(st, h)  # another round off the loop
    st.handover_done(h, True)
    st.process(_msg(frames, f), 0)
    assert st.labeler is h.labeler and st.handovers == 1


@pytest.mark.parametrize("event", ["labeled run", "time jump", "lost", "removed"])
def test_a_new_run_or_a_recovery_during_training_abandons_the_handover(frames, event):
    st, h = _started(frames)
    f = INIT + 1
    for _ in range(10):
        st.process(_msg(frames, f), 0)
        f += 1
    plain = st.labeler
    if event == "labeled run":  # retrains from the new run's init frames
        st.process(_msg(frames, 0, labeled=True, seq0=5000), 0, Verdict(new_run=True))
        assert st.labeler is None
    elif event == "time jump":  # a gap of unknown length: recovery from the plain model
        st.process(_msg(frames, f), 0, Verdict(new_run=True, time_jumped=True))
        assert st.recovering
    elif event == "lost":
        assert st.start_recovery("lost")
    else:
        st.release()
    assert st.handover is None and h.abandoned and st.handovers_abandoned == 1
    with pytest.raises(LabelerError, match="handover abandoned"):
        st.handover_job(h)  # (a job in flight stops at its next frame)
    st.handover_done(h, True)  # a late result installs nothing
    assert st.handover is None and not st.handover_due()
    if event in ("time jump", "lost"):
        labeler = st.labeler
        assert isinstance(labeler, BootingLabeler) and labeler is not h.labeler
        assert labeler.model is plain.model  # the recovery boots the plain labeler's model
        st.process(_msg(frames, f + 1), 0)
        assert st.labeler is labeler and st.handovers == 0


def test_the_catch_up_plan_strides_then_ends_at_the_full_rate():
    assert catch_up_plan(0, 6, 12) == []
    assert catch_up_plan(5, 6, 12) == [0, 1, 2, 3, 4]
    assert catch_up_plan(40, 6, 12) == [0, 6, 12, 18, 24, *range(28, 40)]
    assert catch_up_plan(40, 6, 0) == [0, 6, 12, 18, 24, 30, 36, 39]  # the newest always


async def _feed(
    srv, mem: MemoryTransport, frames: StreamFrames, f: int, seq0: int = 0, t0: float = 0.0
) -> None:
    """Injects frame ``f`` and waits until the stream has handled it (no queue drops)."""
    before = srv.metrics.value("mocap_frames_out_total", stream="vol") + srv.metrics.drops()
    mem.inject(encode_frame("vol", seq0 + f, t0 + float(frames.times[f]), frames.points[f]))
    await until(
        lambda: (
            srv.metrics.value("mocap_frames_out_total", stream="vol") + srv.metrics.drops() > before
        ),
        f"frame {f} handled",
    )
    await asyncio.sleep(1.0 / RATE)  # (the job's thread gets the GIL as a live source allows)


def _inject_init(mem: MemoryTransport, frames) -> None:
    """The stream's labeled init frames, into the service's input."""
    for f in range(INIT):
        mem.inject(encode_frame("vol", f, float(frames.times[f]), frames.points[f],
                                list(_labels(frames, f))))  # fmt: skip


def _statuses(mem: MemoryTransport) -> list[str]:
    return [decode(p).state for s, kind, p, _ in mem.sent if kind == "status" and s == "vol"]


def test_a_service_stream_hands_over_without_losing_a_frame(frames):
    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            _inject_init(mem, frames)
            f = INIT
            st = srv.streams["vol"]
            while st.handovers == 0:
                assert f < frames.n_frames - 100, "no handover before the scene's end"
                await _feed(srv, mem, frames, f)
                f += 1
            swapped = f - 1  # the frame labeled first by the window labeler
            assert isinstance(st.labeler, BootingLabeler) and st.window_frames == INIT
            for g in range(f, f + 60):
                await _feed(srv, mem, frames, g)
            outs = [decode(p) for _, kind, p, _ in mem.sent if kind == "labeled"]
            return st, srv.metrics, outs, swapped, f + 60, _statuses(mem)

    st, metrics, outs, swapped, end, statuses = run(go(), timeout=300.0)
    assert metrics.drops() == 0
    # the handover is counted where a dashboard sees it
    assert metrics.value("mocap_handovers_total", stream="vol", outcome="took_over") == 1
    assert metrics.value("mocap_handovers_total", stream="vol", outcome="abandoned") == 0
    assert metrics.snapshot()["streams"]["vol"]["handovers"] == 1
    assert sorted(m.seq for m in outs) == list(range(INIT, end))  # every frame labeled
    assert set(statuses[statuses.index("online") :]) == {"online"}  # never degraded or lost
    after = [m for m in outs if m.seq >= swapped]
    assert {m.model for m in after} == {st.model_id}  # the window labeler's outputs
    assert all(m.model < st.model_id for m in outs if m.seq < swapped)
    ok = total = 0
    for m in after:
        a, b = _correct(frames, m.seq, m, st.names)
        ok, total = ok + a, total + b
    assert ok >= 0.95 * total, (ok, total)


def test_a_new_labeled_run_while_the_window_model_trains_abandons_it(frames, monkeypatch):
    """The first run's window model is held in training; a new labeled run retrains (a new
    handover); the first job, released, ends abandoned and never installs."""
    gate = threading.Event()
    calls: list[int] = []
    original = StreamState._window_labeler

    def held(self, init, names, rate, cancel=None, model=None):
        calls.append(len(init.frames))
        if len(calls) == 1:
            gate.wait(timeout=120.0)
        return original(self, init, names, rate, cancel, model)

    monkeypatch.setattr(StreamState, "_window_labeler", held)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            _inject_init(mem, frames)
            for f in range(INIT, INIT + 10):
                await _feed(srv, mem, frames, f)
            st = srv.streams["vol"]
            first = st.handover
            await until(lambda: calls, "the first window model's training")
            # a new run: labeled frames at another seq and time (the restart rule confirms
            # it after its first frames, which it drops as suspect)
            seq0, t0 = 10_000, 100.0
            for f in range(INIT):
                mem.inject(encode_frame("vol", seq0 + f, t0 + float(frames.times[f]),
                                        frames.points[f], list(_labels(frames, f))))  # fmt: skip
            await until(lambda: first.abandoned, "the first handover abandoned")
            assert st.handover is None  # (the new run trains at its first unlabeled frame)
            gate.set()
            f = INIT
            while st.handovers == 0:
                assert f < frames.n_frames - 10, "no handover before the scene's end"
                await _feed(srv, mem, frames, f, seq0, t0)
                f += 1
            return st, first, srv.metrics

    st, first, metrics = run(go(), timeout=300.0)
    assert st.labeler is not first.labeler and isinstance(st.labeler, BootingLabeler)
    assert st.handovers == 1 and st.handovers_abandoned == 1
    for outcome in ("took_over", "abandoned"):
        assert metrics.value("mocap_handovers_total", stream="vol", outcome=outcome) == 1
    assert len(calls) == 2


def test_run_in_process_returns_raises_and_cancels():
    """The window model's training runs in a child process (``window_worker = "process"``):
    its result comes back, its error is named, a cancelled call terminates the child."""
    import math
    import time

    from labeler_service.errors import BudgetExceeded
    from labeler_service.service.background import run_in_process

    assert run_in_process(math.factorial, 10) == 3_628_800
    with pytest.raises(LabelerError, match="failed in its process: ValueError"):
        run_in_process(math.factorial, -1, name="fact")
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(BudgetExceeded, match="sleepy: cancelled; its process was terminated"):
        run_in_process(time.sleep, 60.0, cancel=cancel, name="sleepy")
    assert _settings().window_worker == "process"


@pytest.mark.parametrize("entry", ["handover_job", "window_model"])
def test_an_abandoned_handover_terminates_its_window_models_process(frames, monkeypatch, entry):
    """The stream removed (or a new run, a recovery) while its window model trains in a child
    process: the child is terminated then, not left running until the model is done. The
    server's job gets a budget event of its own (``Background``); only that one reached the
    child, the handover's abandonment did not (hostile run: a stream removed mid-handover left
    its ``window-model-<stream>`` process training on)."""
    import multiprocessing
    import time

    from labeler_service.errors import BudgetExceeded
    from labeler_service.service import stream as stream_mod

    real = stream_mod.run_in_process
    started = threading.Event()

    def slow(fn, *args, cancel=None, name="job"):  # a window model that takes its time
        started.set()
        return real(time.sleep, 30.0, cancel=cancel, name=name)

    monkeypatch.setattr(stream_mod, "run_in_process", slow)
    st, h = _started(frames)
    st.window_in_process = True
    budget = threading.Event()  # the Background job's own (never set here)
    errors: list[BaseException] = []

    def job() -> None:
        try:
            getattr(st, entry)(h, cancel=budget)  # (the server: window_model, then the job)
        except BaseException as exc:
            errors.append(exc)

    th = threading.Thread(target=job, daemon=True)
    th.start()
    assert started.wait(60.0), "the window model never started"
    deadline = time.monotonic() + 30.0
    while not [p for p in multiprocessing.active_children() if p.name == "window-model-vol"]:
        assert time.monotonic() < deadline, "no window-model child process"
        time.sleep(0.01)
    st.release()  # (the server, when the stream is removed or expires)
    th.join(timeout=25.0)
    assert not th.is_alive(), "the job waited for its abandoned window model"
    assert errors and isinstance(errors[0], BudgetExceeded | LabelerError), errors
    assert not [p for p in multiprocessing.active_children() if p.name == "window-model-vol"]
    assert h.abandoned and st.handover is None and st.handovers_abandoned == 1


def test_the_window_model_process_holds_no_background_slot(frames, monkeypatch):
    """While a stream's window model trains in its child process, another job (a second
    stream's training, a boot) gets the background slot: the child needs none of the
    service's GIL (hostile run: a second stream starting then waited the whole window model,
    0.7 s of its frames). The handover then completes with that model."""
    from labeler_service.service import stream as stream_mod

    gate = threading.Event()
    started = threading.Event()
    real = stream_mod.run_in_process

    def held(fn, *args, cancel=None, name="job"):  # the child, held until the test lets go
        started.set()
        while not gate.wait(0.01):
            if cancel is not None and cancel.is_set():
                raise LabelerError("cancelled")
        return real(fn, *args, cancel=cancel, name=name)

    monkeypatch.setattr(stream_mod, "run_in_process", held)

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(), [mem]) as srv:
            _inject_init(mem, frames)
            st = srv.streams["vol"]
            await _feed(srv, mem, frames, INIT)
            await until(started.is_set, "the window model's training")
            # the slot is free: a job of another stream runs while the window model trains
            other = await srv.background.run(lambda: "other", budget_s=60.0, name="other")
            assert not gate.is_set() and st.handover is not None and st.handovers == 0
            gate.set()
            f = INIT + 1
            while st.handovers == 0:
                assert f < frames.n_frames - 10, "no handover before the scene's end"
                await _feed(srv, mem, frames, f)
                f += 1
            return st, other

    st, other = run(go(), timeout=300.0)
    assert other == "other"
    assert isinstance(st.labeler, BootingLabeler) and st.handovers_abandoned == 0


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs Linux /proc")
def test_a_child_killed_before_it_read_its_job_fails_the_call_instead_of_hanging_it():
    """The job (a window of ~250 kB) went as the child Process's args, which multiprocessing
    writes into the child's bootstrap pipe while holding that pipe's read end itself: a child
    killed before it read them all (Ctrl-C reaching it mid-import) left the calling thread
    blocked in ``start()`` for good, and the service's exit waited on it after "stopped".
    Now the job goes over a pipe whose other end only the child holds: the call fails."""
    import os
    import signal
    import time

    from labeler_service.service.background import run_in_process

    big = b"x" * (8 << 20)  # far more than a pipe holds
    box: list[BaseException | object] = []

    def call():
        try:
            box.append(run_in_process(len, big, name="big"))
        except BaseException as exc:  # noqa: BLE001 (handed to the test thread)
            box.append(exc)

    def spawned() -> set[int]:
        """Our spawn children, from /proc (multiprocessing lists one only once started)."""
        out = set()
        for d in os.listdir("/proc"):
            try:
                with open(f"/proc/{d}/stat", encoding="ascii") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
                with open(f"/proc/{d}/cmdline", "rb") as f:
                    cmd = f.read()
            except (OSError, ValueError, IndexError):
                continue
            if ppid == os.getpid() and b"spawn_main" in cmd:
                out.add(int(d))
        return out

    before = spawned()
    t = threading.Thread(target=call, daemon=True)
    t.start()
    deadline = time.monotonic() + 60
    kids: set[int] = set()
    while not kids and time.monotonic() < deadline:
        kids = spawned() - before
        time.sleep(0.001)
    assert kids, "no child started"
    os.kill(kids.pop(), signal.SIGKILL)
    t.join(timeout=60)
    assert not t.is_alive(), "run_in_process hung on a child that died before its job"
    assert isinstance(box[0], LabelerError), box
