"""The one mechanism for CPU jobs off the event loop (service/background.py): results and
exceptions come back, a job over budget is abandoned (and told so), one job runs at a time,
and a closed runner refuses new jobs. In-stream training uses it; boot from a model will."""

from __future__ import annotations

import asyncio
import threading

import pytest
from hostile.helpers import run

from labeler_service.errors import BudgetExceeded
from labeler_service.service.background import Background


def test_results_and_exceptions_come_back():
    async def go():
        bg = Background()
        assert await bg.run(lambda a, b: a + b, 2, 3, budget_s=5) == 5
        with pytest.raises(ZeroDivisionError):
            await bg.run(lambda: 1 / 0, budget_s=5)

    run(go())


def test_a_job_over_budget_is_abandoned_and_told_to_stop():
    stopped = threading.Event()

    def slow(cancel):
        cancel.wait(10)  # a cooperative job: stops when told
        stopped.set()

    async def go():
        bg = Background()
        with pytest.raises(BudgetExceeded, match="budget"):
            await bg.run(slow, budget_s=0.1, name="train-x")
        await asyncio.sleep(0.1)
        return bg.running

    assert run(go()) == 0
    assert stopped.is_set()


def test_one_job_at_a_time_others_wait_within_their_budget():
    active, peak = [0], [0]
    lock = threading.Lock()

    def job():
        with lock:
            active[0] += 1
            peak[0] = max(peak[0], active[0])
        threading.Event().wait(0.05)
        with lock:
            active[0] -= 1
        return 1

    async def go():
        bg = Background(concurrency=1)
        return await asyncio.gather(*(bg.run(job, budget_s=5) for _ in range(5)))

    assert run(go()) == [1] * 5
    assert peak[0] == 1


def test_a_slot_held_by_an_abandoned_job_makes_the_next_wait_then_fail():
    release = threading.Event()

    async def go():
        bg = Background(concurrency=1)
        with pytest.raises(BudgetExceeded):
            await bg.run(lambda: release.wait(10), budget_s=0.05)
        with pytest.raises(BudgetExceeded, match="no free slot"):
            await bg.run(lambda: 1, budget_s=0.1)
        release.set()
        await asyncio.sleep(0.1)
        assert await bg.run(lambda: 2, budget_s=1) == 2
        bg.close()
        with pytest.raises(BudgetExceeded, match="closed"):
            await bg.run(lambda: 3, budget_s=1)

    run(go())


class _Big:
    """Stands for a training's state (a labeler with its matrices)."""


def test_an_abandoned_jobs_outcome_is_dropped_in_its_thread_without_the_gc():
    import gc
    import weakref

    refs = []

    def job(fail, cancel):
        big = _Big()
        refs.append(weakref.ref(big))
        cancel.wait(10)  # abandoned meanwhile
        if fail:  # the traceback holds this frame (and ``big``) ...
            raise ValueError("over budget anyway")
        return big  # ... or the result is the big object itself

    async def go():
        bg = Background()
        for fail in (True, False):
            with pytest.raises(BudgetExceeded):
                await bg.run(job, fail, budget_s=0.05)
            while bg.running:
                await asyncio.sleep(0.01)

    gc.disable()  # freed by reference counting when the thread ends, not by a collection
    try:
        run(go())
        assert [r() for r in refs] == [None, None]
    finally:
        gc.enable()
