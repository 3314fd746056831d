"""A completion refused for a reversed chirality quadruple refuses only the segments that
reverse one (boot_match._without_reversed, ``_complete(partial=True)``, used by
``Booter._reclaim``): five hugging performers rebooted after a restarted sender with three
frames lost, one performer's completion put an upper-arm marker on a partner's point (its
forearm then reversed two quadruples) and the whole completion was refused, with it that
performer's own left foot, which the partner's hypothesis held as its right foot (three
markers: a mirror image with no handedness). The reclaim never saw the foot, and the two
performers' feet stayed exchanged for the rest of the take, the stream online."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(5, 6.0, seed=7, rate=RATE, ghosts=2.0)


def _segment_of(tpl, m):
    for seg in tpl.segments:
        if m in seg.tolist():
            return seg
    return np.array([m])


def _case(walk):
    """P1 on its own points with its left foot and the segments of one thick chirality
    quadruple unplaced; a completion ``out`` placing the foot on its own points and the
    quadruple's segments with two of its markers exchanged (the quadruple reversed)."""
    from labeler_service.labeling.boot_match import _reversed_thick, _volumes

    tpl, names, pts, _ = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    stems = ("ANK", "TOE", "HEE", "MT5")
    foot = np.array([ix[n] for n in names if n.startswith("L") and n[1:] in stems])
    assert foot.size >= 3
    det = _volumes(pts[tpl.chirality])
    thick = np.cbrt(np.abs(det)) >= 20.0
    # a quadruple away from the left foot and its segments (not the foot's)
    for q, ok in zip(tpl.chirality, thick, strict=True):
        segs = np.unique(np.concatenate([_segment_of(tpl, int(m)) for m in q]))
        if ok and not np.isin(segs, foot).any() and not np.isin(q, foot).any():
            break
    else:
        pytest.skip("no thick quadruple away from the left foot")
    assign = np.arange(tpl.n)
    assign[foot] = -1
    assign[segs] = -1
    out = np.arange(tpl.n)
    out[q[0]], out[q[1]] = q[1], q[0]  # two vertices exchanged: the volume's sign flips
    assert _reversed_thick(_volumes(pts[out[q]][None]))[0]
    return tpl, pts, assign, out, foot, segs


def test_the_reversed_segments_are_dropped_the_rest_kept(walk):
    from labeler_service.labeling.boot_match import _fill_reversed, _without_reversed

    tpl, pts, assign, out, foot, segs = _case(walk)
    new = np.flatnonzero(out != assign)
    assert _fill_reversed(tpl, assign, pts, new[None], out[new][None])[0]
    got = _without_reversed(tpl, assign, out, pts)
    # the foot stays on its own points, the reversed segments are not placed, nothing else moves
    assert np.array_equal(got[foot], foot)
    assert np.all(got[segs] == -1)
    rest = np.setdiff1d(np.arange(tpl.n), np.concatenate([foot, segs]))
    assert np.array_equal(got[rest], assign[rest])
    kept = np.flatnonzero(got != assign)
    assert not _fill_reversed(tpl, assign, pts, kept[None], got[kept][None])[0]


def test_a_completion_reversing_nothing_is_kept_whole(walk):
    from labeler_service.labeling.boot_match import _without_reversed

    tpl, pts, assign, _, foot, segs = _case(walk)
    right = np.arange(tpl.n)
    assert np.array_equal(_without_reversed(tpl, assign, right, pts), right)


def test_the_reclaim_completes_partially(walk):
    """``Booter._reclaim`` asks for the partial completion (all or nothing lost the foot)."""
    import inspect

    from labeler_service.labeling import boot

    src = inspect.getsource(boot.Booter._reclaim)
    assert "partial=True" in src
