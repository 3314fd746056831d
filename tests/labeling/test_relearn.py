"""The labeled start's booter learned again from the stream's own clean frames
(``BootConfig.relearn_every_s``, ``BootingLabeler._relearn``; docs/algorithm.md)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.test_boot import RATE, Stream
from labeling.walks import split_walk

from labeler_service.capture import Capture
from labeler_service.labeling.registry import make_window_labeler
from labeler_service.labeling.structure import window_model

WINDOW = 20


@pytest.fixture(scope="module")
def walk():
    return split_walk(2, 8.0, seed=5, rate=RATE)


def _run(walk, frames: int, ghost: bool = False, hidden: int = -1, **boot):
    """A labeled start (window model of the first ``WINDOW`` frames, as ``evaluate`` makes it)
    fed ``frames`` frames of the walk; ``ghost``: one stray point in every frame; ``hidden``:
    a marker whose point every frame after the window leaves out."""
    model, cap = walk
    s = Stream(cap, model, seed=2, hide=0.0)
    first = [s.frame(f) for f in range(WINDOW)]
    pos = np.full((WINDOW, len(model.marker_names), 3), np.nan, np.float32)
    for k, (pts, tr) in enumerate(first):
        pos[k, tr[tr >= 0]] = pts[tr >= 0]
    window = window_model(Capture(pos, model.marker_names, RATE))
    lab = make_window_labeler(window, rate=RATE, window_frames=WINDOW)
    if boot:  # (the settings are frozen: a copy, and the period read again)
        lab.boot_config = lab.boot_config.model_copy(update=boot)
        every = lab.boot_config.relearn_every_s
        lab._relearn_every = round(every * RATE) if every > 0 else 0
    for f in range(frames):
        pts, tr = s.frame(f)
        if f >= WINDOW and hidden >= 0:
            pts, tr = pts[tr != hidden], tr[tr != hidden]
        if ghost:
            pts = np.concatenate([pts, np.array([[5000.0, 5000.0, 5000.0]], np.float32)])
            tr = np.concatenate([tr, [-1]])
        lab.process(pts, f / RATE, tr if f < WINDOW else None)
    return lab, window


def test_the_booter_learns_again_from_the_clean_stream_and_the_labeler_stays(walk):
    lab, window = _run(walk, WINDOW + round(2.2 * RATE))
    assert lab.relearned == 1
    assert lab._booter.model is not window and lab.model is window  # only the booter's
    inner = lab._inner
    lab2, window2 = _run(walk, WINDOW + round(2.2 * RATE), relearn_every_s=0.0)
    assert lab2.relearned == 0 and lab2._booter.model is window2
    assert inner is lab._inner  # the labeler and its state are kept
    # learned from ~2 s of motion, not the window's 20 frames: its pair deviations differ
    new, old = lab._booter.model.subjects[0], window.subjects[0]
    assert not np.allclose(np.asarray(new.A, float), np.asarray(old.A, float), equal_nan=True)


def test_no_relearn_from_frames_with_an_unlabeled_point_and_marker_or_too_few(walk):
    """A free point makes a frame unclean only while some marker of the active subjects is
    unlabeled too (it may be that marker's point); a stray point beside every marker labeled
    is none of theirs (before, any free point made the frame unclean)."""
    frames = WINDOW + round(2.2 * RATE)
    lab, _ = _run(walk, WINDOW + 1)
    every = np.arange(len(lab._names))
    assert lab._clean(every) and lab._clean(np.append(every, -1))  # a stray point: clean
    assert lab._clean(every[1:])  # a hidden marker, every point labeled
    assert not lab._clean(np.append(every[1:], -1))  # the free point may be that marker
    lab, window = _run(walk, frames, ghost=True, hidden=3)
    assert lab.relearned == 0 and lab._booter.model is window
    lab, window = _run(walk, frames, hidden=3)  # a hidden marker alone: every point labeled
    assert lab.relearned == 1
    lab, window = _run(walk, frames, relearn_min_frames=10_000)
    assert lab.relearned == 0


def test_where_the_extension_runs_elsewhere_the_boot_job_relearns(walk):
    """The service runs the extension off the frame path (``inline_extend`` off), where a
    window model trained on the frame path would stall the stream: the relearn that falls due
    rides on the next boot job instead. :meth:`needs_boot` asks for one, the snapshot carries
    the clean frames (not to a worker process: ``remote``), the job's ``boot_step`` trains,
    and the install between two frames takes the booter over under a new worker key. Before,
    the service never relearned, and ``evaluate`` (which does) did not predict it."""
    model, cap = walk
    lab, _ = _run(walk, 2)
    lab.inline_extend = False
    lab.inline_boot = False
    s = Stream(cap, model, seed=3, hide=0.0)
    for f in range(2, WINDOW + round(2.2 * RATE)):
        pts, tr = s.frame(f)
        lab.process(pts, f / RATE, tr if f < WINDOW else None)
        if lab._relearn_pending:
            break
    assert lab.relearned == 0 and lab._relearn_pending and lab.needs_boot()
    key, booter = lab.key, lab._booter
    # what crosses to a worker process: no model while the booter's is the labeler's
    assert lab._shadow().for_transfer().model is None
    snap = lab.boot_snapshot()
    assert snap.relearn and len(snap.relearn) >= lab.boot_config.relearn_min_frames
    assert snap.remote().relearn is None and not lab._relearn_pending
    result = lab.boot_step(snap)
    assert snap.relearned is not None and lab._booter is booter  # trained, not installed
    lab.install_boot(snap, result)
    assert lab.relearned == 1 and lab.key != key and lab._booter is not booter
    assert lab.boot_model is lab._booter.model and lab.model is not lab.boot_model
    # after it the worker could not rebuild the labeler's model from the booter: it goes along
    sent = lab._shadow().for_transfer()
    assert sent.model is lab.model and sent.boot_model is None and sent._booter is None


def test_a_catch_up_shadow_keeps_no_relearn_history(walk):
    """The catch-up's shadow is a shallow copy: it shared the labeler's relearn deques, and
    its frames (fed in the boot job's thread) went into the stream's history."""
    model, cap = walk
    lab, _ = _run(walk, WINDOW + 10)
    n = len(lab._relearn_frames)
    sh = lab._shadow()
    assert sh._relearn_frames is not lab._relearn_frames and not sh._relearn_every
    s = Stream(cap, model, seed=3, hide=0.0)
    sh._inner_from_window()
    for f in range(WINDOW + 10, WINDOW + 20):
        sh.process(*s.frame(f)[:1], f / RATE)
    assert len(lab._relearn_frames) == n
