"""A completion refused for a reversed chirality quadruple reads the new marker's segment
again (boot_match._chiral_reread): a four-marker pelvis plate booted with one marker hidden is
three markers with no handedness, and read left for right its fourth marker can only join
mirrored, which the chirality check refuses for the whole take (the shoulder take's pelvis in
holdout11: ASIS and PSIS left for right, ASISl never placed)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

RATE = 120.0
PELVIS = ("RASI", "LASI", "RPSI", "LPSI")


@pytest.fixture(scope="module")
def walk():
    return split_walk(5, 6.0, seed=7, rate=RATE, ghosts=2.0)


def _mirrored(walk):
    """P1 on its true points (point ``i`` is marker ``i``) but its pelvis read left for right
    with LASI hidden: RASI on LASI's point, RPSI and LPSI exchanged; RASI's point free."""
    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[ix["RASI"]] = ix["LASI"]
    assign[ix["RPSI"]] = ix["LPSI"]
    assign[ix["LPSI"]] = ix["RPSI"]
    assign[ix["LASI"]] = -1
    return tpl, ix, pts, hist, assign


def test_the_mirror_completion_is_refused_and_read_again(walk):
    """LASI on the free point (RASI's, where the mirror reading puts it) reverses a thick
    quadruple; reading the plate again puts all four markers on their own points and moves
    nothing else."""
    from labeler_service.labeling.boot_match import _chiral_reread, _fill_reversed

    tpl, ix, pts, _, assign = _mirrored(walk)
    out = assign.copy()
    out[ix["LASI"]] = ix["RASI"]
    new = np.array([ix["LASI"]])
    assert _fill_reversed(tpl, assign, pts, new[None], out[new][None])[0]
    got = _chiral_reread(tpl, assign, out, new, pts)
    assert {n: int(got[ix[n]]) for n in PELVIS} == {n: ix[n] for n in PELVIS}
    rest = np.setdiff1d(np.arange(tpl.n), [ix[n] for n in PELVIS])
    assert np.array_equal(got[rest], assign[rest])


def test_a_right_reading_is_not_moved(walk):
    """The plate read right with LASI hidden: a completion putting LASI on its own point
    reverses nothing, so there is nothing to read again; offered a refused completion anyway
    (LASI on a point of another body, tied to the plate by no rigid pair: the new marker may
    be the one off), nothing is placed or moved."""
    from labeler_service.labeling.boot_match import _chiral_reread, _fill_reversed

    tpl, ix, pts, _, _ = _mirrored(walk)
    assign = np.arange(tpl.n)
    assign[ix["LASI"]] = -1
    new = np.array([ix["LASI"]])
    right = assign.copy()
    right[ix["LASI"]] = ix["LASI"]
    assert not _fill_reversed(tpl, assign, pts, new[None], right[new][None])[0]
    # LASI on the right knee's point, that knee unplaced: off every trained distance of the
    # plate, so no reading of the plate's points keeps them
    assign[ix["RKNE"]] = -1
    wrong = assign.copy()
    wrong[ix["LASI"]] = ix["RKNE"]
    assert np.array_equal(_chiral_reread(tpl, assign, wrong, new, pts), assign)
