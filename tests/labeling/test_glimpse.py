"""Markers a labeled window glimpsed in 1-2 frames (``train_subject(glimpsed=True)``, the
window model's trainer): each joins a body with its nearest usable markers, so the labeled
start can label it; the labeler trained in place never does."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture
from labeler_service.labeling.training import train_subject


def _frames(rng, f=20, m=8):
    base = rng.normal(scale=80.0, size=(m, 3))
    return (base + rng.normal(scale=0.5, size=(f, m, 3))).astype(np.float64)


def test_a_glimpsed_marker_joins_a_body_of_its_nearest_neighbours(rng):
    pos = _frames(rng)
    pos[:-2, 6] = np.nan  # seen in the last 2 frames only
    pos[:, 7] = np.nan  # never seen
    pos[-1, 7] = np.nan
    names = [f"m{i}" for i in range(8)]
    plain = train_subject("s", names, pos, 100.0, max_size=4)
    assert not any(6 in b for b in plain.bodies)
    assert not np.isfinite(plain.D_array()[6, :6]).any()
    t = train_subject("s", names, pos, 100.0, glimpsed=True, max_size=4)
    (body,) = [b for b in t.bodies if 6 in b]
    assert len(body) == 4 and 7 not in body
    d = np.linalg.norm(pos[-2:, 6, None] - pos[-2:, :6], axis=2).mean(axis=0)
    nearest = set(np.argsort(d)[:3].tolist())
    assert set(body) - {6} == nearest
    D, A = t.D_array(), t.A_array()
    for k in nearest:
        assert D[6, k] == pytest.approx(d[k], rel=1e-6)
        assert A[6, k] == pytest.approx(6.0)  # the body rule's tolerance: rigid at the edge
    assert not any(7 in b for b in t.bodies)  # never seen: nothing to place it by
    # the bodies of the usable markers are the same as without the rule
    assert [b for b in t.bodies if 6 not in b] == plain.bodies


@pytest.mark.parametrize("others_seen", [1, 2])
def test_a_glimpse_without_three_usable_neighbours_gets_no_body(rng, others_seen):
    """Seen once, in a frame where only one or two usable markers are seen: on two, a triangle
    hinged on them could be read either way round (a take whose markers were nearly all seen
    in one init frame only: 4,726 wrong labels of 15,684 through such triangles)."""
    pos = _frames(rng, m=6)
    pos[:-1, 5] = np.nan
    pos[-1, others_seen:5] = np.nan
    t = train_subject("s", [f"m{i}" for i in range(6)], pos, 100.0, glimpsed=True)
    assert not any(5 in b for b in t.bodies)


def test_the_labeled_start_labels_markers_its_window_glimpsed():
    """Three markers of one walker seen in the last 2 of 50 init frames: trained in place they
    stay unlabeled for the whole take; through the window model they are labeled."""
    from labeler_service.evaluation.scoring import evaluate
    from labeler_service.scenes.simulate import simulate_scene

    cap = simulate_scene(performers=2, seconds=3.0, scenario="walk", seed=1, rate=120.0)
    cols = [i for i, n in enumerate(cap.labels) if n.startswith("P2:")][:3]
    pos = cap.positions.copy()
    pos[:48, cols] = np.nan
    scene = Capture(pos, cap.labels, cap.rate)
    plain, _ = evaluate(scene, methods=["online"], labeled_start="labeler")
    window, _ = evaluate(scene, methods=["online"])
    assert window["settings"]["labeled_start"] == "model"
    assert plain["errors"]["unlabeled"] > 0.9 * 3 * (cap.n_frames - 50)
    assert window["errors"]["unlabeled"] <= 0.01 * plain["errors"]["unlabeled"]
    assert window["errors"]["same_subject"] == window["errors"]["cross_subject"] == 0
