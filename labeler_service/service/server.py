"""The asyncio service: transports in, one worker per stream, labeled frames out.

::

    transport.messages() --decode/validate--> per-stream DropOldestQueue --worker--> labeler
         (udp, mqtt, memory)   (rejects counted)     (keep newest, drops counted)      |
                                                                                        v
    transport.send(stream, "labeled" | "model" | "status")  <---- encode_labeled ------+

Tasks are named (``ingest-udp``, ``stream-<name>``, ``model-repeat``, ``transport-drops``,
``metrics-log``); leaving the ``async with`` publishes ``offline`` status, cancels every task,
then awaits them. What the transports drop themselves (receive-queue overflow, datagrams the
kernel refused) is added to the drop metric once a second, when freed C-heap memory is also
returned to the OS (``malloc_trim`` in a thread, :mod:`~labeler_service.service.background`;
after a removed stream or the end of an abandoned job also a full ``gc.collect``, cheap because
the objects of the start-up are frozen). Kernels are compiled on a synthetic scene before the
status turns ``online`` (``booting`` for a stream that cannot label yet) and ``ready`` is set.
Labeling runs inline on the event loop (measured fastest on 2 cores), except the one heavy call
per stream (the first unlabeled frame, which trains the labeler), which runs off the loop through
:class:`~labeler_service.service.background.Background` with a ``train_budget_s`` budget (over
it: status ``training_failed``) so other streams keep flowing. ``labeling_thread = true``
labels every frame in one thread per stream instead (the numba kernels release the GIL).
A stream of the window start (``labeled_start``) is trained as a plain one first; its window
model, booting labeler and catch-up then run through the same ``Background`` (task
``handover-<stream>``, budget ``train_budget_s`` per job, catch-up in time slices that give the
slot up between them) and the stream swaps labelers at a frame boundary
(:mod:`~labeler_service.service.handover`).

Boot (a configured stream with a ``model``; ``boot = true``): after each frame, when the
stream's booting labeler wants an attempt and none is in flight, its snapshot is taken in the
frame thread and the attempt runs through the same ``Background`` (budget ``boot_budget_s``;
over it: ``mocap_boot_failed_total``, the labeler backs off); the result is installed before
the next frame is labeled. Frames keep flowing meanwhile, their points unlabeled until a
subject boots (``mocap_boot_attempts_total``, ``mocap_boot_seconds``,
``mocap_subjects_booted``).

Bounded state: streams not in the settings take one of ``max_streams`` slots only with a
labeled frame (or when their trained labeler is in the cache; a full table evicts by evidence,
:meth:`Server._free_slot`; churn is logged rate-limited), and are removed after
``stream_idle_s`` without frames (task ``expire``), their labeler kept in a small LRU cache
(``stream_cache_size``) and their metric series removed; frames for streams without a slot are
counted under one series (stream ``""``). Health (labeled fraction) changes publish a status
(``degraded``, ``lost``, back to ``online``) and log a warning.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import AsyncExitStack

import numpy as np

from labeler_service.errors import (
    BudgetExceeded,
    ConfigError,
    InitBufferFullError,
    LabelerError,
    LimitExceeded,
    MocapError,
    ProtocolError,
)
from labeler_service.labeling.frame import FrameLabeler
from labeler_service.labeling.registry import LabelerFactory, make_labeler
from labeler_service.service.background import (
    Background,
    configure_allocator,
    release_memory,
    run_in_process,
)
from labeler_service.service.boot_worker import BootWorker
from labeler_service.service.continuity import ACCEPT, Verdict
from labeler_service.service.handover import YIELD_S
from labeler_service.service.metrics import RateLimitedLog, ServiceMetrics
from labeler_service.service.protocol import FrameMsg, SubscribeMsg, decode, encode_status
from labeler_service.service.settings import ServiceSettings, StreamSettings, exposure_warnings
from labeler_service.service.stream import StreamState, no_start
from labeler_service.service.transports.base import (
    DropOldestQueue,
    Incoming,
    Transport,
    cancel_and_wait,
)
from labeler_service.wording import plural

#: the message types a client may send the service (the others are its output)
_ACCEPTED = frozenset({"frame", "subscribe"})
#: Starts of the boot worker tried before it is given up (``Server._start_worker``), and the
#: wait before the next try, times the failures so far (s).
WORKER_TRIES = 3
WORKER_RETRY_S = 10.0
log = logging.getLogger(__name__)

#: Frames of sequential progress (:attr:`StreamState.progress`) that protect a stream in its
#: start-up window from eviction by a newcomer (names that appear with one or two packets).
PROVEN_FRAMES = 3


def build_transports(settings: ServiceSettings) -> list[Transport]:
    """The transports the settings enable (UDP and/or MQTT)."""
    out: list[Transport] = []
    if settings.udp.enabled:
        from labeler_service.service.transports.udp import UdpTransport

        out.append(UdpTransport(settings.udp))
    if settings.mqtt.enabled:
        from labeler_service.service.transports.mqtt import MqttTransport

        out.append(MqttTransport(settings.mqtt, [s.name for s in settings.streams]))
    if not out:
        raise MocapError("no transport enabled: set udp.enabled or mqtt.enabled")
    return out


def synthetic_warmup_frames(
    seed: int = 0, subjects: int = 2, markers: int = 6, frames: int = 80, rate: float = 120.0
) -> tuple[tuple[str, ...], list[tuple[np.ndarray, float, np.ndarray | None]]]:
    """A tiny scene (rigid clusters moving smoothly) to compile every kernel before serving.

    Returns marker names and ``(points, t, labels or None)`` frames: the first half labeled
    (training window), the rest unlabeled with one marker hidden now and then (recovery path)
    and a ghost point.
    """
    rng = np.random.default_rng(seed)
    names = tuple(f"W{s}:m{i}" for s in range(subjects) for i in range(markers))
    shapes = rng.normal(scale=60.0, size=(subjects, markers, 3))
    out = []
    for f in range(frames):
        t = f / rate
        pos = []
        for s in range(subjects):
            a = 0.5 * np.sin(2.0 * t + s)
            rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            centre = np.array([600.0 * s + 200.0 * t, 50.0 * np.sin(3 * t), 1000.0])
            pos.append(centre + shapes[s] @ rot.T)
        p = np.concatenate(pos).astype(np.float32)
        idx = np.arange(len(names), dtype=np.int32)
        if f >= frames // 2 and f % 5 == 0:
            keep = idx != (f // 5) % len(names)
            p, idx = p[keep], idx[keep]
        p = np.concatenate([p, p[:1] + np.float32(80.0)])
        idx = np.concatenate([idx, [-1]]).astype(np.int32)
        order = rng.permutation(len(p))
        out.append((p[order], t, idx[order] if f < frames // 2 else None))
    return names, out


def warm_up(kind: str, config, factory: LabelerFactory = make_labeler) -> float:
    """Runs a labeler of ``kind`` over the synthetic scene (numba compiles or loads its cache);
    returns the seconds it took."""
    from labeler_service.labeling.booting import warmup_jump_watch

    t0 = time.perf_counter()
    names, frames = synthetic_warmup_frames()
    labeler = factory(kind, marker_names=names, rate=120.0, config=config)
    _feed_warmup(labeler, frames, f"labeler warm-up failed ({kind})")
    if kind == "online":  # (its streams watch for jumps of the scene: StreamState._jumped)
        warmup_jump_watch(120.0)
    return time.perf_counter() - t0


def _feed_warmup(labeler, frames, failed: str) -> None:
    """Warms ``labeler`` up and feeds it the synthetic ``frames``; a failure is a
    :class:`LabelerError` starting with ``failed``."""
    labeler.warmup()
    try:
        for points, t, labels in frames:
            labeler.process(points, t, labels)
    except Exception as exc:
        raise LabelerError(f"{failed}: {exc}") from exc


def window_starts(settings: ServiceSettings) -> bool:
    """True when a stream of the service may start through a window model (``labeled_start``
    not ``labeler`` on a stream without a model file, or on the streams not listed, which
    take the default): the service then warms the booting labeler's kernels up too."""
    if settings.labeler != "online":
        return False
    listed = any(s.model is None and s.labeled_start != "labeler" for s in settings.streams)
    default = StreamSettings.model_fields["labeled_start"].default
    return listed or (settings.allow_new_streams and default != "labeler")


def warm_up_window_start(config) -> float:
    """Runs the window start over the synthetic scene (window model, booting labeler and its
    boot kernels, which numba compiles or loads here rather than in the first handover);
    returns the seconds it took."""
    from labeler_service.capture import Capture
    from labeler_service.labeling.registry import make_window_labeler
    from labeler_service.labeling.structure import window_model

    t0 = time.perf_counter()
    names, frames = synthetic_warmup_frames()
    labeled = [(p, t, lab) for p, t, lab in frames if lab is not None]
    pos = np.full((len(labeled), len(names), 3), np.nan, dtype=np.float32)
    for k, (p, _, lab) in enumerate(labeled):
        pos[k, lab[lab >= 0]] = p[lab >= 0]
    model = window_model(Capture(pos, names, 120.0, source="warm-up"))
    labeler = make_window_labeler(model, rate=120.0, window_frames=len(labeled), config=config)
    _feed_warmup(labeler, frames, "window start warm-up failed")
    return time.perf_counter() - t0


def warm_up_recovery(config) -> float:
    """Compiles (or loads) what a recovery runs (docs/service.md "Recovery"): a booting
    labeler's kernels (:func:`~labeler_service.labeling.booting.warmup_booting`).
    Every stream of the online labeler may recover through a booting labeler; without this a
    first recovery on a cold cache compiled them in the frame path (a helper's replay: 2.4 s,
    127 frames dropped as ``queue_full``). Returns the seconds it took."""
    from labeler_service.labeling.booting import warmup_booting

    t0 = time.perf_counter()
    warmup_booting(120.0, config)
    return time.perf_counter() - t0


def warm_up_all(settings: ServiceSettings, factory: LabelerFactory = make_labeler) -> float:
    """Every warm-up the service's start runs (:func:`warm_up`, then the window start's or a
    recovery's kernels); returns the seconds it took."""
    took = warm_up(settings.labeler, settings.labeler_config, factory)
    if window_starts(settings):
        took += warm_up_window_start(settings.labeler_config)
    elif settings.labeler == "online":  # (the window start's covers it)
        took += warm_up_recovery(settings.labeler_config)
    return took


async def compile_apart(settings: ServiceSettings) -> None:
    """Runs :func:`warm_up_all` in a child process first (:func:`~.background.run_in_process`,
    the window model's mechanism: SIGINT blocked in the child, ended on a stop), so that numba
    compiles there and the service then loads the compiled kernels from its on-disk cache.
    Compiling in the service's own process kept about 1 GB resident for its whole life (a
    hostile soak: 1.03 GB after the first start's compile, 280-290 MB after later starts;
    ``warm_up`` alone 947 against 214 MB). A warm cache costs the child about 1.3 s. A child
    that fails is logged and the service warms up in process as before; a stop during the
    start ends the child."""
    cancel = threading.Event()
    t0 = time.perf_counter()
    try:
        await asyncio.to_thread(
            run_in_process, warm_up_all, settings, cancel=cancel, name="kernel compile"
        )
    except asyncio.CancelledError:  # a stop during the start
        cancel.set()
        raise
    except LabelerError as exc:
        log.warning("the kernels' compile in a child process failed (%s): compiling them in "
                    "the service's process", exc)  # fmt: skip
        return
    log.info("kernels compiled or found in the cache by a child process (%.1f s)",
             time.perf_counter() - t0)  # fmt: skip


class Server:
    """The labeling service over the given transports. Use as ``async with Server(...)``.

    ``compile_apart`` (set by ``mocap-labeler serve``): compile the kernels in a child process
    first (:func:`compile_apart`); tests construct servers without it."""

    compile_apart = False

    def __init__(
        self,
        settings: ServiceSettings,
        transports: Sequence[Transport] | None = None,
        factory: LabelerFactory = make_labeler,
    ) -> None:
        self.settings = settings
        self.transports = list(transports) if transports is not None else None
        self.factory = factory
        self.metrics = ServiceMetrics()
        self.streams: dict[str, StreamState] = {}
        self._queues: dict[str, DropOldestQueue[tuple[FrameMsg, int, Verdict]]] = {}
        self._workers: dict[str, asyncio.Task] = {}
        #: trained labelers of expired unconfigured streams: name -> (labeler, rate, last t), LRU
        self.cache: OrderedDict[str, tuple[FrameLabeler, float, float | None]] = OrderedDict()
        self.background = Background()
        #: boot steps run in this worker process (``boot_worker = "process"``), started at
        #: start-up when a configured stream boots (``boot = true``, or a ``boot = false``
        #: model stream's recovery), else in the background at a stream's first recovery
        #: (``_want_worker``)
        self.boot_worker = (
            BootWorker(helpers=settings.boot_helpers) if settings.boot_worker == "process" else None
        )
        self._worker_starting = False
        #: failed starts of the worker and when the next may be tried (_start_worker)
        self._worker_failures = 0
        self._worker_retry_at = 0.0
        #: names whose labeled frames the UDP pre-filter let through recently (``_admit``)
        self._starting: OrderedDict[str, None] = OrderedDict()
        self._configured = frozenset(st.name for st in settings.streams)
        self._trim_soon = False
        self._published_model: dict[str, int] = {}
        self._transport_drops: dict[tuple[str, str, str], int] = {}
        self._executors: dict[str, ThreadPoolExecutor] = {}
        #: running tasks; a task leaves the set when it ends (a finished task keeps its result
        #: or exception, whose traceback holds the frame's locals: an expired stream's state)
        self._tasks: set[asyncio.Task] = set()
        self._stack: AsyncExitStack | None = None
        self._rlog = RateLimitedLog(log)
        self._transport_down: dict[str, str | None] = {}  # transport name -> its trouble
        self.ready: asyncio.Event | None = None
        self._ready_ns = 0  # time.time_ns() when the transports' frames start being read
        self.metrics_port: int | None = None
        self.warmup_s = 0.0

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> Server:
        configure_allocator()
        self.ready = asyncio.Event()
        if self.transports is None:
            self.transports = build_transports(self.settings)
        self._stack = AsyncExitStack()
        try:
            for line in exposure_warnings(self.settings):
                log.warning("%s", line)
            models = {}  # (read once: each stream starts from the model read here)
            for s in self.settings.streams:
                # a broken model file fails before anything binds a port or warms up (it bound
                # UDP first: a supervisor saw the port taken, then the error)
                if s.model is not None:
                    from labeler_service.labeling.templates import load_model

                    models[s.name] = await asyncio.to_thread(load_model, s.model)
            if self.settings.metrics_port is not None:
                # before the warm-up: a port in use fails at once, not after it
                try:
                    self.metrics_port = self.metrics.serve_http(
                        self.settings.metrics_host, self.settings.metrics_port
                    )
                except OSError as exc:
                    raise ConfigError(
                        f"metrics_port: cannot listen on {self.settings.metrics_host}:"
                        f"{self.settings.metrics_port}: {exc.strerror or exc}"
                    ) from exc
            for t in self.transports:
                t.admission = self._admit
                await self._stack.enter_async_context(t)  # type: ignore[arg-type]
                rcvbuf = t.receive_buffer_bytes
                if rcvbuf is not None:
                    self.metrics.receive_buffer.set(rcvbuf)
            for s in self.settings.streams:
                await self._status(s.name, "starting")
            if self.settings.warmup:
                log.info("warming up the kernels (the first start after an install compiles "
                         "them: a minute or more)")  # fmt: skip
                if self.compile_apart:
                    await compile_apart(self.settings)
                self.warmup_s = await asyncio.to_thread(warm_up_all, self.settings, self.factory)
                log.info("kernels warm (%.2f s)", self.warmup_s)
            for s in self.settings.streams:
                state = self._new_stream(s.name, s)
                if s.model is not None:
                    await asyncio.to_thread(state.start_from_model, model=models[s.name])
                    if self.settings.warmup and state.booting is not None:
                        await asyncio.to_thread(state.booting.warmup)  # the boot's kernels too
                    # boot = true: it boots; boot = false: a live source's first frame starts
                    # a recovery (_want_worker), booted by the spare
                    lab = state.booting or state.spare
                    if (
                        lab is not None
                        and self.boot_worker is not None
                        and not self._worker_failures
                    ):
                        await self._start_worker(self.boot_worker, state)
                    await self._publish_model(state)
            # everything alive now (modules, compiled kernels, models) lives as long as the
            # process: the collector skips it from now on (full collections stay cheap)
            gc.collect()
            gc.freeze()
            # unlabeled frames received before this moment waited out the start (seconds: the
            # warm-up, the boot worker's): stale, dropped as ``starting`` (labeled after
            # `ready`, they came out 3.3 s late, a hostile run)
            self._ready_ns = time.time_ns()
            for t in self.transports:
                self._spawn(self._ingest(t), f"ingest-{t.name}")
            self._spawn(self._model_repeat(), "model-repeat")
            self._spawn(self._transport_drops_loop(), "transport-drops")
            self._spawn(self._log_loop(), "metrics-log")
            self._spawn(self._expire_loop(), "expire")
            self._spawn(self._silence_loop(), "silence")
            if self.metrics_port is not None:
                log.info("metrics on http://%s:%d/metrics", self.settings.metrics_host,
                         self.metrics_port)  # fmt: skip
            for name, st in self.streams.items():
                await self._status(name, st.ready_status())
        except BaseException:
            await self._shutdown()
            raise
        self.metrics.ready.set(1)
        self.ready.set()
        log.info("ready: %s", ", ".join(t.name for t in self.transports))
        self._transport_health(log_all=True)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._shutdown()

    async def _shutdown(self) -> None:
        self.metrics.ready.set(0)
        for name in list(self.streams):
            with contextlib.suppress(Exception):
                await self._status(name, "offline")
        self.background.close()
        if self.boot_worker is not None:
            self.boot_worker.close()
        tasks, self._tasks = self._tasks, set()
        await cancel_and_wait(tasks)
        self._count_transport_drops()
        for ex in self._executors.values():
            ex.shutdown(wait=True, cancel_futures=True)
        self._executors.clear()
        self.metrics.close()
        if self._stack is not None:
            stack, self._stack = self._stack, None
            await stack.aclose()
        log.info("stopped: %s", self.metrics.log_line(self._log_streams()))

    def _spawn(self, coro, name: str) -> asyncio.Task:
        task = asyncio.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # ------------------------------------------------------------------ streams
    def _new_stream(self, name: str, s: StreamSettings | None) -> StreamState:
        state = StreamState(name, self.settings, s, self.factory)
        state.boot_worker = self.boot_worker
        state.window_in_process = self.settings.window_worker == "process"
        self.streams[name] = state
        self._queues[name] = DropOldestQueue(self.settings.queue_size)
        if self.settings.labeling_thread:
            self._executors[name] = ThreadPoolExecutor(1, thread_name_prefix=f"label-{name}")
        if s is not None and s.model is not None and self.settings.boot:
            state.on_lost = self._lost_reboots
        self._workers[name] = self._spawn(self._worker(state), f"stream-{name}")
        self.metrics.streams_active.set(len(self.streams))
        return state

    def _dynamic(self) -> list[StreamState]:
        return [st for st in self.streams.values() if not st.configured]

    def _stream_for(self, msg: FrameMsg, source: object = None) -> StreamState | None:
        """The stream's state; a stream not in the settings gets a slot only with a labeled
        frame (or a cached labeler), evicting another unconfigured stream only by the rule of
        :meth:`_free_slot` when all are taken. ``source``: who sent the frame (UDP: its
        address)."""
        name = msg.stream
        state = self.streams.get(name)
        if state is not None:
            return state
        if not self.settings.allow_new_streams:
            return None
        cached = self.cache.get(name)
        if msg.labels is None and cached is None:
            return None  # an unlabeled frame cannot start a stream: no slot for it
        if len(self._dynamic()) >= self.settings.max_streams and not self._free_slot(source):
            return None
        if cached is not None:
            del self.cache[name]
            self._rlog.info("churn-new", "stream %s: back (resumes from its cached labeler)",
                            name)  # fmt: skip
        else:
            self._rlog.info("churn-new", "stream %s: new (starts from labeled init frames)",
                            name)  # fmt: skip
        state = self._new_stream(name, None)
        state.source = source
        if cached is not None:
            state.resume(*cached)
        self._spawn(self._status(name, state.ready_status()), f"status-{name}")
        return state

    def _admit(self, name: str, payload: bytes) -> str | None:
        """The UDP receiver's pre-filter (before decoding): the receive-queue key of a frame
        for stream ``name``, or None to drop it unread as ``unknown_stream``. Admitted, under
        their stream's name (the queue is fair between keys, FIFO within one): frames of a
        stream with a slot or a cached labeler, labeled frames (they may start a stream; their
        names are remembered, at most 64), and the frames following those before the slot
        exists (it is made when the first one is decoded). ``b"labels" in payload`` is a
        conservative test: a false positive only costs a full decode."""
        if name in self.streams:
            return name
        if name in self._configured:  # (its slot is made at the start, before `ready`)
            self._rlog.warning("starting-stream", "udp: frames of stream %s dropped unread: the "
                               "service is starting (its configured streams are set up before "
                               "it says ready)", name)  # fmt: skip
            return None
        if not self.settings.allow_new_streams:
            return None
        starting = self._starting
        if b"labels" in payload:
            starting[name] = None
            starting.move_to_end(name)
            if len(starting) > 64:
                starting.popitem(last=False)
            return name
        if name in starting or name in self.cache:
            return name
        # said (rate-limited), else the frames went as a count in the periodic line only
        self._rlog.warning("unknown-stream", "udp: frames dropped unread (unknown_stream): %s",
                           no_start(name))  # fmt: skip
        return None

    def _free_slot(self, source: object = None) -> bool:
        """Frees one slot of an unconfigured stream for a newcomer from ``source``, or returns
        False (the newcomer's frame is dropped as ``unknown_stream``).

        An idle stream goes first. Else only a stream still in its labeled start-up window (no
        labeler; a started one is in real use) can go, and only when it is the weaker claim:
        its source holds at least two more such slots than the newcomer's would with it (a
        flood of names from one sender), or it has shown less than :data:`PROVEN_FRAMES`
        frames of sequential progress (:attr:`StreamState.progress`) and comes from the
        newcomer's source or one holding at least as many slots. The victim: the source
        holding the most start-up slots first, then the least progress, then the least
        recently active. So a flooder churns only its own one-packet names or is refused, and
        a stream making progress is never evicted by names that appear with one or two
        packets."""
        dyn = self._dynamic()
        now = time.monotonic()
        idle = [st for st in dyn if self._idle(st, now)]
        if idle:
            self._remove_stream(idle[0].name)
            return True
        unstarted = [st for st in dyn if not st.started]
        held: dict[object, int] = {}
        for st in unstarted:
            held[st.source] = held.get(st.source, 0) + 1
        mine = held.get(source, 0) + 1  # the newcomer's source with the newcomer
        candidates = [
            st
            for st in unstarted
            if held[st.source] >= mine + 2
            or (st.progress < PROVEN_FRAMES and (st.source == source or held[st.source] >= mine))
        ]
        if not candidates:
            return False
        victim = min(candidates, key=lambda st: (-held[st.source], st.progress,
                                                 st.last_activity))  # fmt: skip
        self._remove_stream(victim.name)
        return True

    def _remove_stream(self, name: str) -> None:
        state = self.streams.pop(name)
        task = self._workers.pop(name, None)
        if task is not None:
            task.cancel()
        # its boot and handover jobs leave the background queue (a running one is told to stop):
        # a hostile run's expired streams still ran their queued boots' whole budgets, one
        # after another, 40 s after their senders had stopped
        mine = {f"boot-{name}", f"handover-{name}"}
        for job in [t for t in self._tasks if t.get_name() in mine]:
            job.cancel()
        self._queues.pop(name, None)
        ex = self._executors.pop(name, None)
        if ex is not None:
            ex.shutdown(wait=False, cancel_futures=True)
        self._published_model.pop(name, None)
        if state.labeler is not None and state.rate and self.settings.stream_cache_size > 0:
            self.cache[name] = (state.labeler, state.rate, state.t_last)
            self.cache.move_to_end(name)
            while len(self.cache) > self.settings.stream_cache_size:
                self.cache.popitem(last=False)
        # what the stream buffered goes now, whoever still refers to the state (its cancelled
        # worker's frame until the task ends; an abandoned training job until it returns)
        state.release()
        self.metrics.forget(name)
        self._trim_soon = True  # its buffers: full gc (freelists) and trim, off this call
        self.metrics.streams_expired.inc()
        self.metrics.streams_active.set(len(self.streams))
        self._spawn(self._status(name, "offline"), f"status-{name}-offline")
        self._rlog.info("churn-removed", "stream %s: removed (idle or evicted); %d cached "
                        "labelers", name, len(self.cache))  # fmt: skip

    def _idle(self, st: StreamState, now: float) -> bool:
        """No frame for ``stream_idle_s`` and nothing left to do (queue empty, not training)."""
        return (
            now - st.last_activity > self.settings.stream_idle_s
            and not st.training
            and not len(self._queues.get(st.name, ()))
        )

    async def _expire_loop(self) -> None:
        """Removes unconfigured streams idle for ``stream_idle_s`` (configured ones stay)."""
        period = min(5.0, self.settings.stream_idle_s / 4)
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            idle = [st for st in self._dynamic() if self._idle(st, now)]
            for st in idle:
                self._remove_stream(st.name)
            # what the removed streams held is returned by the next transport-drops tick

    async def _silence_loop(self) -> None:
        """A stream whose frames stop: after ``silent_after_s`` with no frame arriving (or
        three of its usual gaps between frames, when longer), its status turns ``idle`` and
        its labeled fraction 0 (the log says since when and from whom); its labeler is kept,
        and the next labeled frame gives the status back. Before, a stream whose sender had
        stopped read ``online`` (log, status topic, gauge) for as long as the service ran."""
        window = self.settings.silent_after_s
        while True:
            await asyncio.sleep(min(0.5, max(0.05, window / 4)))
            now = time.monotonic()
            for name, st in list(self.streams.items()):
                if not st.arrival_gaps or st.status in ("idle", "training_failed"):
                    continue  # (fewer than two frames: it reads ``booting`` or ``starting``)
                # at least three of its usual gaps between frames: a sender at 1 Hz is slow, not
                # gone (at one frame per 1.1 s every frame turned the status over)
                quiet = now - st.last_activity
                if quiet <= max(window, 3.0 * float(np.median(st.arrival_gaps))):
                    continue
                st.status = "idle"
                st.labeled_fraction = st.recovered_fraction = float("nan")
                self.metrics.health(name, 0.0, 0.0)
                if st.labeler is not None:
                    kept = "its labeler is kept for the sender's return"
                elif st.init_frames:  # (the labeler is trained when unlabeled frames come)
                    n_init = len(st.init_frames)
                    kept = (
                        f"its {n_init} labeled init frame{'s' * (n_init != 1)} are kept: its "
                        "labeler is trained when the first unlabeled frame arrives"
                    )
                else:
                    kept = "it has no labeler yet (no model, and no labeled init frames kept)"
                self._rlog.warning(f"idle-{name}", "stream %s: no frame for %.1f s (the last "
                                   "from %s): status idle; %s", name, quiet,
                                   _who(st.sender), kept)  # fmt: skip
                await self._status(name, "idle")

    # ------------------------------------------------------------------ ingest
    async def _ingest(self, transport: Transport) -> None:
        """Decodes every message of one transport; a bad one is counted and skipped."""
        async for inc in transport.messages():
            try:
                self._handle(transport, inc)
            except ProtocolError as exc:
                self.metrics.drop(exc.reason)
                self._rlog.warning(
                    f"reject-{exc.reason}", "%s: rejected message (%s): %s", transport.name,
                    exc.reason, exc,
                )  # fmt: skip
            except Exception:  # never let one message end the loop
                self.metrics.drop("internal")
                if self._rlog.warning("ingest-internal", "%s: internal error", transport.name):
                    log.exception("ingest error")

    def _handle(self, transport: Transport, inc: Incoming) -> None:
        msg = decode(
            inc.payload, self.settings.max_points, self.settings.max_message_bytes, _ACCEPTED
        )
        if isinstance(msg, FrameMsg):
            self._on_frame(msg, inc)
        elif isinstance(msg, SubscribeMsg):
            if inc.reply_to is None:
                raise ProtocolError(f"{transport.name}: subscribe is UDP only", "type")
            transport.subscribe(inc.reply_to, msg.stream, msg.token, len(inc.payload))
        else:
            raise ProtocolError(f"{type(msg).__name__} is not accepted by the service", "type")

    def _on_frame(self, msg: FrameMsg, inc: Incoming) -> None:
        if 0 < inc.recv_ns < self._ready_ns and msg.labels is None:
            # (labeled frames are a stream's training window: late, they still train it)
            self.metrics.drop("starting", msg.stream if msg.stream in self.streams else "")
            self._rlog.warning("starting-frames", "unlabeled frames received while the "
                               "service started dropped (stale: it reads frames once it says "
                               "ready)")  # fmt: skip
            return
        if inc.stream is not None and inc.stream != msg.stream:
            self.metrics.drop("stream_mismatch")
            self._rlog.warning("mismatch", "topic stream %s carried stream %s", inc.stream,
                               msg.stream)  # fmt: skip
            return
        source = inc.reply_to if inc.reply_to is not None else inc.transport
        state = self._stream_for(msg, source)
        if state is None:
            self.metrics.drop("unknown_stream")  # one series: stream names are not labels
            self._rlog.warning("unknown", "frame for unknown stream %r dropped", msg.stream)
            return
        now = time.monotonic()
        busier = state.busier_than_sender(source, now, self.settings.silent_after_s)
        if (
            state.sender is not None
            and source != state.sender
            and now - state.sender_at <= self.settings.silent_after_s
            and not busier
        ):
            # another sender's frames while the stream's sender sends (and sends more):
            # dropped before the restart rule sees them (three of them in a row were adopted
            # as a new run, and a burst every 0.5 s took a live stream over: its labels 0.47
            # correct for 6 s)
            self.metrics.drop("second_sender", msg.stream)
            self._stalled(state, msg)
            self._rlog.warning(f"second-{msg.stream}", "stream %s: frames from a second sender "
                               "(%s) dropped while %s sends: one stream takes one sender's "
                               "frames (give each sender its own stream name)", msg.stream,
                               _who(source), _who(state.sender))  # fmt: skip
            return
        verdict = state.check_frame(msg)
        if verdict.reason is not None:
            self.metrics.drop(verdict.reason, msg.stream)
            if verdict.reason in ("seq_jump", "time_jump"):
                last_t = state.continuity.last_t
                self._rlog.warning(f"jump-{msg.stream}", "stream %s: %s at seq %d t %.6g "
                                   "(last accepted seq %s t %.6g): suspect frame dropped",
                                   msg.stream, verdict.reason, msg.seq, msg.t, state.last_seq,
                                   float("nan") if last_t is None else last_t)  # fmt: skip
            if verdict.reason in _CONTINUITY_DROPS:
                self._stalled(state, msg)
            return
        state.stalled_since = None
        if verdict.t is not None:  # a jittered clock's step back: labeled at the run's time
            msg = dataclasses.replace(msg, t=verdict.t, t_sent=msg.t)
        if state.sender is not None and source != state.sender:
            self._rlog.info(f"sender-{msg.stream}", "stream %s: frames now come from %s "
                            "(before: %s)", msg.stream, _who(source),
                            _who(state.sender))  # fmt: skip
        if state.sender_at > 0:
            state.arrival_gaps.append(now - state.sender_at)
        state.sender = source
        state.sender_at = now
        if verdict.gap:
            self.metrics.gap(msg.stream, verdict.gap)
        self.metrics.frame_in(msg.stream)
        if self._queues[msg.stream].put((msg, inc.recv_ns, verdict)) is not None:
            self.metrics.drop("queue_full", msg.stream)
            self._rlog.warning(f"queue-{msg.stream}", "stream %s: falling behind, dropping the "
                               "oldest frame", msg.stream)  # fmt: skip

    def _stalled(self, state: StreamState, msg: FrameMsg) -> None:
        """Frames keep arriving and none continues the stream (each dropped by the continuity
        rule: a sender whose ``t`` is frozen or runs backwards while ``seq`` counts on, whose
        ``seq`` is frozen, or a second sender's frames only). After ``health_window_s`` of such
        arrivals, with no quiet gap that long between them, the status turns ``lost``, the
        labeled fraction 0 (it climbs back through the usual average with the accepted frames
        that follow), and the log says what the frames carry (rate-limited). A stream that
        publishes nothing must not stay ``online``."""
        now = time.monotonic()
        window = self.settings.health_window_s
        if state.stalled_since is None or now - state.stalled_last > window:
            state.stalled_since = now  # (a pause is no stall: the arrivals must go on)
        state.stalled_last = now
        if now - state.stalled_since < window or state.status == "lost":
            return
        last_t = state.continuity.last_t
        if state.last_seq is not None and msg.seq == state.last_seq:
            why = (
                f"their seq ({msg.seq}) does not advance past the last accepted frame's: does "
                "the sender number its frames?"
            )
        elif last_t is not None and msg.t <= last_t:
            why = (
                f"their t ({msg.t:.6g} s) does not advance past the last accepted frame's "
                f"({last_t:.6g} s): is the sender's clock frozen or running backwards?"
            )
        elif (
            state.last_seq is not None
            and last_t is not None
            and msg.seq > state.last_seq
            and (msg.t - last_t) / (msg.seq - state.last_seq) > self.settings.max_time_step_s
        ):
            step = (msg.t - last_t) / (msg.seq - state.last_seq)
            why = (
                f"their seq counts on but t advances {step:.6g} per frame, more than "
                f"max_time_step_s ({self.settings.max_time_step_s:g} s): is t in milliseconds? "
                "Frame times travel in seconds (docs/protocol.md)"
            )
        else:
            why = (
                f"their seq ({msg.seq}) and t ({msg.t:.6g} s) do not continue the last "
                f"accepted frame's (seq {state.last_seq}, t "
                f"{float('nan') if last_t is None else last_t:.6g} s) nor each other: "
                "does the sender number its frames and stamp their times?"
            )
        self._rlog.warning(f"stalled-{state.name}", "stream %s: frames arrive but none "
                           "continued the stream for %.1f s (%s): status lost", state.name,
                           now - state.stalled_since, why)  # fmt: skip
        state.status = "lost"
        state.labeled_fraction = 0.0
        state.recovered_fraction = 0.0
        self.metrics.health(state.name, 0.0, 0.0)
        self._spawn(self._status(state.name, "lost"), f"status-{state.name}-stalled")

    # ------------------------------------------------------------------ workers
    async def _worker(self, state: StreamState) -> None:
        queue = self._queues[state.name]
        loop = asyncio.get_running_loop()
        executor = self._executors.get(state.name)
        while True:
            # yield once per frame: readers drain the sockets into the drop-oldest queues
            # first, so a backlog is dropped (counted) rather than aged in kernel buffers
            await asyncio.sleep(0)
            item = await queue.get_or_wake()
            if item is None:  # woken by a finished boot attempt while no frame waits
                self._install_between(state)
                continue
            msg, recv_ns, verdict = item
            self.metrics.queue(state.name, len(queue))
            n_recoveries = state.recoveries  # a new run or an unlabeled first frame starts one
            try:
                new_run_ns = 0  # (a rebuild or a reboot: counted in the frame's labeling time)
                if verdict.new_run:
                    t0 = time.perf_counter_ns()
                    state.new_run(msg, verdict)
                    new_run_ns = time.perf_counter_ns() - t0
                if state.needs_training(msg):
                    out = await self._train(state, msg, recv_ns)
                elif executor is not None:
                    out = await loop.run_in_executor(
                        executor, state.process, msg, recv_ns, ACCEPT, new_run_ns
                    )
                else:
                    out = state.process(msg, recv_ns, ACCEPT, new_run_ns)
            except BudgetExceeded as exc:
                self.metrics.drop("training_failed", state.name)
                log.warning("stream %s: training failed: %s", state.name, exc)
                self._trim_soon = True  # the failed job's arrays are freed after this block
                state.status = "training_failed"
                await self._status(state.name, "training_failed")
                continue
            except LimitExceeded as exc:
                self.metrics.drop(exc.reason, state.name)
                self._rlog.warning(f"{exc.reason}-{state.name}", "%s", exc)
                continue
            except LabelerError as exc:
                reason = "labeler_error" if state.started else "no_model"
                self.metrics.drop(reason, state.name)
                self._rlog.warning(f"{reason}-{state.name}", "%s", exc)
                if state.started:
                    await self._failing(state, exc)
                continue
            except InitBufferFullError as exc:
                self.metrics.drop("init_overflow", state.name)
                self._rlog.warning(f"init-{state.name}", "%s", exc)
                continue
            except Exception as exc:
                self.metrics.drop("labeler_error", state.name)
                if self._rlog.warning(f"err-{state.name}", "stream %s: labeler failed on seq %d",
                                      state.name, msg.seq):  # fmt: skip
                    log.exception("labeler error")
                await self._failing(state, exc)
                continue
            finally:
                if state.recoveries != n_recoveries:
                    self.metrics.recovery(state.name)
                self._count_handovers(state)
            if out is None:
                continue
            state.failing_since = None
            units = state.units.update(state.name, msg.points, msg.t, out.observed,
                                       getattr(state.labeler, "model", None))  # fmt: skip
            if units is not None:
                self._rlog.warning(f"units-{state.name}", "%s", units)
            rate = state.rate_check.update(state.name, msg.t, state.rate)
            if rate is not None:
                doubt = ""
                if state.stream_settings.rate is None:  # (the model's rate: the model in doubt)
                    doubt = state.units.model_doubt(getattr(state.labeler, "model", None))
                log.warning("%s%s", rate, doubt)
            self._boot_news(state)
            if self._published_model.get(state.name) != state.model_id:
                await self._publish_model(state)
            behind_s = (time.time_ns() - recv_ns) / 1e9
            if behind_s > self.settings.behind_warn_s:
                # (a stream too heavy for its rate, or one that shares the labeling with a
                # heavy one, aged its frames 0.7 s in its queue and said only ``degraded``)
                self._rlog.warning(f"behind-{state.name}", "stream %s: falling behind: a "
                                   "frame published %.0f ms after it arrived (labeling %.1f "
                                   "ms for its %d points; %d frames queued; %d streams share "
                                   "the labeling)", state.name, 1e3 * behind_s,
                                   1e3 * out.label_s, len(msg.points), len(queue),
                                   len(self.streams))  # fmt: skip
            sent_ok = await self._send_all(state.name, "labeled", out.payload)
            if sent_ok:
                self.metrics.frame_out(
                    state.name, out.label_s, out.latency_s, out.observed, out.recovered,
                    out.missing, out.unlabeled,
                )  # fmt: skip
            try:
                await self._health(state, out)
            except Exception:  # a status that cannot be sent must not end the worker
                if self._rlog.warning(f"health-{state.name}", "stream %s: health update failed",
                                      state.name):  # fmt: skip
                    log.exception("health error")
            if state.boot_due():
                await self._start_boot(state, executor)
            if state.handover_due():
                self._start_handover(state)
            if state.spare_due():
                state.spare_building = True
                self._spawn(self._build_spare(state), f"spare-{state.name}")
            if state.recovering or (self._worker_failures and state.booting is not None):
                self._want_worker(state)

    def _want_worker(self, state: StreamState) -> None:
        """Starts the boot worker process in the background (once; the worker restarts itself
        after a kill) for a stream whose recovery has begun on a service that started none
        (its configured streams do not boot: a stream trained from labeled init frames, an
        unconfigured one), and tries a failed start again for any stream that boots. Without
        it the recovery's attempts ran in a thread of the service and held the frame path's
        GIL: 10 x 360 Hz with no labels and ``boot = false``, 693-716 frames dropped against
        0-233 with the worker, 0.50-0.67 correct after boot against 0.93-0.99. Attempts
        requested while it starts (~1.2 s) run in a thread as before (a small recovery's boot
        takes milliseconds there)."""
        w = self.boot_worker
        if w is None or w.enabled or w.closed or self._worker_starting:
            return
        if self._worker_failures and time.monotonic() < self._worker_retry_at:
            return
        self._worker_starting = True
        self._spawn(self._start_worker(w, state), "boot-worker-start")

    async def _start_worker(self, w: BootWorker, state: StreamState) -> None:
        """Starts the worker (once: a no-op after) and sends it the stream's booting labeler's
        model (its booter and the catch-up's kernels, before the first attempt). A worker
        that cannot start or prepare (killed while it started, out of processes) leaves the
        boot attempts in a thread of the service; the start is tried again after
        ``WORKER_RETRY_S`` times the failures, ``WORKER_TRIES`` times in all, then the worker
        is closed. Such a failure used to end the service's start; closed at the first one, a
        single kill during the start left every later boot in the thread (a hostile run)."""
        try:
            await asyncio.to_thread(w.start)
            lab = state.booting or state.spare
            if lab is not None:
                await asyncio.to_thread(w.prepare, lab)
        except Exception as exc:
            if not w.closed:  # (a worker closed by the shutdown while it started: silent)
                self._worker_failures += 1
                n = self._worker_failures
                if n < WORKER_TRIES:
                    self._worker_retry_at = time.monotonic() + WORKER_RETRY_S * n
                    log.warning("boot worker: the process could not start or prepare stream "
                                "%s's booter (%s; try %d of %d); boot attempts run in a thread "
                                "of the service until it starts, tried again in %g s",
                                state.name, exc, n, WORKER_TRIES, WORKER_RETRY_S * n)  # fmt: skip
                    w.reset()
                else:
                    log.exception("boot worker: the process could not start (%d tries); boot "
                                  "attempts run in a thread of the service", n)  # fmt: skip
                    w.close()
        finally:
            self._worker_starting = False

    async def _build_spare(self, state: StreamState) -> None:
        """A model stream's next booting labeler (for a recovery, or a reboot after a time
        jump), built in a thread (:meth:`StreamState.build_spare`); a failure is logged and
        not tried again (every later one is built in the frame, as before)."""
        try:
            await asyncio.to_thread(state.build_spare)
        except Exception:
            state._spare_for = None
            log.exception("stream %s: building the next booting labeler failed (recoveries "
                          "and reboots build theirs in the frame from now on)",
                          state.name)  # fmt: skip
        finally:
            state.spare_building = False

    # ------------------------------------------------------------------ handover
    def _start_handover(self, state: StreamState) -> None:
        """Runs the window start's handover job (:meth:`StreamState.handover_job`: the window
        model, its labeler, the catch-up) off the loop (task ``handover-<stream>``)."""
        h = state.handover
        assert h is not None
        h.inflight = True
        h.again = False
        self._spawn(self._handover(state, h), f"handover-{state.name}")

    async def _handover(self, state: StreamState, h) -> None:
        """One handover job through :class:`Background` (budget ``train_budget_s``); the next
        frame of the stream installs its window labeler (or sends it back for another round);
        a failure or the budget abandons the handover (the plain labeler stays)."""
        t0 = time.perf_counter()
        fed = jobs = 0
        try:
            if h.labeler is None and h.model is None and state.window_in_process:
                h.model = await self._window_model(state, h)
            while True:
                fed += await self.background.run(
                    state.handover_job, h, budget_s=self.settings.train_budget_s,
                    name=f"handover-{state.name}", priority=_priority(state),
                )  # fmt: skip
                jobs += 1
                if not h.more or h.abandoned:
                    break
                # a time slice ended behind the stream: other streams' waiting jobs first
                await asyncio.sleep(YIELD_S)
        except asyncio.CancelledError:
            state.handover_done(h, False, "the service stops")
            raise
        except Exception as exc:
            if not h.abandoned:
                log.warning("stream %s: the window start's handover failed: %s: %s",
                            state.name, type(exc).__name__, exc)  # fmt: skip
            state.handover_done(h, False, f"{type(exc).__name__}: {exc}")
            self._count_handovers(state)
            self._trim_soon = True
            return
        log.info("stream %s: the window start's catch-up caught up after %.2f s (%d jobs, %d "
                 "frames fed)", state.name, time.perf_counter() - t0, jobs, fed)  # fmt: skip
        state.handover_done(h, not h.abandoned, "abandoned")
        self._count_handovers(state)

    def _count_handovers(self, state: StreamState) -> None:
        self.metrics.handover_totals(state.name, state.handovers, state.handovers_abandoned)

    async def _window_model(self, state: StreamState, h):
        """The window model in its child process (:meth:`StreamState.window_model`), outside
        the ``Background`` slot (the child needs none of our GIL: other streams' trainings and
        boots run meanwhile), within ``train_budget_s``; over it the child is terminated."""
        cancel = threading.Event()
        budget = self.settings.train_budget_s
        try:
            return await asyncio.wait_for(
                asyncio.to_thread(state.window_model, h, cancel), timeout=budget
            )
        except TimeoutError:
            raise BudgetExceeded(
                f"window-model-{state.name}: over its budget of {budget:g} s, abandoned"
            ) from None
        finally:
            cancel.set()  # (ended: a no-op; over budget or the service stops: the child ends)

    # ------------------------------------------------------------------ boot
    async def _start_boot(self, state: StreamState, executor: ThreadPoolExecutor | None) -> None:
        """Takes a due attempt's snapshot in the frame thread and runs the attempt off the loop
        (task ``boot-<stream>``); the next frame installs its result."""
        try:
            if executor is not None:
                loop = asyncio.get_running_loop()
                req = await loop.run_in_executor(executor, state.boot_request)
            else:
                req = state.boot_request()
        except Exception:
            state.boot_inflight = False
            self.metrics.boot_failed(state.name)
            if self._rlog.warning(f"boot-{state.name}", "stream %s: boot snapshot failed",
                                  state.name):  # fmt: skip
                log.exception("boot snapshot error")
            return
        if req is not None:
            self._spawn(self._boot(state, req), f"boot-{state.name}")

    async def _boot(self, state: StreamState, req) -> None:
        """One boot attempt (or extension of the booted subjects to markers not seen yet)
        through :class:`Background` (budget ``boot_budget_s``)."""
        if req.snapshot.subjects:  # an extension alone is not a boot attempt
            self.metrics.boot_attempt(state.name)
        budget = self.settings.boot_budget_s
        try:
            # its turn comes after the jobs that asked first, one per stream at most, each
            # bounded by its budget: waiting for them is no failure of this stream's boot
            outcome = await self.background.run(
                state.boot_job, req, budget_s=budget, name=f"boot-{state.name}",
                wait_s=budget * max(1, len(self.streams)), priority=_priority(state),
            )  # fmt: skip
        except BudgetExceeded as exc:
            self.metrics.boot_failed(state.name)
            self._rlog.warning(f"boot-{state.name}", "stream %s: boot attempt abandoned: %s",
                               state.name, exc)  # fmt: skip
            self._boot_done(state, req, None)
            return
        except asyncio.CancelledError:
            state.boot_done(req, None)
            raise
        except LabelerError as exc:  # ours, e.g. the worker died (the next attempt restarts it)
            self.metrics.boot_failed(state.name)
            self._rlog.warning(f"boot-{state.name}", "stream %s: boot attempt failed: %s",
                               state.name, exc)  # fmt: skip
            self._boot_done(state, req, None)
            return
        except Exception:
            self.metrics.boot_failed(state.name)
            if self._rlog.warning(f"boot-{state.name}", "stream %s: boot attempt failed",
                                  state.name):  # fmt: skip
                log.exception("boot error")
            self._boot_done(state, req, None)
            return
        if req.snapshot.subjects:
            self.metrics.boot_seconds(state.name, outcome.seconds)
        self._boot_done(state, req, outcome)

    def _boot_done(self, state: StreamState, req, outcome) -> None:
        """Hands an attempt's outcome (None: abandoned or failed) to the stream and wakes its
        worker, which installs it between frames (:meth:`_install_between`) unless a frame
        is already waiting (that frame installs it)."""
        state.boot_done(req, outcome)
        queue = self._queues.get(state.name)
        if state.install_due and queue is not None:
            queue.wake()

    def _install_between(self, state: StreamState) -> None:
        """Installs a finished attempt's result between frames, in the stream's worker while
        no frame waits (:meth:`StreamState.install_pending`): the next frame's labeling does
        not carry it. Only when frames are labeled on the loop: with ``labeling_thread`` the
        next frame installs it in its thread."""
        if state.name in self._executors:
            return
        try:
            seconds = state.install_pending()
        except Exception:  # as a frame's labeler error: logged, the stream goes on
            self.metrics.drop("labeler_error", state.name)
            if self._rlog.warning(f"err-{state.name}", "stream %s: boot install failed",
                                  state.name):  # fmt: skip
                log.exception("boot install error")
            return
        if seconds is None:
            return
        self.metrics.boot_install(state.name, seconds)
        self._boot_news(state)

    def _boot_news(self, state: StreamState) -> None:
        """What a frame or an install between frames changed in a booting stream: subjects
        booted (log, metrics), the active count, the re-verification's withdrawals."""
        if state.just_booted:
            self._booted(state)
        elif state.booting is not None:
            self.metrics.subjects(state.name, state.booting.n_active)
        if state.verify_events:
            self._verified(state)

    @staticmethod
    def _lost_reboots(state: StreamState) -> None:
        """``on_lost`` of a booting model stream: its labeler has dropped the subjects that
        vanished (their labels go to nobody) and boots each again as soon as it is seen."""
        log.warning("stream %s: lost; re-booting from the model (still labeled: %s)",
                    state.name, ", ".join(state.subjects_booted) or "none")  # fmt: skip

    def _booted(self, state: StreamState) -> None:
        """Logs and counts subjects the last frame installed from a boot."""
        active = state.subjects_booted
        self.metrics.subjects(state.name, len(active))
        rec = state.boots[-1] if state.boots else None
        # (where it ran, not the setting: a worker that could not start leaves them in a thread)
        where = "the boot worker process" if rec is not None and rec.worker else "a thread"
        log.info("stream %s: booted %s (attempt %.3f s, job %s in %s, caught up over %s); "
                 "labeling %d of %s", state.name, ", ".join(state.just_booted),
                 rec.seconds if rec else float("nan"), rec.thread if rec else "?", where,
                 plural(rec.caught_frames if rec else 0, "frame"), len(active),
                 plural(len(state.booting.model.subjects) if state.booting else 0,
                        "subject"))  # fmt: skip

    def _verified(self, state: StreamState) -> None:
        """Counts and logs (rate-limited, per stream) the booted subjects whose labels the
        last frame withdrew (re-verification) or dropped (rejected, or vanished)."""
        for kind, _ in state.verify_events:
            self.metrics.verify_event(state.name, kind)
        parts = [
            f"{what} {', '.join(sorted({n for k, n in state.verify_events if k == kind}))}"
            for kind, what in (
                ("withdraw", "re-verification withdrew labels of"),
                ("reject", "re-verification dropped (boots again)"),
                ("drop", "dropped as vanished (boots again when seen)"),
                ("jump", "dropped: the scene jumped past their tracks (boots again)"),
                ("blackout", "dropped after a camera dropout past blackout_reboot_s (boots again)"),
                ("exchange", "re-verification exchanged left and right markers of"),
            )
            if any(k == kind for k, _ in state.verify_events)
        ]
        self._rlog.info(f"verify-{state.name}", "stream %s: %s", state.name, "; ".join(parts))
        if state.booting is not None:
            self.metrics.subjects(state.name, state.booting.n_active)

    async def _train(self, state: StreamState, msg: FrameMsg, recv_ns: int):
        """Trains the stream's labeler off the loop (budget ``train_budget_s``); a failure
        (over budget, or the training raised) is reported as ``training_failed``."""
        init = state.take_init()
        cfg = self.settings.labeler_config
        if (
            self.settings.labeler == "online"
            and cfg.restructure_s > 0
            and len(init.frames) < cfg.restructure_max_train_frames
        ):
            log.warning("stream %s: %s: the labeler re-forms this thin "
                        "structure from the stream every %.1f s, in the frame path (tens of ms "
                        "when it changes); send %d or more init frames at high rates",
                        state.name, plural(len(init.frames), "labeled init frame"),
                        cfg.restructure_s,
                        cfg.restructure_max_train_frames)  # fmt: skip
        self.metrics.training.inc()
        state.training = True
        try:
            labeler, rate, out, label_ns, handover = await self.background.run(
                state.train_staged, init, msg, budget_s=self.settings.train_budget_s,
                name=f"train-{state.name}", priority=_priority(state),
            )  # fmt: skip
        except BudgetExceeded:
            raise
        except Exception as exc:
            raise BudgetExceeded(f"{type(exc).__name__}: {exc}") from exc
        finally:
            self.metrics.training.dec()
            state.training = False
            state.last_activity = time.monotonic()
        output = state.install_trained(labeler, rate, msg, out, recv_ns, label_ns, handover)
        if state.handover_due():
            self._start_handover(state)
        if state.status != "online":
            state.status = "online"
            await self._status(state.name, "online")
        return output

    async def _failing(self, state: StreamState, exc: BaseException) -> None:
        """A frame of a started stream failed (``labeler_error``). When every frame has failed
        for ``health_window_s`` the status turns ``lost`` (logged once with the last error): a
        stream that publishes nothing must not stay ``online``. The next labeled frame's health
        update gives the status back."""
        now = time.monotonic()
        if state.failing_since is None:
            state.failing_since = now
        if now - state.failing_since < self.settings.health_window_s or state.status == "lost":
            return
        state.status = "lost"
        log.warning("stream %s: no frame labeled for %.1f s, each one failed (last: %s: %s): "
                    "status lost", state.name, now - state.failing_since, type(exc).__name__,
                    exc)  # fmt: skip
        await self._status(state.name, "lost")

    async def _health(self, state: StreamState, out) -> None:
        changed = state.update_health(out)
        self.metrics.health(state.name, state.labeled_fraction, state.recovered_fraction)
        if changed is None:
            return
        level = logging.INFO if changed in ("online", "booting") else logging.WARNING
        log.log(level, "stream %s: status %s (labeled fraction %.2f, recovered %.2f)",
                state.name, changed, state.labeled_fraction, state.recovered_fraction)  # fmt: skip
        await self._status(state.name, changed)
        if changed == "lost":
            try:
                if state.on_lost is not None:
                    state.on_lost(state)
                elif state.start_recovery("lost"):
                    self.metrics.recovery(state.name)
            except Exception:
                log.exception("stream %s: recovery after lost failed", state.name)

    async def _send_all(self, stream: str, kind: str, payload: bytes, retain: bool = False) -> bool:
        ok = False
        assert self.transports is not None
        for t in self.transports:
            try:
                await t.send(stream, kind, payload, retain)
                ok = True
            except ProtocolError as exc:
                self.metrics.drop("output_oversize", stream)
                self._rlog.warning(f"oversize-{stream}", "%s", exc)
            except Exception as exc:
                self.metrics.drop("send_error", stream)
                self._rlog.warning(f"send-{t.name}", "%s: send failed: %s", t.name, exc)
        return ok

    async def _publish_model(self, state: StreamState) -> None:
        if state.model_payload is None:
            return
        self._published_model[state.name] = state.model_id
        await self._send_all(state.name, "model", state.model_payload, retain=True)

    async def _status(self, stream: str, status: str) -> None:
        await self._send_all(stream, "status", encode_status(stream, status), retain=True)

    async def _model_repeat(self) -> None:
        """Re-sends every model message once per ``model_repeat_s`` (late UDP subscribers)."""
        while True:
            await asyncio.sleep(self.settings.model_repeat_s)
            for state in list(self.streams.values()):
                if state.model_payload is not None:
                    await self._publish_model(state)

    def _count_transport_drops(self) -> None:
        """Adds what each transport dropped since the last call to ``mocap_dropped_total``."""
        for t in self.transports or ():
            for (stream, reason), n in t.drop_counts().items():
                key = (t.name, stream, reason)
                delta = n - self._transport_drops.get(key, 0)
                if delta > 0:
                    self._transport_drops[key] = n
                    self.metrics.drop(reason, stream, delta)

    async def _transport_drops_loop(self) -> None:
        abandoned = 0
        while True:
            await asyncio.sleep(1.0)
            self._count_transport_drops()
            self._transport_health()
            self.metrics.background_threads.set(self.background.running)
            if self.background.abandoned_ended > abandoned:
                # an abandoned job ended (its state is freed only now); a job that ended in time
                # frees its state by reference counting and needs no collection
                abandoned = self.background.abandoned_ended
                self._trim_soon = True
            if self._trim_soon:
                # after a failed training (cycles: exception <-> frames) or a removed stream: a
                # full collection also empties the interpreter's free lists, whose few objects
                # otherwise pin whole 1 MiB object arenas that a flood of labeled frames (2,000
                # label strings each) spread over (measured: 500 -> 250 MB after init_buffer);
                # ~60 ms with the start-up objects frozen, only after such events
                self._trim_soon = False
                gc.collect()
            # what was freed since (a drained receive backlog, removed streams, finished jobs)
            # goes back to the OS: ~10 us when there is nothing to return, tens of ms after a
            # large free, hence in a thread (ctypes releases the GIL)
            await asyncio.to_thread(release_memory)

    def _log_streams(self) -> dict[str, tuple[str, int]]:
        """Per stream its status and, when it boots, its model's subject count (log line)."""
        out = {}
        for name, st in self.streams.items():
            lab = st.booting
            out[name] = (st.status, len(lab.model.subjects) if lab is not None else 0)
        return out

    def _transport_health(self, log_all: bool = False) -> None:
        """Sets ``mocap_transport_up`` per transport; logs each transport that is down (every
        call with ``log_all``, else when it goes down) and each that comes back."""
        for t in self.transports or ():
            trouble = t.trouble()
            self.metrics.transport_up.labels(transport=t.name).set(trouble is None)
            was = self._transport_down.get(t.name)
            if trouble is not None and (log_all or was is None):
                log.warning("%s: %s; frames do not flow through it until then", t.name,
                            trouble)  # fmt: skip
            elif trouble is None and was is not None:
                log.info("%s: carries frames again", t.name)
            self._transport_down[t.name] = trouble

    async def _log_loop(self) -> None:
        while True:
            await asyncio.sleep(self.settings.log_interval_s)
            log.info("%s", self.metrics.log_line(self._log_streams()))
            self._transport_health(log_all=True)


#: drops by the continuity rule (service/continuity.py): frames that continue nothing
_CONTINUITY_DROPS = ("seq_jump", "time_jump", "duplicate", "late")


def _priority(state: StreamState) -> int:
    """A stream's class for the background slots (:class:`Background`, lower first): the
    configured streams' jobs (the volumes the operator declared) before those of streams any
    sender opens by name. Bursts of labeled frames to two new names queued their trainings
    ahead of a configured stream's re-identification: 18 s, and with six bursts 54 s twice."""
    return 0 if state.configured else 1


def _who(source: object) -> str:
    """A frame's sender for the log: ``host:port`` for UDP, else the transport's name."""
    if isinstance(source, tuple) and len(source) >= 2:
        return f"{source[0]}:{source[1]}"
    return str(getattr(source, "name", source))
