"""Exchanges and relocations of a hypothesis until neither changes it
(boot_match._local_search). The 10-person hug at 360 Hz booted a performer with its finger and
fifth metacarpal markers on each other's points (the hand triangle is nearly equilateral, only
the wrist links tell them apart) and kept them so for the whole take: the exchange had run
once, before the relocation that put one of them on the other's point."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points
from scipy.spatial import cKDTree

from labeler_service.labeling import boot_match
from labeler_service.labeling.boot_match import LOCAL_ROUNDS, _local_search

RATE = 120.0


@pytest.fixture(scope="module")
def hand():
    """P1 of a walk on its true points, plus one far point (another performer's thigh)."""
    tpl, names, pts, hist = subject_on_its_points(split_walk(3, 6.0, seed=11, rate=RATE))
    far = pts[names.index("LFIN")] + np.array([250.0, 0.0, -300.0])
    return tpl, {n: i for i, n in enumerate(names)}, np.vstack([pts, far])


def _reading(tpl, ix, far: int, moved: dict[str, str]) -> np.ndarray:
    """The true reading with the markers ``moved`` on another marker's point (or ``far``)."""
    assign = np.arange(tpl.n)
    for marker, point in moved.items():
        assign[ix[marker]] = far if point == "far" else ix[point]
    return assign


READINGS = [
    {"LHM5": "LFIN", "LFIN": "far"},
    {"LHM5": "LHM2", "LHM2": "far"},
    {"LFIN": "LHM5", "LHM5": "far"},
    {"LHM5": "LHM2", "LHM2": "LFIN", "LFIN": "far"},
    {"LFIN": "far", "LHM5": "LFIN", "LHM2": "LHM5"},
]


@pytest.mark.parametrize("moved", READINGS)
def test_a_hand_read_through_a_far_point_ends_right(hand, moved):
    """One hand marker on a far point, others one place along: one exchange pass and one
    relocation leave two hand markers on each other's points (the relocation brings the far
    marker back onto a free point of the hand, the wrong one); the next exchange reads them
    right."""
    tpl, ix, pts = hand
    far = pts.shape[0] - 1
    claimed = np.zeros(pts.shape[0], dtype=bool)
    tree = cKDTree(pts)
    once = _reading(tpl, ix, far, moved)
    boot_match._exchange(tpl, once, pts)
    free = ~claimed
    free[once[once >= 0]] = False
    boot_match._relocate(tpl, once, pts, free, tree)
    assert not np.array_equal(once, np.arange(tpl.n))  # (the case needs a second round)

    assign = _reading(tpl, ix, far, moved)
    free = _local_search(tpl, assign, pts, claimed, tree)
    assert np.array_equal(assign, np.arange(tpl.n))
    assert np.array_equal(free, np.arange(pts.shape[0]) == far)


def test_a_right_reading_is_left_as_it_is_after_one_round(hand, monkeypatch):
    tpl, ix, pts = hand
    calls = []
    real = boot_match._exchange
    monkeypatch.setattr(boot_match, "_exchange", lambda *a: calls.append(1) or real(*a))
    assign = np.arange(tpl.n)
    _local_search(tpl, assign, pts, np.zeros(pts.shape[0], dtype=bool), cKDTree(pts))
    assert np.array_equal(assign, np.arange(tpl.n))
    assert len(calls) == 1


def test_rounds_are_bounded(hand, monkeypatch):
    """Moves that never settle (the exchange's score is not the exact likelihood difference,
    so a cycle is conceivable) stop after ``LOCAL_ROUNDS`` rounds."""
    tpl, ix, pts = hand
    calls = []

    def flip(tpl, assign, pts, rounds=8):
        calls.append(1)
        assign[0], assign[1] = assign[1], assign[0]

    monkeypatch.setattr(boot_match, "_exchange", flip)
    assign = np.arange(tpl.n)
    _local_search(tpl, assign, pts, np.zeros(pts.shape[0], dtype=bool), cKDTree(pts))
    assert len(calls) == LOCAL_ROUNDS
