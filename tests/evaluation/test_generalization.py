"""The cross-take benchmark's matrix: groups never mix, tennis stays together, starts skip
empty frames, every take has several partners."""

from __future__ import annotations

import numpy as np
import pytest
from benchmark_scripts import load_benchmark

gen = load_benchmark("generalization")


def test_split_keeps_the_tennis_data_together():
    groups = {t.key: t.group for t in gen.TAKES}
    tennis = [g for k, g in groups.items() if "tennis" in k or "two_players" in k]
    assert len(tennis) == 2 and len(set(tennis)) == 1
    clusters = [g for k, g in groups.items() if "clusters_73" in k]
    assert len(clusters) == 2 and len(set(clusters)) == 1
    assert not any("raw_unlabeled" in k for k in groups)
    assert set(groups.values()) == set(gen.GROUPS)


@pytest.mark.realdata
def test_matrix_scenes(real_path):
    real_path("tennis_serve_pig_39markers_50hz.c3d")  # skips without the real data
    scenes = gen.matrix("all", quick=False, seeds=2)
    pairs = [s for s in scenes if len(s.takes) == 2]
    alone = [s for s in scenes if len(s.takes) == 1]
    assert len(alone) == len(gen.TAKES)
    for s in pairs:
        assert {t.group for t, _ in s.takes} == {s.group}
    partners: dict[str, set[str]] = {}
    for s in pairs:
        a, b = (t.key for t, _ in s.takes)
        partners.setdefault(a, set()).add(b)
        partners.setdefault(b, set()).add(a)
    assert all(len(p) >= 3 for p in partners.values())
    assert len({s.seed for s in pairs}) == len(pairs)
    assert {s.radius for s in pairs} == set(gen.RADII)
    bts = next(s for s in alone if "gait_bts" in s.name)
    assert bts.takes[0][1] >= 239  # the BTS take is empty before frame 239
    tennis = next(s for s in pairs if "tennis" in s.takes[0][0].key)
    assert tennis.rate() == 50.0
    assert gen.matrix("holdout", quick=True, seeds=2)[0].group == "holdout"


@pytest.mark.realdata
def test_crowd_scenes_hold_that_many_distinct_takes_of_one_group(real_path):
    real_path("tennis_serve_pig_39markers_50hz.c3d")  # skips without the real data
    scenes = gen.matrix("all", quick=False, seeds=1, crowd=4)
    assert len(scenes) == len(gen.TAKES)  # every take starts one crowd per seed, none alone
    for s in scenes:
        keys = [t.key for t, _ in s.takes]
        assert len(keys) == 4 == len(set(keys)) and {t.group for t, _ in s.takes} == {s.group}
        assert "crowd4" in s.name
    per_take = {t.key: sum(t.key in [x.key for x, _ in s.takes] for s in scenes) for t in gen.TAKES}
    assert set(per_take.values()) == {4}
    with pytest.raises(gen.MocapError, match="--crowd 8"):
        gen.matrix("tune", quick=False, seeds=1, crowd=8)


def test_scored_span_counts_the_interpolated_neighbour():
    assert gen.scored_span(10, 5, 1.0) == (10, 15)  # same rate: frames 10..14
    assert gen.scored_span(10, 5, 2.0) == (10, 19)  # decimation: 10, 12, .., 18
    assert gen.scored_span(0, 3, 2.4) == (0, 6)  # 0, 2.4, 4.8: 4.8 reads frames 4 and 5


def _frames_read(start: int, frames: int, step: float, n_frames: int) -> set[int]:
    """The take frames ``compose`` reads for ``frames`` scene frames from ``start`` (worked out
    here independently of ``scored_span``): each sample's floor, and the next frame when the
    sample falls between two."""
    at = start + np.arange(frames) * step
    low = np.floor(at + 1e-9).astype(int)
    between = (at - low) > 1e-9
    read = set(low.tolist()) | set((low[between] + 1).tolist())
    return {f for f in read if f < n_frames}


@pytest.mark.realdata
def test_boot_training_segments_never_overlap_the_scored_ones(real_path):
    real_path("tennis_serve_pig_39markers_50hz.c3d")  # skips without the real data
    planned = skipped = 0
    for scene in gen.matrix("all", quick=False, seeds=2):
        frames, plan = gen.boot_frames(scene, scene.frames(8.0, 1200))
        assert frames <= scene.frames(8.0, 1200)
        if plan is None:
            skipped += 1
            continue
        planned += 1
        rate = scene.rate()
        assert [t.key for t, _ in plan.takes] == [t.key for t, _ in scene.takes]  # same names
        for (take, start), (_, a) in zip(scene.takes, plan.takes, strict=True):
            cap = gen.load(take)[0]
            scored = _frames_read(start, frames, cap.rate / rate, cap.n_frames)
            train = _frames_read(a, plan.frames, cap.rate / rate, cap.n_frames)
            assert not scored & train, (scene.name, take.key)
            assert (max(train) - min(train) + 1) / cap.rate >= gen.BOOT_MIN_TRAIN_S - 2.0 / rate
    assert planned > 3 * skipped  # most scenes have room for a training segment


def test_boot_summary_counts_subjects_and_models_missing_their_markers():
    def row(scene, boot_s, missing):
        return {
            "scene": scene,
            "takes": ["x"],
            "boot_minus_window": None,
            "model_missing_markers": missing,
            "boot": {
                "boot_s_max": None if None in boot_s.values() else max(boot_s.values()),
                "boot_s": boot_s,
                "ghost_labeled_rate": None,
                "absent_labeled": 0,
                "identity_swaps": 0,
            },
        }

    rows = [
        row("s0", {"A": 0.1, "B": None}, ["B:knee"]),  # B's model lacks a marker
        row("s1", {"A": None, "B": 0.2}, []),
    ]
    out = gen.boot_summary(rows)
    assert out["subjects_booted"] == [2, 4]
    # B in s0 is left out of the second count: its model cannot name every marker it shows
    assert out["subjects_booted_model_complete"] == [2, 3]
    assert out["never_booted"] == ["s0", "s1"]
