"""The one mechanism for CPU jobs off the event loop (service/background.py): results and
exceptions come back, a job over budget is abandoned (and told so), one job runs at a time
and the waiting ones start first come first served (a wait bound of their own for boots),
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


def _order(priorities: dict[str, int]) -> str:
    """The order in which jobs asked in ``priorities``' order (name -> priority), waiting
    behind a running one, got the slot."""
    release = threading.Event()
    order: list[str] = []

    async def go():
        bg = Background(concurrency=1)
        first = asyncio.ensure_future(bg.run(lambda: release.wait(10), budget_s=30))
        await asyncio.sleep(0.1)  # (the first holds the slot)
        waiters = []
        for name, priority in priorities.items():
            job = bg.run(lambda n=name: order.append(n), budget_s=30, priority=priority)
            waiters.append(asyncio.ensure_future(job))
            await asyncio.sleep(0.06)  # asked in this order, over a few polls
        release.set()
        await asyncio.gather(first, *waiters)

    run(go(), timeout=30)
    return "".join(order)


def test_slots_go_first_come_first_served():
    # a stream whose jobs keep asking must not take every free slot from another's: the jobs
    # waiting behind a running one start in the order they asked
    assert _order(dict.fromkeys("abcdefgh", 0)) == "abcdefgh"


def test_a_lower_priority_class_goes_first_and_first_come_within_it():
    # the service's configured streams (priority 0) before streams any sender opens by name
    # (1): bursts of labeled frames to new names queued trainings ahead of a configured
    # stream's re-identification for 18-54 s
    assert _order(dict(zip("abcdef", (1, 1, 0, 1, 0, 0), strict=True))) == "cefabd"


def test_with_a_wait_bound_the_budget_starts_when_the_job_does():
    # a boot waiting its turn behind another stream's job is not over its own budget: the wait
    # has its bound (wait_s), the budget counts the job
    release = threading.Event()

    async def go():
        bg = Background(concurrency=1)
        holder = asyncio.ensure_future(bg.run(lambda: release.wait(10), budget_s=30))
        await asyncio.sleep(0.1)
        waiting = asyncio.ensure_future(bg.run(lambda: "ran", budget_s=0.2, wait_s=30))
        await asyncio.sleep(0.5)  # longer than the waiter's budget
        assert not waiting.done()
        release.set()
        assert await waiting == "ran"
        await holder
        # without the bound the wait still counts against the budget (in-stream training)
        release.clear()
        holder = asyncio.ensure_future(bg.run(lambda: release.wait(10), budget_s=30))
        await asyncio.sleep(0.1)
        with pytest.raises(BudgetExceeded, match="no free slot within its budget"):
            await bg.run(lambda: 1, budget_s=0.2)
        with pytest.raises(BudgetExceeded, match="no free slot within its wait bound"):
            await bg.run(lambda: 1, budget_s=5, wait_s=0.2)
        release.set()
        await holder

    run(go(), timeout=30)


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
