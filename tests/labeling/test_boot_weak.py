"""Weakly placed markers read again (boot_match._weak_markers, _complete_weak and the second
pass of _fill): a booted subject whose chain was read one marker along, or whose segment sits
on another segment's points, keeps its true points free and the segments next to it
unlabeled unless the weakly placed markers may move."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

from labeler_service.labeling.boot import BootConfig, Booter

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(5, 6.0, seed=7, rate=RATE, ghosts=2.0)


def _case(walk):
    """P1 on its true points in the first frame whose 12-frame window sees all of them:
    ``(tpl, names, pts, hist)``; point ``i`` is marker ``i``."""
    return subject_on_its_points(walk)


def test_weak_markers_are_the_ones_read_along_the_chain(walk):
    """The forearm marker read on the wrist marker's point has no rigid partner in place;
    every correctly placed marker keeps its support."""
    from labeler_service.labeling.boot_match import _weak_markers

    tpl, names, pts, hist = _case(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[[ix["LWRA"], ix["LWRB"]]] = -1
    assign[ix["LFRM"]] = ix["LWRA"]  # LFRM on LWRA's point; LFRM's own point free
    miss = np.flatnonzero(assign < 0)
    assert _weak_markers(tpl, assign, miss, pts).tolist() == [ix["LFRM"]]
    # placed right with one bar marker hidden: its two partners hold one rigid pair each
    # (weak: they may be re-read), no marker outside the bar's body is
    right = np.arange(tpl.n)
    right[ix["LWRB"]] = -1
    weak = _weak_markers(tpl, right, np.array([ix["LWRB"]]), pts).tolist()
    assert weak == sorted([ix["LFRM"], ix["LWRA"]])


def test_fill_moves_a_marker_read_along_the_chain(walk):
    """The plain joint fill refuses (a placed marker fits the leftover point better); with the
    weak marker re-read the forearm bar is placed right, the misplaced marker moved."""
    from labeler_service.labeling.boot_match import _fill

    tpl, names, pts, hist = _case(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[[ix["LWRA"], ix["LWRB"]]] = -1
    assign[ix["LFRM"]] = ix["LWRA"]
    free = np.zeros(tpl.n, dtype=bool)
    free[[ix["LFRM"], ix["LWRB"]]] = True  # the points no marker holds
    out = _fill(tpl, assign, pts, hist, free, np.zeros((0, 3)), BootConfig())
    assert np.array_equal(out, np.arange(tpl.n))


def test_completion_releases_a_segment_on_another_segments_points(walk):
    """Two forearm-bar markers read on the hand's points (the third hidden at boot) clash with
    both true readings; released, the completion places forearm and hand on their own points
    (the kneeling performer's ankle, heel and toe read on its other hand and forearm)."""
    from labeler_service.labeling.boot_match import _complete, _complete_weak

    tpl, names, pts, hist = _case(walk)
    ix = {n: i for i, n in enumerate(names)}
    bar = [ix["LFRM"], ix["LWRA"], ix["LWRB"]]
    hand = [ix["LFIN"], ix["LHM2"], ix["LHM5"]]
    assign = np.arange(tpl.n)
    assign[hand[:2] + bar[2:]] = -1
    assign[bar[:2]] = hand[:2]  # LFRM, LWRA on LFIN's and LHM2's points; theirs free
    taken = np.zeros(tpl.n, dtype=bool)
    cfg = BootConfig()
    plain = _complete(tpl, assign, pts, hist, taken, cfg)
    assert np.array_equal(plain[bar[:2]], hand[:2])  # the plain completion cannot undo it
    out = _complete_weak(tpl, assign, pts, hist, taken, cfg)
    assert np.array_equal(out[bar + hand], np.array(bar + hand))


def test_extension_carries_moves_with_each_label_once(walk):
    """Booter.extend with track ages: the moved marker leaves its old point, and no label is
    given twice."""
    model, _ = walk
    tpl, names, pts, hist = _case(walk)
    ix = {n: i for i, n in enumerate(names)}
    labels = np.arange(tpl.n) + tpl.offset
    labels[[ix["LFRM"], ix["LWRB"]]] = -1
    labels[ix["LWRA"]] = tpl.offset + ix["LFRM"]
    out = Booter(model).extend(pts, hist, labels, [0], np.full(tpl.n, 1.0))
    assert np.array_equal(out, np.arange(tpl.n) + tpl.offset)
    plain = Booter(model).extend(pts, hist, labels, [0])  # (no ages: nothing moves)
    assert plain[ix["LWRA"]] == tpl.offset + ix["LFRM"]
    assert np.unique(plain[plain >= 0]).size == np.count_nonzero(plain >= 0)


def test_completion_keeps_weak_markers_placed_right(walk):
    """Weak is not wrong: with a bar marker and the hand hidden, the bar's two placed markers
    are weak; released, they must come back where they were (a move must fit better)."""
    from labeler_service.labeling.boot_match import _complete_weak, _weak_markers

    tpl, names, pts, hist = _case(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    hidden = [ix["LWRB"], ix["LFIN"], ix["LHM2"], ix["LHM5"]]
    assign[hidden] = -1
    keep = np.ones(tpl.n, dtype=bool)
    keep[hidden] = False  # the hidden markers' points are gone from the frame
    pts2, hist2 = pts[keep], hist[keep]
    back = np.cumsum(keep) - 1
    assign = np.where(assign >= 0, back[np.maximum(assign, 0)], -1)
    assert _weak_markers(tpl, assign, np.array(hidden), pts2).size
    out = _complete_weak(
        tpl, assign, pts2, hist2, np.zeros(pts2.shape[0], dtype=bool), BootConfig()
    )
    placed = assign >= 0
    assert np.array_equal(out[placed], assign[placed])
