"""The presence check (kernels/step.py ``_presence``): a performer who left cannot keep labels.

Two articulated performers (tests/labeling/scene.py) are labeled at 120 Hz; the second leaves
the volume (its markers vanish) a third of the way in. Ghost points, one at a time and each
living a few frames, appear where it stood and next to the performer who stays - the situation
of the ``ghosts3`` cells with a leaver, where the departed subject's predictions took 46-74 %
of the ghost points. Isolated points cannot show a rigid body's shape, so none may carry the
departed subject's labels, and the performer who stays keeps his. A performer who vanishes at
once (a take that ends) is checked in the frame he vanishes (``presence_drop``), before ghosts
taken there count as his observed markers.
"""

from __future__ import annotations

import numpy as np
import pytest
from labeling.scene import GhostScore, articulated

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.state import Bodies, new_bodies
from labeler_service.labeling.kernels.step import _consistent
from labeler_service.labeling.labeler import Labeler
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.testing.dropout import thinned_errors

RATE = 120.0
INIT = 30
FRAMES = 360
LEAVE = 120


def _run(config: LabelerConfig) -> tuple[int, int, float]:
    """(ghosts given a label of the departed subject, ghosts, accuracy of the one who stays)."""
    rng = np.random.default_rng(11)
    pos, names = articulated(rng, subjects=2, frames=FRAMES, rate=RATE)
    lab = Labeler(names, RATE, config)
    last = pos[LEAVE - 1, 8:].copy()
    ghost = np.full(3, np.nan)
    life = 0
    score = GhostScore(first=8, start=max(INIT, LEAVE))
    for f in range(FRAMES):
        frame = pos[f].copy()
        if f >= LEAVE:
            frame[8:] = np.nan
        vis = np.flatnonzero(np.isfinite(frame[:, 0]))
        pts = frame[vis]
        truth = vis.astype(np.int32)
        if f >= LEAVE:
            if life == 0:  # a new ghost: by a stayer's marker or where the leaver's were
                src = pos[f, rng.integers(0, 8)] if rng.random() < 0.5 else last[rng.integers(8)]
                ghost = src + rng.uniform(-60.0, 60.0, 3)
                life = int(rng.integers(3, 8))
            life -= 1
            pts = np.vstack([pts, ghost[None].astype(np.float32)])
            truth = np.append(truth, -1).astype(np.int32)
        score.feed(lab, rng, f, RATE, pts, truth, INIT)
    return score.result()


def test_departed_subject_takes_no_ghost():
    taken, ghosts, acc = _run(LabelerConfig())
    assert ghosts > 200
    assert taken == 0
    assert acc >= 0.995


def test_without_the_check_the_departed_subject_takes_ghosts():
    """The scene really tempts the departed subject (so the test above can fail)."""
    taken, ghosts, _ = _run(LabelerConfig(presence_min_markers=0))
    assert taken > 0.05 * ghosts


VANISH_RATE, VANISH_INIT, VANISH_AT, VANISH_FRAMES = 120.0, 60, 240, 400


def _vanish(config: LabelerConfig, ghosts: int = 5, seed: int = 3) -> tuple[int, int, float]:
    """(ghosts labeled, ghosts, accuracy of the real points): the second of two simulated
    walkers (51 markers each) vanishes at once - a take that ends, a performer hidden whole -
    and for 20 frames ghost points stand where ``ghosts`` of his markers would be next."""
    cap = simulate_scene(2, VANISH_FRAMES / VANISH_RATE, "walk", seed=seed, rate=VANISH_RATE,
                         ghosts=0.0)  # fmt: skip
    pos = cap.positions.astype(np.float32)
    second = len(cap.labels) // 2
    lab = Labeler(tuple(cap.labels), VANISH_RATE, config)
    rng = np.random.default_rng(seed)
    last = np.flatnonzero(np.isfinite(pos[VANISH_AT - 1, second:, 0])) + second
    at = rng.choice(last, ghosts, replace=False)
    where = 2 * pos[VANISH_AT - 1, at] - pos[VANISH_AT - 2, at]
    taken = n_ghosts = correct = total = 0
    for f in range(VANISH_FRAMES):
        frame = pos[f].copy()
        if f >= VANISH_AT:
            frame[second:] = np.nan
        vis = np.flatnonzero(np.isfinite(frame[:, 0]))
        pts, truth = frame[vis], vis.astype(np.int32)
        if VANISH_AT <= f < VANISH_AT + 20:
            g = where + rng.normal(0.0, 1.0, where.shape)
            pts = np.vstack([pts, g.astype(np.float32)])
            truth = np.append(truth, np.full(ghosts, -1)).astype(np.int32)
        order = rng.permutation(pts.shape[0])
        pts, truth = np.ascontiguousarray(pts[order]), truth[order]
        out = lab.process(pts, f / VANISH_RATE, truth if f < VANISH_INIT else None)
        ghost = truth < 0
        n_ghosts += int(ghost.sum())
        taken += int(np.count_nonzero(out.point_labels[ghost] >= 0))
        if f >= VANISH_INIT:
            real = ~ghost
            correct += int(np.count_nonzero(out.point_labels[real] == truth[real]))
            total += int(real.sum())
    return taken, n_ghosts, correct / total


def test_a_subject_vanishing_at_once_takes_no_ghost_where_it_was():
    """Five ghosts where his markers would be are as many "observed" markers in the next
    frame, so only the vanish itself (5 of 51 labeled) can show he is gone (``presence_drop``)."""
    taken, ghosts, acc = _vanish(LabelerConfig())
    assert ghosts == 100
    assert taken == 0
    assert acc >= 0.995


def test_without_the_drop_check_the_vanished_subject_keeps_the_ghosts():
    taken, ghosts, _ = _vanish(LabelerConfig(presence_drop=0.0))
    assert taken > 0.5 * ghosts


@pytest.mark.parametrize("seed", [2, 3])
def test_a_frame_thinned_for_everyone_is_no_subject_vanishing(seed):
    """Two walkers at 30 Hz whose frame at 2 s keeps a quarter of every performer's points (a
    review's dropout run, :func:`thinned_errors`): the vanish check dropped the labels of
    subjects that fell just under a quarter, and they came back through the narrowest gate.
    The others kept no more than he did, so no one left."""
    on = thinned_errors(LabelerConfig(), 30.0, 0.25, seed=seed)
    assert on == thinned_errors(LabelerConfig(presence_drop=0.0), 30.0, 0.25, seed=seed)


def _one_body(d: float) -> Bodies:
    D = np.full((3, 3), d)
    np.fill_diagonal(D, 0.0)
    return new_bodies(3, [[0, 1, 2]], [D], [np.full((3, 3), 1.0)], 10)


def test_consistent_needs_enough_members_at_their_distances():
    side = 100.0
    pts = np.array([[0, 0, 0], [side, 0, 0], [side / 2, side * np.sqrt(3) / 2, 0]])
    bodies = _one_body(side)
    assigned = np.array([0, 1, 2], dtype=np.int32)
    assert _consistent(0, pts, assigned, bodies, 3, 10.0)
    assert not _consistent(0, pts, np.array([0, 1, -1], dtype=np.int32), bodies, 3, 10.0)
    assert _consistent(0, pts, np.array([0, 1, -1], dtype=np.int32), bodies, 2, 10.0)
    far = pts.copy()
    far[2, 2] = 60.0  # the third member 60 mm off its place: two links ~17 mm too long
    assert not _consistent(0, far, assigned, bodies, 3, 10.0)
    assert _consistent(0, far, assigned, bodies, 3, 20.0)


def _absent_twin(age, groups, need, gone_before, also):
    gone = np.zeros(age.shape[0], dtype=bool)
    for g in groups:
        seen = sum(1 for m in g if age[m] > 0)
        for m in g:
            gone[m] = seen < need or (also and gone_before[m])
    return gone


def test_absent_matches_twin(rng):
    from labeler_service.labeling.kernels.state import new_tracks
    from labeler_service.labeling.kernels.step import _absent

    groups = [[0, 1, 2], [3, 4], [5, 6, 7, 8], [9, 10, 11, 12, 13]]
    tracks = new_tracks(np.full(14, 1e6), np.ones(14, dtype=bool), groups)
    for also in (False, True):
        for _ in range(20):
            tracks.age[:] = rng.integers(0, 3, 14) * (rng.random(14) < 0.4)
            before = rng.random(14) < 0.3
            tracks.gone[:] = before
            _absent(tracks, 3, also)
            assert list(tracks.gone) == list(_absent_twin(tracks.age, groups, 3, before, also))
