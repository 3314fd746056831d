"""Limbs of one performer read as another's (issue 11, the 10-person hug at 360 Hz): the
reclaim's comparison of two subjects (boot_match._evidence, _tied) and the release of a loose
segment in the weak completion (boot_match._loose_part, _complete_weak)."""

from __future__ import annotations

import numpy as np
from labeling.test_boot_match import _two_walkers_window

from labeler_service.labeling import boot as boot_mod
from labeler_service.labeling.boot import BootConfig
from labeler_service.labeling.boot_match import (
    _complete,
    _complete_weak,
    _evidence,
    _Hypothesis,
    _loose_part,
    _pair_error,
    _tied,
)


def _names(booter, tpl) -> list[str]:
    return [n.split(":")[-1] for n in booter.model.marker_names[tpl.offset : tpl.offset + tpl.n]]


def _hand(booter, tpl, a) -> np.ndarray:
    """A hand segment of ``tpl`` (no marker shared with a body of more than the hand) placed
    whole on its true points in ``a``."""
    names = _names(booter, tpl)
    for seg in tpl.segments:
        if np.all(a[seg] >= 0) and all(names[m][1:] in ("FIN", "HM2", "HM5") for m in seg):
            return seg
    raise AssertionError("no whole hand segment in the window")


def test_evidence_counts_right_pairs_for_a_reading_not_against_it():
    """The same markers on their true points, against more of their subject placed right:
    the plain sum of pair costs grows with the pairs (each pair's density term), the
    likelihood ratio falls (each right pair is evidence). Two subjects reading the same points
    with different numbers of markers placed were compared on the plain sum."""
    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    hand = _hand(booter, t0, a0)
    fewer = a0.copy()
    rest = np.flatnonzero(a0 >= 0)
    rest = rest[~np.isin(rest, hand)]
    fewer[rest[::2]] = -1
    assert _pair_error(t0, hand, a0[hand], a0, pts) > _pair_error(t0, hand, a0[hand], fewer, pts)
    assert _evidence(t0, hand, a0[hand], a0, pts) < _evidence(t0, hand, a0[hand], fewer, pts)


def test_reclaim_does_not_take_points_tied_to_their_holder(monkeypatch):
    """Subject 0's completion claims the points of a segment of subject 1 that pairs of one
    trained body tie to the rest of subject 1 (a hugging partner's shoulder and arm, read as
    this performer's arm through articulated links): they stay with subject 1, however the
    likelihoods compare."""
    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    names0, names1 = _names(booter, t0), _names(booter, t1)
    seg = next(
        s
        for s in t1.segments
        if np.all(a1[s] >= 0) and _tied(t1, s, a1[s], a1, pts) >= 2 and s.size >= 3
    )
    mine = np.array([names0.index(names1[m]) for m in seg])
    a0[mine] = -1
    claim = a0.copy()
    claim[mine] = a1[seg]
    assert _tied(t0, mine, claim[mine], a0, pts) < _tied(t1, seg, a1[seg], a1, pts) - 1
    monkeypatch.setattr(boot_mod, "_complete", lambda tpl, assign, *a, **k: (
        claim.copy() if tpl.index == 0 else assign.copy()
    ))  # fmt: skip
    # the margin of the likelihoods alone would let the claim through
    monkeypatch.setattr(boot_mod, "EXCHANGE_MARGIN", -1e9)
    before0, before1 = a0.copy(), a1.copy()
    accepted = [_Hypothesis(0, a0, 0.0), _Hypothesis(1, a1, 0.0)]
    booter._reclaim(accepted, pts, h)
    np.testing.assert_array_equal(accepted[1].assign, before1)
    np.testing.assert_array_equal(accepted[0].assign, before0)


def test_weak_completion_releases_a_partners_hand_read_as_this_subjects_own():
    """Subject 0 holds subject 1's hand as its own (the three hand markers fit each other, so
    none is weak) while its own forearm and hand are unplaced: the hand is loose (nothing
    rigid ties it to the rest of subject 0) and the plain completion cannot place the forearm
    next to it; released, the forearm and the hand are placed on subject 0's own points."""
    booter, h, pts, t0, t1, a0, a1 = _two_walkers_window()
    names0 = _names(booter, t0)
    hand0 = _hand(booter, t0, a0)
    hand1 = np.array([_names(booter, t1).index(names0[m]) for m in hand0])
    # subject 1's hand, over the whole window, 150 mm above subject 0's (the walkers are
    # apart; in a hug the partner's hand is there)
    h = h.copy()
    h[a1[hand1]] += pts[a0[hand0]].mean(axis=0) - pts[a1[hand1]].mean(axis=0) + [0, 0, 150]
    pts = h[:, -1]
    side = names0[hand0[0]][0]
    bar = np.array([names0.index(side + x) for x in ("FRM", "WRA", "WRB")])
    truth = a0.copy()
    assign = a0.copy()
    assign[bar] = -1
    assign[hand0] = a1[hand1]  # subject 1's hand read as subject 0's
    taken = np.zeros(pts.shape[0], dtype=bool)
    rest1 = np.flatnonzero(a1 >= 0)
    taken[a1[rest1[~np.isin(rest1, hand1)]]] = True  # subject 1's other points are its own
    cfg = BootConfig()
    assert _loose_part(t0, hand0, assign, pts).size == hand0.size
    plain = _complete(t0, assign, pts, h, taken, cfg)
    assert np.array_equal(plain[hand0], a1[hand1])  # the plain completion keeps the wrong hand
    assert not np.array_equal(plain[bar], truth[bar])
    out = _complete_weak(t0, assign, pts, h, taken, cfg)
    np.testing.assert_array_equal(out[hand0], truth[hand0])
    np.testing.assert_array_equal(out[bar], truth[bar])
