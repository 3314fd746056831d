"""CPU jobs off the event loop, with a time budget and cancellation: one small mechanism.

In-stream training (the first unlabeled frame after the init window) and, later, boot from a
subject model run here so the loop keeps serving other streams::

    bg = Background()
    try:
        result = await bg.run(job, arg, budget_s=5.0, name="train-volume1")
    except BudgetExceeded:
        ...  # abandoned: the caller reports `training_failed`
    bg.close()  # at shutdown: cancels waiters, signals running jobs

Each job runs in its own **daemon** thread, so an abandoned job never delays the process exit
(a ThreadPoolExecutor's workers are joined at exit). Python cannot kill a thread: a job that
wants to stop early takes a ``cancel`` keyword (a :class:`threading.Event`, set when its budget
runs out or at :meth:`Background.close`) and checks it between steps. A job over budget is
abandoned: its result, if it ever comes, is discarded.

At most ``concurrency`` jobs run at once (default 1: CPU jobs share the GIL with the event
loop, so two at once slow the live streams without finishing sooner); the others wait for a
slot in the order they asked (first come, first served: a stream whose jobs keep failing cannot
take every free slot from another's) within their ``priority`` class (lower first: the service
puts its configured streams' jobs before those of streams any sender can open by name, whose
trainings made a configured stream wait 18-54 s for a re-identification), and the wait counts
against their budget - or, with
``wait_s``, against that bound and the budget starts when the job does (a boot waits its turn
behind the other streams' jobs, each bounded by its budget, instead of failing for their
sake). A slot is freed when a thread really ends, not when its job is abandoned, so abandoned
work never piles up: with every slot held by abandoned threads, new jobs wait and then fail.

While a job runs, the interpreter's switch interval drops from 5 ms to ``SWITCH_INTERVAL_S``
(0.5 ms): the event loop gives up the GIL at every socket call, and with a CPU-bound thread
beside it each hand-back waited up to 5 ms (the convoy effect) - enough to make a 120 Hz stream
fall behind while a 1,000-marker training ran.

After each job the C heap is trimmed (:func:`release_memory`): glibc keeps what a thread's
arena freed, so without it four abandoned 1,000-marker trainings left the service 180 MB larger
for good (measured: 370 MB -> 201 MB after ``malloc_trim``). An abandoned job's outcome (its
result or exception, whose traceback holds the job's frames) is dropped in the job's thread
before that trim, so its memory is freed then and not at the next full gc.
:func:`configure_allocator` (called by the service at start-up) keeps large blocks out of the
heap so that freeing them returns them at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import inspect
import itertools
import logging
import sys
import threading
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

from labeler_service.errors import BudgetExceeded
from labeler_service.service.boot_worker import (  # a child as the boot worker's
    NICE,
    POLL_S,
    start_child,
)

T = TypeVar("T")
log = logging.getLogger(__name__)

#: Interpreter switch interval while a background job runs (see the module docstring).
SWITCH_INTERVAL_S = 0.0005
_switch_lock = threading.Lock()
_switch_users = 0
_switch_saved = 0.005


def _switch_enter() -> None:
    global _switch_users, _switch_saved
    with _switch_lock:
        if _switch_users == 0:
            _switch_saved = sys.getswitchinterval()
            sys.setswitchinterval(min(_switch_saved, SWITCH_INTERVAL_S))
        _switch_users += 1


def _switch_exit() -> None:
    global _switch_users
    with _switch_lock:
        _switch_users -= 1
        if _switch_users == 0:
            sys.setswitchinterval(_switch_saved)


class Background:
    """Runs blocking callables in daemon threads with a per-job budget (see module doc)."""

    def __init__(self, concurrency: int = 1) -> None:
        self.concurrency = concurrency
        self._slots = threading.BoundedSemaphore(concurrency)
        #: ``(priority, ticket)`` of the jobs waiting for a slot: the least goes first (within a
        #: priority, the order they asked)
        self._waiting: list[tuple[int, int]] = []
        self._tickets = itertools.count()
        self._running: dict[threading.Thread, threading.Event] = {}
        self._closed = False
        #: abandoned jobs that have ended since the start (their frames are freed only then)
        self.abandoned_ended = 0

    @property
    def running(self) -> int:
        """Threads still alive (including abandoned jobs)."""
        self._running = {t: e for t, e in self._running.items() if t.is_alive()}
        return len(self._running)

    async def run(
        self,
        fn: Callable[..., T],
        *args: Any,
        budget_s: float,
        name: str = "job",
        wait_s: float | None = None,
        priority: int = 0,
    ) -> T:
        """``fn(*args)`` in a daemon thread; raises :class:`BudgetExceeded` after ``budget_s``.

        Jobs get a slot by ``priority`` (lower first), then in the order they asked. Without
        ``wait_s`` the wait for it counts against ``budget_s``; with it, the wait is bounded by
        ``wait_s`` and ``budget_s`` starts when the job does (a wait of a second or more is
        logged). Exceptions of ``fn`` propagate. If ``fn`` accepts a ``cancel`` keyword it gets
        a :class:`threading.Event` set when the job is abandoned or the runner closes.
        """
        if self._closed:
            raise BudgetExceeded(f"{name}: the background runner is closed")
        loop = asyncio.get_running_loop()
        asked = loop.time()
        deadline = asked + (budget_s if wait_s is None else wait_s)
        key = (priority, next(self._tickets))
        self._waiting.append(key)
        try:
            # wait for a slot, by priority and then first come first served, within the bound
            while not (min(self._waiting) == key and self._slots.acquire(blocking=False)):
                if loop.time() >= deadline:
                    bound = "budget" if wait_s is None else "wait bound"
                    raise BudgetExceeded(
                        f"{name}: no free slot within its {bound} of "
                        f"{deadline - asked:g} s ({self.concurrency} job(s) still running, "
                        f"{len(self._waiting) - 1} other(s) waiting)"
                    )
                await asyncio.sleep(0.05)
        finally:
            self._waiting.remove(key)
        waited = loop.time() - asked
        if waited >= 1.0:
            log.info("%s: waited %.1f s for a free background slot", name, waited)
        if wait_s is not None:
            deadline = loop.time() + budget_s
        fut: asyncio.Future[T] = loop.create_future()
        cancel = threading.Event()
        kwargs = {"cancel": cancel} if _takes_cancel(fn) else {}

        def deliver(ok: bool, value: Any) -> None:
            if fut.done():
                return
            if ok:
                fut.set_result(value)
            else:
                fut.set_exception(value)

        def body() -> None:
            _switch_enter()
            value: Any = None
            ok = False
            try:
                value = fn(*args, **kwargs)
                ok = True
            except BaseException as exc:  # handed to the awaiting coroutine
                value = exc
            finally:
                _switch_exit()
            try:
                if cancel.is_set():
                    self.abandoned_ended += 1
                    # abandoned (over budget, or closed): nobody awaits the outcome; drop it
                    # here, before the trim (an exception's traceback holds the job's frames,
                    # and this frame holds the exception: a cycle only the gc would break)
                    if isinstance(value, BaseException):
                        value.__traceback__ = None
                    value = None
                elif not loop.is_closed():
                    with contextlib.suppress(RuntimeError):  # loop closed meanwhile
                        loop.call_soon_threadsafe(deliver, ok, value)
                    value = None
            finally:
                release_memory()  # what the job freed goes back to the OS
                self._slots.release()

        thread = threading.Thread(target=body, name=name, daemon=True)
        self._running[thread] = cancel
        thread.start()
        try:
            async with asyncio.timeout(max(0.0, deadline - loop.time())):
                return await asyncio.shield(fut)
        except TimeoutError:
            cancel.set()
            raise BudgetExceeded(f"{name}: over its budget of {budget_s:g} s, abandoned") from None
        except asyncio.CancelledError:
            cancel.set()
            raise

    def close(self) -> None:
        """Refuses new jobs and signals every running one to stop (it is not waited for)."""
        self._closed = True
        for ev in self._running.values():
            ev.set()


def _takes_cancel(fn: Callable[..., Any]) -> bool:
    try:
        return "cancel" in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _libc_trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        return None


_TRIM = _libc_trim()


def release_memory() -> None:
    """Returns freed C-heap memory to the OS (glibc ``malloc_trim``; elsewhere a no-op)."""
    if _TRIM is not None:
        _TRIM(0)


#: glibc ``mallopt`` parameter: requests at least this large are served by their own ``mmap``
_M_MMAP_THRESHOLD = -3
#: Blocks from this size up are mapped on their own and unmapped when freed (see
#: :func:`configure_allocator`).
MMAP_THRESHOLD = 256 * 1024
_configured = False


def configure_allocator() -> None:
    """Makes large freed blocks go back to the OS by themselves (once per process; the
    service calls it at start-up). Two mechanisms kept memory after an attack ended:

    - glibc's *dynamic* mmap threshold: after the first large block is freed it rises (up to
      32 MiB), so later large arrays (a 1,000-marker training's matrices, 24 kB-2 MB buffers)
      come from the heap, which fragments and is returned only in part by ``malloc_trim``.
      A fixed threshold (:data:`MMAP_THRESHOLD`) keeps such blocks in their own mappings.
    - numpy's ``madvise(MADV_HUGEPAGE)`` on arrays of 4 MiB and more: in the heap, khugepaged
      then keeps (and refills) whole 2 MiB pages around freed memory.

    Measured on a failed 1,000-marker training: RSS +56 MB after it over the start,
    +17 MB with both (after the trim). Elsewhere (not glibc / numpy without the switch) a
    no-op."""
    global _configured
    if _configured:
        return
    _configured = True
    if _TRIM is not None:
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    try:
        from numpy._core import multiarray
    except ImportError:  # numpy < 2
        try:
            from numpy.core import multiarray  # type: ignore[no-redef]
        except ImportError:
            return
    switch = getattr(multiarray, "_set_madvise_hugepage", None)
    if switch is not None:
        switch(False)


def _child(conn) -> None:  # pragma: no cover (child)
    import os
    import traceback

    with contextlib.suppress(OSError, AttributeError):
        os.nice(NICE)  # (the boot worker's priority)
    try:
        fn, args = conn.recv()  # (run_in_process: the job over our pipe, not the bootstrap's)
        out = (True, fn(*args))
    except BaseException as exc:  # handed back to the parent
        out = (False, f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=5)}")
    try:
        conn.send(out)
    finally:
        conn.close()


class StopFlag(Protocol):
    """What :func:`run_in_process` watches to stop: a :class:`threading.Event`, or anything
    with its ``is_set`` (the handover's :class:`~labeler_service.service.handover.AnyOf`)."""

    def is_set(self) -> bool: ...


def run_in_process(
    fn: Callable[..., T], *args: Any, cancel: StopFlag | None = None, name: str = "job"
) -> T:
    """``fn(*args)`` in a ``spawn`` child process (its Python holds the child's GIL, not the
    event loop's), blocking the calling thread (a :class:`Background` job) until it returns.
    ``fn`` and ``args`` must pickle (a module-level function). ``cancel`` set: the child is
    terminated and :class:`~labeler_service.errors.BudgetExceeded` raised; a child that fails
    or dies raises :class:`~labeler_service.errors.LabelerError` (as the boot worker's). The
    child costs its imports (seconds: numpy, numba, the labeler's modules) on top of ``fn``;
    meant for rare, heavy calls (a stream's window model), not per frame."""
    import multiprocessing

    from labeler_service.errors import LabelerError

    ctx = multiprocessing.get_context("spawn")
    # the job goes over our own pipe, not as the Process's args: multiprocessing writes those
    # into the child's bootstrap pipe while it still holds that pipe's read end itself, so a
    # child dying before it read them all (a window of 250 kB; killed, or Ctrl-C before its
    # SIGINT was blocked) left this thread blocked in start() for good, and the service's exit
    # waited on it. Our pipe's other end is closed here once the child has it: its death
    # breaks the send.
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_child, args=(child,), name=name, daemon=True)
    start_child(proc)
    child.close()
    try:
        try:
            parent.send((fn, args))
        except OSError as exc:  # BrokenPipeError, ConnectionResetError: the child is gone
            raise LabelerError(f"{name}: its process ended before it took its job") from exc
        while not parent.poll(POLL_S):
            if cancel is not None and cancel.is_set():
                raise BudgetExceeded(f"{name}: cancelled; its process was terminated")
            if not proc.is_alive() and not parent.poll(0):
                raise LabelerError(f"{name}: its process ended (exit code {proc.exitcode}) "
                                      "without a result")  # fmt: skip
        try:
            ok, value = parent.recv()
        except EOFError as exc:
            raise LabelerError(f"{name}: its process ended without a result") from exc
        if not ok:
            raise LabelerError(f"{name} failed in its process: {value}")
        return value
    finally:
        parent.close()
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=5.0)
