"""Acceptance scene (a) of issue #3: two real CMU takes composed at 300 mm, scored like
``mocap-labeler evaluate`` (real data; a few seconds)."""

from __future__ import annotations

import pytest

from labeler_service.evaluation.scoring import evaluate
from labeler_service.scenes.compose import TakeSpec, compose_scene


@pytest.fixture(scope="module")
def scene_a(real_path):
    takes = [
        TakeSpec(path=real_path("cmu_01_01_playground.c3d"), start=600),
        TakeSpec(path=real_path("cmu_02_05_expressions.c3d")),
    ]
    return compose_scene(takes, radius=300.0, frames=1200, seed=7)


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.parametrize(
    ("settings", "floor"),
    [({}, 0.995), ({"downsample": 4}, 0.985), ({"ghosts": 3.0}, 0.995)],
)
def test_scene_a_beats_the_baseline(scene_a, settings, floor):
    report, _ = evaluate(scene_a, ["online", "closest-point"], **settings)
    assert report["accuracy"] >= floor
    assert report["accuracy"] > report["baseline_accuracy"]
    if "ghosts" in settings:
        assert report["ghost_labeled_rate"] <= 0.01


@pytest.mark.realdata
@pytest.mark.slow
def test_scene_a_gaps_are_recovered(scene_a):
    report, _ = evaluate(scene_a, ["online"], gaps=2, gap_frames=20)
    assert report["recovery_rate"] >= 0.99
    assert report["recovery_mean_mm"] <= 12.0
