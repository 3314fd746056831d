"""Boot attempts in a worker process: the frame path keeps its interpreter's GIL.

A boot attempt (:meth:`~labeler_service.labeling.booting.BootingLabeler.boot_step`) is about
two thirds Python and numpy between its numba kernels (profile, 10 hugging performers at
360 Hz: of a 1.7-5.7 s attempt, 36 % in the node-graph kernel, which releases the GIL, the
rest candidate search, hypotheses and readings in Python; the graph's rows are now computed on
demand, ~1.1-1.25 s of CPU per attempt, most of it Python). Run in a thread of the service it
holds the GIL most of the time, and the event loop's frames wait for it at every hand-back:
labeling p50 0.5 -> 2.3 ms per frame while an attempt ran. Here the step runs in one worker
process instead::

    worker = BootWorker()
    worker.start()                       # spawn + kernel warm-up (a few s; at service start)
    worker.prepare(labeler)              # its booter and the shadow's kernels (at service start)
    result = labeler.boot_step(snap, worker.runner(labeler, cancel))   # in a Background job
    worker.close()

The worker is a ``spawn`` child (the service has threads; ``fork`` would copy their locks)
with a lower CPU priority (``os.nice(NICE)``, 5: on a busy machine the frame path wins the core;
at 10 the boot itself starved on a machine shared with other jobs).
It keeps a :class:`~labeler_service.labeling.boot.Booter` per labeler (``labeler.key``; the
model is sent once, ~0.5 MB for 10 subjects, and the booter is prepared once, ~0.3 s of CPU:
the service does both at start with :meth:`BootWorker.prepare`, which also warms the inner
labeler's kernels a catch-up's shadow runs, so the first attempt pays neither); a snapshot is
~0.3 MB (500 points, a 24-frame history).

With ``helpers=1`` (``HELPERS``, off by default: measured slower on the shared machine) the
worker has a *helper* process: an attempt's hypotheses are computed per subject template, each
a pure function of the template and the points (~85 % of a 10-performer attempt's CPU), so
the worker and the helper take the subjects from one shared counter (the next one nobody has
taken) and the worker then resolves them together as alone (the same labels). A helper that
dies leaves the worker alone (it does the subjects itself); a killed worker takes its helper
with it. One request at a time (a lock): the
service runs one background job at a time anyway. A request whose job is abandoned
(``cancel`` set: over ``boot_budget_s``, or shutdown) kills the worker, so no stale attempt
keeps the CPU; the next request starts a new one. A worker that dies raises
:class:`~labeler_service.errors.LabelerError` for that request and is restarted on the next.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import traceback
from collections import OrderedDict
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from labeler_service.errors import BudgetExceeded, LabelerError

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from labeler_service.labeling.booting import BootingLabeler, BootSnapshot, StepRunner

#: ``os.nice`` increment of the worker (lower priority than the frame path).
NICE = 5
#: Booters (one per labeler) a worker keeps, least recently used dropped first.
MAX_BOOTERS = 8
#: Helper processes of the worker (0 or 1): an attempt's subjects are shared between the two
#: (each takes the next subject nobody has taken; labels as computed alone). Off: on the shared
#: 2-core machine (load 4-5, autogroup scheduling: a session's processes share one slice) the
#: first attempt took longer with it (``benchmarks/boot_worker_step.py``: median 1.41 -> 2.07
#: s); on a quiet one 0.63 -> 0.39 s, but beside a 10 x 360 Hz stream on the same 2 cores the
#: service's attempt gained nothing. The service's setting is ``boot_helpers``.
HELPERS = 0
#: How often a waiting request looks at its cancel event and the worker's health (s).
POLL_S = 0.02


def start_child(proc: multiprocessing.process.BaseProcess) -> None:
    """Starts a ``spawn`` child with SIGINT blocked in it, as CPython's resource tracker is
    started: Ctrl-C in a terminal goes to the whole foreground process group, and a child
    still importing (the boot worker, a window model's process) printed a KeyboardInterrupt
    traceback, or died mid-attempt (``boot worker: lost``) while the service shut down
    cleanly. The service ends its children itself (terminate, kill). The mask is the calling
    thread's, restored at once; a SIGINT meanwhile is delivered to the service after it."""
    if not hasattr(signal, "pthread_sigmask"):
        proc.start()
        return
    from multiprocessing import resource_tracker

    # start() launches the resource tracker the first time, which ends by *unblocking* SIGINT
    # in the calling thread (resource_tracker._launch): launched first, it leaves our mask be
    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _Session:
    """One catch-up in the worker (see :meth:`BootWorker.catch_up`)."""

    def __init__(
        self, worker: BootWorker, labeler: BootingLabeler, cancel: threading.Event | None
    ) -> None:
        self.worker, self.labeler, self.cancel = worker, labeler, cancel
        self._held = False

    def begin(self, shadow: BootingLabeler, snapshot: BootSnapshot, result: Any):
        w, lab = self.worker, self.labeler
        w._lock.acquire()
        self._held = True
        try:
            conn, spec = w._spec_for(lab.key, lab.boot_spec)
            msg = ("catch", lab.key, spec, shadow.for_transfer(), snapshot, result)
            booted = w._request(msg, self.cancel, "catch-up", conn)
            w._note(lab.key)
        except BaseException:
            self._release()
            raise
        if booted is None:
            self._release()
        return booted

    def frames(self, batch: list) -> None:
        try:
            self.worker._request(("frames", batch), self.cancel, "catch-up")
        except BaseException:
            self._release()
            raise

    def extend(self) -> None:
        try:
            self.worker._request(("extend",), self.cancel, "catch-up")
        except BaseException:
            self._release()
            raise

    def finish(self) -> BootingLabeler:
        try:
            return self.worker._request(("finish",), self.cancel, "catch-up")
        finally:
            self._release()

    def abort(self) -> None:
        """The catch-up will not finish (its job was abandoned): the worker, holding its
        shadow, is stopped, and the next request starts a new one."""
        if self._held:
            self.worker._kill()
            self._release()

    def _release(self) -> None:
        if self._held:
            self._held = False
            self.worker._lock.release()


class _Booters:
    """A worker process's booters by labeler key, least recently used dropped first."""

    def __init__(self) -> None:
        self._booters: OrderedDict[str, Any] = OrderedDict()

    def get(self, key: str, spec) -> Any:
        from labeler_service.labeling.boot import Booter

        booter = self._booters.get(key)
        if booter is None:
            if spec is None:
                raise LabelerError(f"boot worker: no model for labeler {key}")
            booter = self._booters[key] = Booter(*spec)
            while len(self._booters) > MAX_BOOTERS:
                self._booters.popitem(last=False)
        self._booters.move_to_end(key)
        return booter


def _grab(counter: Any, n: int) -> int:
    """The next subject (index into the attempt's list) nobody has taken yet, -1: none left."""
    with counter.get_lock():
        k = int(counter.value)
        if k >= n:
            return -1
        counter.value = k + 1
        return k


def _help(conn: Connection, counter: Any, nice: int) -> None:  # pragma: no cover - child
    """The helper's loop (see :class:`BootWorker`), requests from the worker: ``("ping",)``;
    ``("prepare", key, model_and_config)``; ``("hyps", key, model_and_config_or_None, subjects,
    pts, hist)`` -> ``{k: hypotheses of subjects[k]}`` for the subjects it took from the shared
    counter. Answers ``(True, value)`` or ``(False, traceback text)``."""
    with contextlib.suppress(OSError):
        os.nice(nice)
    from labeler_service.labeling.boot import warmup_kernels

    warmup_kernels()
    booters = _Booters()

    def handle(msg: tuple) -> Any:
        kind = msg[0]
        if kind == "ping":
            return None
        if kind == "prepare":
            booters.get(msg[1], msg[2])
            return None
        if kind == "hyps":
            _, key, spec, wanted, pts, hist = msg
            booter = booters.get(key, spec)
            pairs = booter.pairs(pts)
            out = {}
            while (k := _grab(counter, len(wanted))) >= 0:
                out[k] = booter.hypotheses(wanted[k], pts, hist, pairs)
            return out
        raise LabelerError(f"boot helper: unknown request {kind!r}")

    _answer(conn, handle)


def _answer(conn: Connection, handle: Any, failed: Any = None) -> None:  # pragma: no cover
    """A child's request loop (the worker's and its helper's): each request is answered
    ``(True, handle(request))``, or ``(False, traceback text)`` when that raises (``failed()``
    runs first); returns when the pipe closes, also while answering (the service killed during
    an attempt: the orphan printed a BrokenPipeError traceback into its log)."""
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        try:
            reply = (True, handle(msg))
        except Exception:
            if failed is not None:
                failed()
            reply = (False, traceback.format_exc())
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return
        except Exception:  # (an answer that does not pickle)
            if failed is not None:
                failed()
            conn.send((False, traceback.format_exc()))


class _Helper:
    """The worker's side of its helper: shares an attempt's subjects with it (a
    :data:`~labeler_service.labeling.boot.HypothesesShare`)."""

    def __init__(self, conn: Connection | None, counter: Any) -> None:
        self.conn, self.counter = conn, counter
        self._known: OrderedDict[str, None] = OrderedDict()  # mirror of its booters' LRU

    def request(self, msg: tuple) -> Any:
        assert self.conn is not None
        self.conn.send(msg)
        ok, value = self.conn.recv()
        if not ok:
            raise LabelerError(f"boot helper failed:\n{value}")
        return value

    def note(self, key: str) -> None:
        self._known[key] = None
        self._known.move_to_end(key)
        while len(self._known) > MAX_BOOTERS:
            self._known.popitem(last=False)

    def share(self, key: str):
        def run(booter, wanted: list[int], pts, hist, pairs) -> list:
            if self.conn is None or len(wanted) < 2:
                return [h for s in wanted for h in booter.hypotheses(s, pts, hist, pairs)]
            with self.counter.get_lock():
                self.counter.value = 0
            spec = None if key in self._known else (booter.model, booter.config)
            try:
                self.conn.send(("hyps", key, spec, wanted, pts, hist))
            except (OSError, ValueError) as exc:
                # (gone, killed from outside: the worker goes on alone; said once, it was not)
                log.warning("boot helper gone (%s); the worker does every subject itself", exc)
                self.conn = None
                return run(booter, wanted, pts, hist, pairs)
            self.note(key)
            mine = {}
            while (k := _grab(self.counter, len(wanted))) >= 0:
                mine[k] = booter.hypotheses(wanted[k], pts, hist, pairs)
            try:
                ok, theirs = self.conn.recv()
            except (EOFError, OSError):
                ok, theirs = False, "lost"
            if not ok:
                log.warning("boot helper failed; its subjects are done here:\n%s", theirs)
                self.conn = None
                theirs = {k: booter.hypotheses(wanted[k], pts, hist, pairs)
                          for k in range(len(wanted)) if k not in mine}  # fmt: skip
            both = {**mine, **theirs}
            return [h for k in range(len(wanted)) for h in both[k]]

        return run


def _serve(
    conn: Connection, nice: int, peer: Connection | None = None, counter: Any = None
) -> None:  # pragma: no cover - runs in the child
    """The worker's loop, one request at a time, each answered ``(True, value)`` or
    ``(False, traceback text)``: ``("ping",)`` -> None once the kernels are warm (the helper's
    too); ``("step", key, model_and_config_or_None, snapshot)`` -> ``(result, extended, ms)``
    (the subjects' hypotheses shared with the helper, ``peer``, through ``counter``); a
    catch-up: ``("catch", key, model_and_config_or_None, shadow, snapshot, result)`` -> the
    subjects booted (the shadow stays here), ``("frames", batch)`` labels a batch on it,
    ``("extend",)`` extends its subjects (the catch-up's last extension), ``("finish",)`` ->
    the shadow (for transfer); ``("prepare", key, model_and_config, rate, labeler_config)``
    builds the booter of ``key`` (the helper's too) and warms the kernels a shadow's frames
    run (before the first attempt)."""
    with contextlib.suppress(OSError):
        os.nice(nice)
    from labeler_service.labeling.boot import warmup_kernels
    from labeler_service.labeling.booting import boot_step_on, warmup_labeler

    warmup_kernels()
    booters = _Booters()
    helper = _Helper(peer, counter)
    shadow: Any = None  # the catch-up in progress

    def handle(msg: tuple) -> Any:
        nonlocal shadow
        kind = msg[0]
        if kind == "ping":
            if helper.conn is not None:
                helper.request(("ping",))
            return None
        if kind == "prepare":
            _, key, spec, rate, config = msg
            booters.get(key, spec)
            if helper.conn is not None:
                helper.request(("prepare", key, spec))
                helper.note(key)
            warmup_labeler(rate, config)
            return None
        if kind == "step":
            _, key, spec, snapshot = msg
            return boot_step_on(booters.get(key, spec), snapshot, helper.share(key))
        if kind == "catch":
            _, key, spec, shadow, snapshot, result = msg
            booter = booters.get(key, spec)
            shadow._booter, shadow.boot_model = booter, booter.model
            if shadow.model is None:  # (sent only when a relearn made it another model)
                shadow.model = booter.model
            return shadow._begin_catch_up(snapshot, result)
        if kind == "frames":
            shadow._catch_up_frames(msg[1])
            return None
        if kind == "extend":
            shadow._catch_up_extend()
            return None
        if kind == "finish":
            out, shadow = shadow.for_transfer(), None
            return out
        raise LabelerError(f"boot worker: unknown request {kind!r}")

    def failed() -> None:
        nonlocal shadow
        shadow = None

    _answer(conn, handle, failed)


class BootWorker:
    """One boot worker process (see the module docstring). Thread-safe."""

    def __init__(self, nice: int = NICE, helpers: int = HELPERS) -> None:
        self.nice = nice
        #: 1: an attempt shares its subjects' hypotheses with a helper process; 0: none
        self.helpers = int(helpers)
        self._lock = threading.Lock()
        self._proc: Any = None
        self._helper: Any = None
        self._counter: Any = None
        self._conn: Connection | None = None
        #: labeler keys whose booter the worker has, in the worker's LRU order
        self._known: OrderedDict[str, None] = OrderedDict()
        self._closed = False
        #: worker processes started so far (restarts after a kill or a crash included)
        self.started = 0
        self._warm = False  # a worker has answered once (start() or any request)

    @property
    def pid(self) -> int | None:
        """The worker's process id (None when none runs)."""
        proc = self._proc
        return proc.pid if proc is not None and proc.is_alive() else None

    def start(self) -> None:
        """Starts the worker and waits until its kernels are warm (blocking: call it off the
        event loop, e.g. with ``asyncio.to_thread``)."""
        with self._lock:
            self._request(("ping",), None, "warm-up")

    def prepare(self, labeler: BootingLabeler) -> None:
        """Sends ``labeler``'s model to the worker, which prepares its booter and warms the
        kernels a catch-up's shadow runs (the inner labeler's), so that the first attempt pays
        neither (blocking, like :meth:`start`; a no-op for a labeler the worker knows)."""
        with self._lock:
            conn, spec = self._spec_for(labeler.key, labeler.boot_spec)
            if spec is None:
                return
            self._request(("prepare", labeler.key, spec, labeler.rate, labeler.config), None,
                          "preparation", conn)  # fmt: skip
            self._note(labeler.key)

    def runner(self, labeler: BootingLabeler, cancel: threading.Event | None = None) -> StepRunner:
        """The ``runner`` for ``labeler.boot_step`` (see the module docstring)."""
        spec = labeler.boot_spec

        def run(snapshot: BootSnapshot):
            return self.step(labeler.key, spec, snapshot, cancel)

        return run

    def catch_up(self, labeler: BootingLabeler, cancel: threading.Event | None = None) -> _Session:
        """A ``remote`` for ``labeler.catch_up`` (:class:`CatchUpRemote`): the shadow's frames
        run in the worker; the worker is held (no other request) until ``finish``, an error or
        ``cancel``."""
        return _Session(self, labeler, cancel)

    def step(
        self,
        key: str,
        spec: tuple[Any, Any],
        snapshot: BootSnapshot,
        cancel: threading.Event | None = None,
    ) -> Any:
        """:func:`~labeler_service.labeling.booting.boot_step_on` in the worker with the booter
        of ``key`` (built from ``spec`` = ``(model, BootConfig)`` the first time)."""
        with self._lock:
            conn, sent = self._spec_for(key, spec)
            out = self._request(("step", key, sent, snapshot), cancel, "boot step", conn)
            self._note(key)
            return out

    def reset(self) -> None:
        """Ends the worker process, if any, without closing: the next request starts one."""
        self._kill()

    def close(self) -> None:
        """Stops the worker (a running attempt is killed); later requests are refused."""
        self._closed = True
        self._kill()

    @property
    def closed(self) -> bool:
        """Closed (:meth:`close`): requests are refused."""
        return self._closed

    @property
    def enabled(self) -> bool:
        """Started and warm once, and not closed: requests go to the worker (a killed or
        crashed one is started again by the next request). Not while the first one starts: a
        request then would wait for its start-up."""
        return self._warm and not self._closed

    # ------------------------------------------------------------------ internals
    def _spec_for(self, key: str, spec: Any) -> tuple[Connection, Any]:
        """The worker's connection and ``spec`` when the worker lacks ``key``'s booter, else
        None (the caller holds the lock and sends its request on that connection). A worker
        that died is started again first: the new one knows no booter (the mirror was read
        before the restart, so the first attempt after a killed worker went without its model
        and failed: "no model for labeler ...")."""
        conn = self._ensure()
        return conn, None if key in self._known else spec

    def _note(self, key: str) -> None:
        """``key``'s booter is in the worker now, most recently used; the worker drops the
        least recently used beyond ``MAX_BOOTERS`` and so does this mirror (a dropped key is
        sent its model again)."""
        self._known[key] = None
        self._known.move_to_end(key)
        while len(self._known) > MAX_BOOTERS:
            self._known.popitem(last=False)

    def _request(
        self,
        msg: tuple,
        cancel: threading.Event | None,
        what: str,
        conn: Connection | None = None,
    ) -> Any:
        """One request-reply (the caller holds the lock), on ``conn`` when given (the worker
        the message was made for: one started since would lack what it assumes)."""
        if conn is None:
            conn = self._ensure()
        conn.send(msg)
        out = self._reply(conn, cancel, what)
        self._warm = True
        return out

    def _ensure(self) -> Connection:
        if self._closed:
            raise LabelerError("boot worker: closed")
        if self._proc is None or not self._proc.is_alive() or self._conn is None:
            old = self._proc
            if old is not None and not old.is_alive():
                # not ended by us (_kill forgets the process first): killed (OOM) or crashed
                log.warning("boot worker process %d had exited (exit code %s); starting a new "
                            "one", old.pid, old.exitcode)  # fmt: skip
            self._kill()
            ctx = multiprocessing.get_context("spawn")
            parent, child = ctx.Pipe()
            peer = helper = counter = None
            if self.helpers > 0:
                counter = ctx.Value("i", 0)
                peer, theirs = ctx.Pipe()
                helper = ctx.Process(target=_help, args=(theirs, counter, self.nice),
                                     name="boot-helper", daemon=True)  # fmt: skip
                start_child(helper)
                theirs.close()
            proc = ctx.Process(target=_serve, args=(child, self.nice, peer, counter),
                               name="boot-worker", daemon=True)  # fmt: skip
            start_child(proc)
            child.close()
            if peer is not None:
                peer.close()  # (the worker's now: the helper ends when the worker does)
            self._proc, self._conn, self._known = proc, parent, OrderedDict()
            # (kept: the children open its semaphore by name, unlinked when it is collected)
            self._helper, self._counter = helper, counter
            self.started += 1
            if self._closed:  # closed while it started (close takes no lock)
                self._kill()
                raise LabelerError("boot worker: closed")
        return self._conn

    def _reply(self, conn: Connection, cancel: threading.Event | None, what: str) -> Any:
        while True:
            try:
                ready = conn.poll(POLL_S)
            except (EOFError, OSError) as exc:
                self._kill()
                raise LabelerError(f"boot worker: lost during the {what}") from exc
            if ready:
                break
            if cancel is not None and cancel.is_set():
                self._kill()  # an abandoned attempt must not keep the CPU
                raise BudgetExceeded(f"boot worker: {what} abandoned")
            if self._proc is None or not self._proc.is_alive():
                self._kill()
                raise LabelerError(f"boot worker: died during the {what}")
        try:
            ok, value = conn.recv()
        except (EOFError, OSError) as exc:
            self._kill()
            raise LabelerError(f"boot worker: lost during the {what}") from exc
        if not ok:
            raise LabelerError(f"boot worker: the {what} failed:\n{value}")
        return value

    def _kill(self) -> None:
        proc, conn, helper = self._proc, self._conn, self._helper
        self._proc, self._conn, self._known, self._helper = None, None, OrderedDict(), None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        for p in (proc, helper):
            if p is not None:
                with contextlib.suppress(OSError, ValueError):
                    if p.is_alive():
                        p.kill()
                    p.join(timeout=5.0)
