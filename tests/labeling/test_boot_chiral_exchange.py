"""A completion refused for a reversed chirality quadruple that says two placed markers sit on
each other's points (boot_match._chiral_exchange): the tennis copy (tune22, Viktor) booted with
its finger and outer wrist exchanged in a nearly isosceles hand triangle; its forearm and
elbow markers, the only evidence, were refused at every extension for 3.3 s."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

from labeler_service.labeling.boot_match import _chiral_exchange, _fill_reversed

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(3, 6.0, seed=11, rate=RATE)


def _refused(walk, a: str, b: str, new: str):
    """``a``/``b`` on each other's points, ``new`` unplaced (``assign``), and the completion
    ``out`` placing ``new`` on its true point, which reverses a thick quadruple."""
    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[ix[a]], assign[ix[b]] = ix[b], ix[a]
    assign[ix[new]] = -1
    out = assign.copy()
    out[ix[new]] = ix[new]
    marks = np.array([ix[new]])
    assert _fill_reversed(tpl, assign, pts, marks[None], out[marks][None])[0]
    return tpl, ix, assign, out, marks, pts, hist


def test_the_exchange_the_new_marker_tells_is_made(walk):
    """The wrist bar ``RWRA``/``RWRB`` exchanged: its pairs to the rest barely tell (the
    window exchange leaves it), the forearm marker the completion brings does, and only
    ``RWRB`` is in the reversed quadruples (its partner is found in its trained body)."""
    tpl, ix, assign, out, marks, pts, hist = _refused(walk, "RWRA", "RWRB", "RFRM")
    got = _chiral_exchange(tpl, assign, out, marks, pts, hist)
    assert np.array_equal(got, np.arange(tpl.n))


def test_a_pair_the_placed_markers_tell_apart_is_not_overturned(walk):
    """``RUPB``/``RFIN`` exchanged (the placed markers alone say so by thousands of nats: the
    window exchange's business): no other pair of the reversed quadruples is exchanged in its
    place (a first version moved the right ``RFRM`` and ``RHM5``)."""
    tpl, ix, assign, out, marks, pts, hist = _refused(walk, "RUPB", "RFIN", "RWRA")
    assert _chiral_exchange(tpl, assign, out, marks, pts, hist) is assign


def test_too_short_a_look_is_not_acted_on(walk):
    """The two points tracked only in the last frames: no exchange on so short a look."""
    tpl, ix, assign, out, marks, pts, hist = _refused(walk, "RWRA", "RWRB", "RFRM")
    short = hist.copy()
    w = short.shape[1]
    short[[ix["RWRA"], ix["RWRB"]], : w - w // 2 + 1] = np.nan
    assert _chiral_exchange(tpl, assign, out, marks, pts, short) is assign


def test_a_completion_that_reverses_nothing_is_not_looked_at(walk):
    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[ix["RFRM"]] = -1
    out = np.arange(tpl.n)
    got = _chiral_exchange(tpl, assign, out, np.array([ix["RFRM"]]), pts, hist)
    assert got is assign
