"""Markers of one booted subject on each other's points (boot_match._window_exchange): the
kneeling performer booted with its ulna and hand markers exchanged kept them so for 817
frames, since the labeler then tracks both points well. The extension exchanges them back
when the tracks say so along the window."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

from labeler_service.labeling.boot_match import _window_exchange

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(3, 6.0, seed=11, rate=RATE)


def _swapped(walk, a: str, b: str):
    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    assign = np.arange(tpl.n)
    assign[ix[a]], assign[ix[b]] = ix[b], ix[a]
    return tpl, ix, assign, hist


@pytest.mark.parametrize(
    "pair", [("LWRB", "LFIN"), ("LELB", "LFRM"), ("LASI", "RASI"), ("C7", "T10")]
)
def test_two_markers_on_each_others_points_are_exchanged_back(walk, pair):
    tpl, ix, assign, hist = _swapped(walk, *pair)
    out = _window_exchange(tpl, assign, hist)
    assert np.array_equal(out, np.arange(tpl.n))


def test_a_right_reading_is_left_as_it_is(walk):
    tpl, names, pts, hist = subject_on_its_points(walk)
    assign = np.arange(tpl.n)
    assert _window_exchange(tpl, assign, hist) is assign


def test_evidence_of_fewer_than_half_the_window_is_not_acted_on(walk):
    """The two points tracked only in the last frames: no exchange on so short a look."""
    tpl, ix, assign, hist = _swapped(walk, "LWRB", "LFIN")
    short = hist.copy()
    w = short.shape[1]
    short[[ix["LWRB"], ix["LFIN"]], : w - w // 2 + 1] = np.nan
    assert _window_exchange(tpl, assign, short) is assign
    assert np.array_equal(_window_exchange(tpl, assign, hist), np.arange(tpl.n))


def test_an_exchange_that_leaves_a_marker_off_its_body_is_refused(walk):
    """A reading the model contradicts either way (one of the two points is 80 mm off where
    the marker should be: a pose or a body the training never saw) gains by the exchange but
    stays wrong: no evidence that the exchange is the answer."""
    tpl, ix, assign, hist = _swapped(walk, "LWRB", "LFIN")
    moved = hist.copy()
    moved[ix["LWRB"]] += np.array([80.0, 0.0, 0.0])  # the point LFIN holds, LWRB's if exchanged
    assert _window_exchange(tpl, assign, moved) is assign


@pytest.mark.parametrize("pair", [("RUPA", "RELB"), ("LTHI", "LTHA"), ("LUPB", "LELB")])
def test_two_markers_exchanged_inside_a_triangle_are_exchanged_back(walk, pair):
    """``a`` and ``b`` of one segment ``a b c`` on each other's points: the pair between them
    keeps its distance and each has one pair off, so neither is doubtful (with ``LUPB``/``LELB``
    the third marker ``LUPA`` is, and has no exchange of its own to make); the exchange back
    fits the segment along the window and leaves both wholly consistent with it."""
    from labeler_service.labeling.boot_match import _doubtful

    tpl, ix, assign, hist = _swapped(walk, *pair)
    have = np.arange(tpl.n)
    doubtful = _doubtful(tpl, have, hist[assign, -1])
    assert not doubtful[[ix[pair[0]], ix[pair[1]]]].any()
    out = _window_exchange(tpl, assign, hist)
    assert np.array_equal(out, np.arange(tpl.n))


def test_a_right_reading_with_a_marker_off_its_segment_is_left_as_it_is(walk):
    """A right reading whose ``RELB`` point is 40 mm off (a pair of one trained body off: the
    elbow and its upper-arm neighbours are suspects) has no exchange that makes it right."""
    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    moved = hist.copy()
    moved[ix["RELB"]] += np.array([0.0, 40.0, 0.0])
    assign = np.arange(tpl.n)
    assert _window_exchange(tpl, assign, moved) is assign


def test_a_triangle_exchange_that_leaves_a_marker_off_its_segment_is_refused(walk):
    """``RUPA``/``RELB`` exchanged, and the point ``RELB`` would hold 40 mm off: the exchange
    back fits better but leaves ``RELB`` off its segment, a reading the model contradicts
    either way."""
    tpl, ix, assign, hist = _swapped(walk, "RUPA", "RELB")
    moved = hist.copy()
    moved[ix["RELB"]] += np.array([40.0, 0.0, 0.0])
    assert _window_exchange(tpl, assign, moved) is assign


def test_a_triangle_exchange_in_contact_is_not_made(walk):
    """Another performer's point beside the segment (a hug): its points may confound the
    evidence, so a triangle exchange waits."""
    tpl, ix, assign, hist = _swapped(walk, "RUPA", "RELB")
    partner = hist[ix["RUPB"], -1][None] + 100.0
    assert _window_exchange(tpl, assign, hist, partner, 250.0) is assign
    assert np.array_equal(_window_exchange(tpl, assign, hist, partner, 50.0), np.arange(tpl.n))


def test_the_extension_rechecks_only_the_subjects_it_is_told_to(walk):
    """A subject the stream's labels placed (a labeled start) keeps its labels; a booted one
    (``checked``) has the pair exchanged back."""
    from labeler_service.labeling.boot import BootConfig, Booter

    model, _ = walk
    tpl, ix, assign, hist = _swapped(walk, "LWRB", "LFIN")
    booter = Booter(model, BootConfig())
    labels = np.full(tpl.n, -1, dtype=np.int64)
    labels[assign] = np.arange(tpl.n)  # point -> marker (P1's offset is 0)
    pts = np.ascontiguousarray(hist[:, -1])
    kept = booter.extend(pts, hist, labels, [0])
    assert np.array_equal(kept, labels)
    fixed = booter.extend(pts, hist, labels, [0], checked=[0])
    assert np.array_equal(fixed, np.arange(tpl.n))


def test_mirror_segments_are_exchanged_back_along_the_window(walk):
    """Two mirror segments read on each other's points (a boot in a near-symmetric pose) are
    exchanged when the window's frames say so; a right reading is left alone."""
    from labeler_service.labeling.boot_match import _window_mirrors

    tpl, names, pts, hist = subject_on_its_points(walk)
    assert tpl.mirrors
    tpl.sided = tpl.mirrors[:1]  # (the simulated body's shape matches are not named twins)
    s1, s2 = tpl.sided[0]
    assign = np.arange(tpl.n)
    assert _window_mirrors(tpl, assign, hist) is assign
    mirrored = assign.copy()
    mirrored[s1], mirrored[s2] = assign[s2], assign[s1]
    assert np.array_equal(_window_mirrors(tpl, mirrored, hist), assign)
    short = hist.copy()
    short[np.concatenate([s1, s2]), : short.shape[1] - 2] = np.nan
    assert _window_mirrors(tpl, mirrored, short) is mirrored  # too short a look
    partner = hist[s1[0], -1][None] + 100.0  # another performer's point beside the segment
    assert _window_mirrors(tpl, mirrored, hist, partner, 250.0) is mirrored
    assert np.array_equal(_window_mirrors(tpl, mirrored, hist, partner, 50.0), assign)


def test_only_mirror_segments_named_as_twins_are_looked_at():
    """A shape match of a shin plate and head markers is no left/right pair; ``LRAD``/``RRAD``
    ... are, marker by marker (not a permutation that only matches shapes)."""
    from labeler_service.labeling.boot_match import _sided

    names = ["LRAD", "LULN", "LHAND", "RRAD", "RULN", "RHAND", "LSHN", "LTIB", "FHD", "BHD"]
    ix = {n: i for i, n in enumerate(names)}

    def seg(*ns):
        return np.array([ix[n] for n in ns])

    arms = (seg("LRAD", "LULN", "LHAND"), seg("RRAD", "RULN", "RHAND"))
    crossed = (seg("LRAD", "LULN", "LHAND"), seg("RULN", "RRAD", "RHAND"))
    odd = (seg("LSHN", "LTIB"), seg("FHD", "BHD"))
    out = _sided([arms, crossed, odd], names)
    assert len(out) == 1 and np.array_equal(out[0][1], arms[1])


def test_a_marker_with_no_frame_in_common_is_no_evidence_and_no_warning(walk):
    """A placed marker whose track shares no frame with the doubtful one's (here a hidden
    point: NaN all along) gives no evidence either way; the median over no frame was numpy's
    'All-NaN slice' warning on the user's console (the suite turns warnings into errors). The
    exchange that has evidence is still made."""
    tpl, ix, assign, hist = _swapped(walk, "LWRB", "LFIN")
    gap = hist.copy()
    gap[ix["C7"]] = np.nan
    out = _window_exchange(tpl, assign, gap)
    assert out[ix["LWRB"]] == ix["LWRB"] and out[ix["LFIN"]] == ix["LFIN"]
