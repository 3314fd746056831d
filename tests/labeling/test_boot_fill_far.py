"""The joint fill (boot_match._fill) of a segment left over next to a partner: its points are
nearer the partner's labeled points than the subject's own placed ones, and they are filled
when no other subject can still claim them (boot_match._reach)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_with_leftover

from labeler_service.labeling.boot import BootConfig

RATE = 120.0
ARM = ("LELB", "LFRM", "LWRA", "LWRB", "LFIN")


@pytest.fixture(scope="module")
def walk():
    return split_walk(5, 6.0, seed=7, rate=RATE, ghosts=2.0)


def _case(walk):
    """P1 on its true points with its left forearm and hand free (tracked), and a partner's
    labeled point 10 mm from each of them (a hug: the partner's arm along this one's)."""
    tpl, _, assign, pts, hist, free, miss = subject_with_leftover(walk, ARM)
    others = pts[miss] + np.array([0.0, 0.0, 10.0])
    return tpl, assign, pts, hist, free, miss, others


def test_a_segment_nearer_a_partner_is_filled_when_nobody_else_claims_it(walk):
    from labeler_service.labeling.boot_match import _fill

    tpl, assign, pts, hist, free, miss, others = _case(walk)
    cfg = BootConfig()
    # the nearest-point rule alone refuses every point of the segment
    assert np.array_equal(_fill(tpl, assign, pts, hist, free, others, cfg), assign)
    # no other subject can claim them: the fill reads the segment
    nobody = np.zeros(tpl.n, dtype=bool)
    got = _fill(tpl, assign, pts, hist, free, others, cfg, nobody)
    assert np.array_equal(got, np.arange(tpl.n))
    # another subject with leftover markers that reach them: they stay free
    claimed = free.copy()
    assert np.array_equal(_fill(tpl, assign, pts, hist, free, others, cfg, claimed), assign)


def test_reach_is_where_a_leftover_marker_can_be(walk):
    from labeler_service.labeling.boot_match import _reach

    tpl, assign, pts, hist, free, miss, others = _case(walk)
    cfg = BootConfig()
    far = pts[miss] + np.array([3000.0, 0.0, 0.0])
    both = np.concatenate([pts, far])
    idx = np.concatenate([miss, tpl.n + np.arange(miss.size)])
    got = _reach(tpl, assign, both, idx, cfg)
    assert got[: miss.size].all() and not got[miss.size :].any()
    # a complete subject claims nothing
    assert not _reach(tpl, np.arange(tpl.n), both, idx, cfg).any()
