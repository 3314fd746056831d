"""The boot worker process (``service/boot_worker.py``): a boot step and a catch-up run there
give what they give in this process; an abandoned request kills the worker, the next request
starts a new one; a failure in the worker is our error, not a hang."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest
from labeling.test_boot import RATE, Stream, _attempt, _run
from labeling.walks import split_walk

from labeler_service.errors import BudgetExceeded, LabelerError
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.service.boot_worker import BootWorker


@pytest.fixture(scope="module")
def walk():
    return split_walk(3, 4.0, seed=11, rate=RATE, ghosts=1.0)


@pytest.fixture(scope="module")
def worker():
    w = BootWorker()
    w.start()
    yield w
    w.close()


def _snapshot(model, cap, seed: int):
    """A booting labeler run 20 frames of the walk (seed ``seed``) and its boot snapshot."""
    lab = BootingLabeler(model, RATE, inline_boot=False)
    _run(lab, Stream(cap, model, seed=seed), range(20))
    return lab, lab.boot_snapshot()


def test_a_step_in_the_worker_gives_the_local_result(walk, worker):
    model, cap = walk
    lab, snap = _snapshot(model, cap, seed=4)
    there = lab.boot_step(snap, worker.runner(lab))
    here = lab.boot_step(snap)
    assert there.subjects == here.subjects and len(here.subjects) == 3
    np.testing.assert_array_equal(there.labels, here.labels)
    assert worker.pid is not None and worker.pid != os.getpid()


def test_a_catch_up_in_the_worker_installs_as_the_local_one(walk, worker):
    """The same late result caught up here and in the worker: the same subjects, and the
    frames after the install labeled alike (the worker's shadow comes back without its inner
    labeler, which restarts from the shadow's window: labels may differ in a few points)."""
    model, cap = walk
    outs = []
    for remote in (False, True):
        lab, s, snap, res = _attempt(model, cap, seed=5)
        _run(lab, s, range(20, 110))  # the attempt "took" 90 frames (0.75 s)
        assert lab.catch_up(snap, res, None, worker.catch_up(lab) if remote else None)
        assert snap.caught is not None and snap.caught.done == 90
        assert set(lab.install_boot(snap, res).tolist()) == {0, 1, 2}
        o, _ = _run(lab, s, range(110, 130))
        outs.append(np.concatenate([x.point_labels for x in o]))
    assert np.mean(outs[0] == outs[1]) >= 0.95


def test_an_abandoned_request_kills_the_worker_and_the_next_starts_one(walk):
    model, cap = walk
    lab, snap = _snapshot(model, cap, seed=6)
    w = BootWorker()
    try:
        assert not w.enabled  # (not before a worker has answered once: attempts would wait)
        w.start()  # (as the server does)
        assert w.enabled and w.started == 1
        cancel = threading.Event()
        cancel.set()  # over budget before the reply
        with pytest.raises(BudgetExceeded):
            lab.boot_step(snap, w.runner(lab, cancel))
        assert w.pid is None and w.started == 1
        assert w.enabled  # streams keep sending their attempts: the next one restarts it
        res = lab.boot_step(snap, w.runner(lab))
        assert len(res.subjects) == 3 and w.started == 2
        # a failure inside the worker comes back as our error (the worker keeps serving)
        with pytest.raises(LabelerError, match="failed"):
            w.step("another-labeler", (None, None), snap.remote())
        assert w.pid is not None and w.started == 2
    finally:
        w.close()
    assert not w.enabled
    with pytest.raises(LabelerError, match="closed"):
        w.step(lab.key, (model, lab.boot_config), snap.remote())


def test_a_worker_killed_from_outside_is_logged_and_started_again(walk, caplog):
    """The OOM killer (or anyone) ends the worker between attempts: the next attempt says so
    in the log, with the exit code, and runs in a new worker - which is sent the model the old
    one had (the first attempt after a kill failed with "no model for labeler": a hostile
    run's ``kill -9`` of the service's worker)."""
    import logging
    import signal

    model, cap = walk
    lab, snap = _snapshot(model, cap, seed=6)
    w = BootWorker()
    try:
        w.start()
        w.prepare(lab)  # (the service's start: the old worker has the model)
        pid = w.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        w._proc.join(timeout=10)
        caplog.set_level(logging.WARNING, logger="labeler_service.service.boot_worker")
        res = lab.boot_step(snap, w.runner(lab))
        assert len(res.subjects) == 3 and w.started == 2
        assert f"boot worker process {pid} had exited (exit code -9)" in caplog.text
    finally:
        w.close()


def test_the_worker_forgets_booters_as_it_drops_them(walk, worker):
    """The worker keeps ``MAX_BOOTERS`` booters, least recently used dropped; the service's
    side mirrors it, so a labeler whose booter was dropped sends its model again (it used to
    be refused for good with "no model for labeler"). (The module's worker: the booters it
    knows from earlier tests are older than these keys, so ``labeler-0`` is still the least
    recently used when the last one comes.)"""
    from labeler_service.service import boot_worker

    model, cap = walk
    lab, _, snap, _ = _attempt(model, cap, seed=4)
    w = worker
    spec = (model, lab.boot_config)
    for k in range(boot_worker.MAX_BOOTERS + 1):
        w.step(f"labeler-{k}", spec, snap.remote())
    assert "labeler-0" not in w._known and len(w._known) == boot_worker.MAX_BOOTERS
    result = w.step("labeler-0", spec, snap.remote())[0]  # (result, extended, ms)
    assert len(result.subjects) == 3


def test_an_abandoned_catch_up_frees_the_worker_for_the_next_request(walk):
    """A catch-up whose job is abandoned between two batches (over budget) stops the worker
    that holds its shadow: the next boot request gets a new worker instead of waiting forever
    for the held one."""
    model, cap = walk
    lab, s, snap, res = _attempt(model, cap, seed=7)
    _run(lab, s, range(20, 110))
    w = BootWorker()
    cancel = threading.Event()
    session = w.catch_up(lab, cancel)

    class AbandonedAfterBegin:
        def begin(self, shadow, snapshot, result):
            out = session.begin(shadow, snapshot, result)
            cancel.set()  # the budget runs out while the first batch is prepared
            return out

        frames, extend, finish = session.frames, session.extend, session.finish
        abort = session.abort

    try:
        assert not lab.catch_up(snap, res, cancel, AbandonedAfterBegin())
        assert w.started == 1 and w.pid is None  # the held worker was stopped
        done: list = []
        t = threading.Thread(
            target=lambda: done.append(lab.boot_step(snap, w.runner(lab))), daemon=True
        )
        t.start()
        t.join(timeout=120.0)
        assert done and len(done[0].subjects) == 3 and w.started == 2
    finally:
        w.close()


def test_a_prepared_worker_boots_without_the_model_and_its_helper_changes_nothing(walk, worker):
    """``prepare`` (at service start) builds the labeler's booter in the worker and its
    helper: the first attempt sends no model; with and without the helper (which takes
    subjects' hypotheses from the same list) the attempt gives the local result. (Without the
    helper: the module's worker, which has never seen this labeler.)"""
    model, cap = walk
    lab, snap = _snapshot(model, cap, seed=8)
    here = lab.boot_step(snap)
    assert len(here.subjects) == 3
    assert worker.helpers == 0 and lab.key not in worker._known
    for helpers in (0, 1):
        w = worker if helpers == 0 else BootWorker(helpers=helpers)
        try:
            w.start()
            w.prepare(lab)
            assert lab.key in w._known
            # no model sent: the booter must be there already
            there = w.step(lab.key, (None, None), snap.remote())[0]
            assert there.subjects == here.subjects
            np.testing.assert_array_equal(there.labels, here.labels)
            assert (w._helper is not None) == (helpers == 1)
        finally:
            if w is not worker:
                w.close()


def test_a_lost_helper_leaves_the_worker_alone_with_the_same_result(walk, capfd):
    """The helper killed from outside: the worker does its subjects itself (the same
    result) and goes on without it, and says so once on its stderr (the service's log; a
    hostile run's kill went unsaid); the worker itself is not restarted."""
    import signal

    model, cap = walk
    lab, snap = _snapshot(model, cap, seed=9)
    here = lab.boot_step(snap)
    w = BootWorker(helpers=1)
    try:
        w.start()
        w.prepare(lab)
        pid = w.pid
        os.kill(w._helper.pid, signal.SIGKILL)
        w._helper.join(timeout=10)
        for _ in range(2):
            there = lab.boot_step(snap, w.runner(lab))
            assert there.subjects == here.subjects
            np.testing.assert_array_equal(there.labels, here.labels)
        assert w.pid == pid and w.started == 1
    finally:
        w.close()
    err = capfd.readouterr().err
    assert err.count("boot helper gone") + err.count("boot helper failed") == 1, err


def _blocked(pid: int) -> int:
    """The process's blocked-signal mask (Linux ``/proc``)."""
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("SigBlk:"):
                return int(line.split()[1], 16)
    raise AssertionError("no SigBlk line")


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
def test_the_service_children_ignore_the_terminals_ctrl_c(worker):
    """Ctrl-C goes to the whole foreground process group: the boot worker and a window
    model's process, still importing, printed a KeyboardInterrupt traceback (or died
    mid-attempt) while the service itself shut down cleanly. They start with SIGINT blocked
    (the service ends them itself); the caller's own mask is left as it was."""
    import signal

    from labeler_service.service.background import run_in_process

    bit = 1 << (signal.SIGINT - 1)
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    assert worker._proc is not None and _blocked(worker._proc.pid) & bit
    assert signal.SIGINT in run_in_process(signal.pthread_sigmask, signal.SIG_BLOCK, [])
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before
    assert signal.SIGINT not in before


def test_a_child_whose_service_is_gone_ends_quietly():
    """The service killed during an attempt: the worker, an orphan now, finished its step and
    printed a ``BrokenPipeError`` traceback twice into the service's log while answering. The
    request loop ends quietly instead; a request that fails is still answered with its
    traceback."""
    from labeler_service.service.boot_worker import _answer

    class Gone:
        def __init__(self, msgs):
            self.msgs, self.sent = list(msgs), []

        def recv(self):
            if not self.msgs:
                raise EOFError
            return self.msgs.pop(0)

        def send(self, reply):
            if reply[0] is True and reply[1] == "late":
                raise BrokenPipeError(32, "Broken pipe")
            self.sent.append(reply)

    def handle(msg):
        if msg == "bad":
            raise ValueError("a failing request")
        return msg

    conn = Gone(["ok", "bad", "late", "never read"])
    _answer(conn, handle)  # returns at the broken pipe, raising nothing
    assert conn.sent[0] == (True, "ok")
    assert conn.sent[1][0] is False and "a failing request" in conn.sent[1][1]
    assert conn.msgs == ["never read"]
