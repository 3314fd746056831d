"""The joint fill (boot_match._fill) with a model that is stale for a joint: a trained body
the stream contradicts stops voting on chirality (_stale_pairs), and a fill whose best map is
not unique still places the markers every rival map agrees on."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from labeling.walks import split_walk, subject_with_leftover

from labeler_service.labeling.boot import BootConfig

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(5, 6.0, seed=7, rate=RATE, ghosts=2.0)


def _case(walk, leftover: tuple[str, ...]):
    """P1 on its true points except ``leftover`` markers (free, tracked), in the first frame
    whose 12-frame window sees all of them; point ``i`` is marker ``i``."""
    return subject_with_leftover(walk, leftover)


def _stale_model(walk, tpl, ix, pts, shift: float, loose: bool):
    """P1's template with one thick chirality quadruple over the upper arm and elbow
    ``[LUPA, LUPB, LELB, LFRM]`` that the true points reverse (as if trained in a pose where
    the elbow sat on the other side), the trained body pair ``LUPA-LELB`` ``shift`` mm longer
    than in the stream and, with ``loose``, the body ``[LUPA, LUPB, LELB]`` not rigid as a
    whole in training (``LUPB-LELB`` ``A`` 12 mm: the trainer completed it across a joint)."""
    from labeler_service.labeling.boot_match import _prepare

    model, _ = walk
    subj = model.subjects[0]
    D, A = subj.D_array(), subj.A_array()
    a, b, c = ix["LUPA"], ix["LELB"], ix["LUPB"]
    D[a, b] += shift
    D[b, a] += shift
    if loose:
        A[b, c] = A[c, b] = 12.0
    edited = subj.model_copy(update={"D": D.tolist(), "A": A.tolist()})
    both = model.model_copy(update={"subjects": [edited, *model.subjects[1:]]})
    t = _prepare(both, BootConfig())[0]
    assert t.strict[a, b] and t.whole[a, b] != loose
    quad = [ix["LUPA"], ix["LUPB"], ix["LELB"], ix["LFRM"]]
    p = pts[quad]
    if np.linalg.det(p[1:] - p[:1]) > 0:
        quad = [quad[0], quad[1], quad[3], quad[2]]
    p = pts[quad]
    det = np.linalg.det(p[1:] - p[:1])
    assert det < 0 and np.cbrt(-det) >= 20.0  # reversed and thick on the true points
    t.chirality = np.array([quad], dtype=np.int64)
    t.chiral_local = np.array([True])
    return t


def test_stale_pairs_are_body_pairs_no_candidate_keeps(walk):
    """A rigid pair of a trained body that was not rigid as a whole, between a leftover and a
    placed marker, is stale when no candidate point is at its trained distance; pairs the
    stream keeps, pairs a wholly rigid body holds (a marker placed wrong) and pairs across
    bodies (a pose) are not."""
    from labeler_service.labeling.boot_match import _stale_pairs

    tpl, ix, assign, pts, hist, free, miss = _case(walk, ("LELB", "LWRA", "LFIN"))
    have = np.flatnonzero(assign >= 0)
    dp = np.linalg.norm(pts[miss][:, None] - pts[have][None], axis=2)
    dc = np.linalg.norm(pts[miss][:, None] - pts[miss][None], axis=2)
    assert not _stale_pairs(tpl, miss, have, dp, dc).any()
    for shift, loose in ((0.0, True), (40.0, False)):
        t = _stale_model(walk, tpl, ix, pts, shift, loose)
        assert not _stale_pairs(t, miss, have, dp, dc).any()
    stale = _stale_pairs(_stale_model(walk, tpl, ix, pts, 40.0, True), miss, have, dp, dc)
    a, b = ix["LUPA"], ix["LELB"]
    assert stale[a, b] and stale[b, a]
    assert np.count_nonzero(stale) == 2
    u = copy.deepcopy(tpl)
    c = ix["LKNE"]
    assert not u.strict[b, c]
    u.D[b, c] += 200.0
    u.D[c, b] += 200.0
    assert not _stale_pairs(u, miss, have, dp, dc).any()


def test_a_stale_body_does_not_refuse_the_fill_by_chirality(walk):
    """The reversed quadruple refuses the fill while its body holds its trained distances (a
    mirror image keeps every distance) or is rigid as a whole (then a placed marker is wrong),
    not when the stream contradicts a body trained across a joint."""
    from labeler_service.labeling.boot_match import _fill

    tpl, ix, assign, pts, hist, free, miss = _case(walk, ("LELB", "LWRA", "LFIN"))
    none, cfg = np.zeros((0, 3)), BootConfig()
    assert np.array_equal(_fill(tpl, assign, pts, hist, free, none, cfg), np.arange(tpl.n))
    for shift, loose in ((0.0, True), (40.0, False)):
        t = _stale_model(walk, tpl, ix, pts, shift, loose)
        assert np.array_equal(_fill(t, assign, pts, hist, free, none, cfg), assign)
    t = _stale_model(walk, tpl, ix, pts, 40.0, True)
    assert np.array_equal(_fill(t, assign, pts, hist, free, none, cfg), np.arange(tpl.n))


def _twins_alike(tpl, i: int, j: int):
    """The template with markers ``i`` and ``j`` indistinguishable: the same trained
    distances and tolerances to every other marker, no chirality or twin witnesses."""
    t = copy.deepcopy(tpl)
    for name in ("D", "A", "tol", "link", "strict", "bound"):
        old = getattr(tpl, name)
        m = getattr(t, name)
        m[j, :] = old[i, :]
        m[:, j] = old[:, i]
        m[i, j] = m[j, i] = old[i, j]
        m[j, j] = old[j, j]
    t.chirality = np.zeros((0, 4), dtype=np.int64)
    t.chiral_local = np.zeros(0, dtype=bool)
    t.twins = np.zeros((0, 4), dtype=np.int64)
    return t


def test_a_fill_that_is_not_unique_places_what_every_rival_agrees_on(walk):
    """With two leftover markers the model cannot tell apart, the maps exchanging them tie:
    the other leftover marker is placed (every rival map agrees on it and a pair of one
    trained body holds at its point), the two wait. A marker every rival agrees on but with
    no such pair (a forearm marker whose body partners are the two waiting) waits too."""
    from labeler_service.labeling.boot_match import _fill

    none, cfg = np.zeros((0, 3)), BootConfig()
    tpl, ix, assign, pts, hist, free, miss = _case(walk, ("LELB", "LWRA", "LWRB"))
    assert np.array_equal(_fill(tpl, assign, pts, hist, free, none, cfg), np.arange(tpl.n))
    t = _twins_alike(tpl, ix["LWRA"], ix["LWRB"])
    want = np.arange(tpl.n)
    want[[ix["LWRA"], ix["LWRB"]]] = -1
    assert np.array_equal(_fill(t, assign, pts, hist, free, none, cfg), want)
    tpl, ix, assign, pts, hist, free, miss = _case(walk, ("LELB", "LFRM", "LWRA", "LWRB"))
    assert np.array_equal(_fill(tpl, assign, pts, hist, free, none, cfg), np.arange(tpl.n))
    t = _twins_alike(tpl, ix["LWRA"], ix["LWRB"])
    assert not t.strict[ix["LFRM"], ix["LELB"]]
    want[ix["LFRM"]] = -1
    assert np.array_equal(_fill(t, assign, pts, hist, free, none, cfg), want)
    # nothing agreed (only the two twins left): nothing placed
    tpl, ix, assign, pts, hist, free, _ = _case(walk, ("LWRA", "LWRB"))
    t = _twins_alike(tpl, ix["LWRA"], ix["LWRB"])
    assert np.array_equal(_fill(t, assign, pts, hist, free, none, cfg), assign)
