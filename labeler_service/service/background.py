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
abandoned: its result, if it ever comes, is discarded. ``max_jobs`` bounds the threads alive at
once (abandoned ones included); a job beyond it is refused with :class:`BudgetExceeded`.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from labeler_service.errors import BudgetExceeded

T = TypeVar("T")


class Background:
    """Runs blocking callables in daemon threads with a per-job budget (see module doc)."""

    def __init__(self, max_jobs: int = 4) -> None:
        self.max_jobs = max_jobs
        self._running: dict[threading.Thread, threading.Event] = {}
        self._closed = False

    @property
    def running(self) -> int:
        """Threads still alive (including abandoned jobs)."""
        self._running = {t: e for t, e in self._running.items() if t.is_alive()}
        return len(self._running)

    async def run(self, fn: Callable[..., T], *args: Any, budget_s: float, name: str = "job") -> T:
        """``fn(*args)`` in a daemon thread; raises :class:`BudgetExceeded` after ``budget_s``.

        Exceptions of ``fn`` propagate. If ``fn`` accepts a ``cancel`` keyword it gets a
        :class:`threading.Event` set when the job is abandoned or the runner closes.
        """
        if self._closed:
            raise BudgetExceeded(f"{name}: the background runner is closed")
        if self.running >= self.max_jobs:
            raise BudgetExceeded(f"{name}: {self.max_jobs} background jobs still running")
        loop = asyncio.get_running_loop()
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
            try:
                value = fn(*args, **kwargs)
            except BaseException as exc:  # handed to the awaiting coroutine
                ok, value = False, exc
            else:
                ok = True
            if not loop.is_closed():
                with contextlib.suppress(RuntimeError):  # loop closed meanwhile
                    loop.call_soon_threadsafe(deliver, ok, value)

        thread = threading.Thread(target=body, name=name, daemon=True)
        self._running[thread] = cancel
        thread.start()
        try:
            async with asyncio.timeout(budget_s):
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
