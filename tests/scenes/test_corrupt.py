"""Seeded corruptions: shuffle, gaps with truth, drop-outs, ghosts, down-sampling."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import moving_clusters

from labeler_service.capture import Capture
from labeler_service.errors import SceneError
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt, iter_stream


def test_shuffle_keeps_points_and_truth(rng) -> None:
    cap = moving_clusters(rng)
    s = corrupt(cap, CorruptionSpec(seed=3))
    assert s.n_frames == cap.n_frames and s.marker_names == cap.labels
    for f in (0, 50, 119):
        np.testing.assert_array_equal(s.points[f], cap.positions[f, s.truth[f]])
    # Shuffled: the order is not the column order in general.
    assert any(not np.array_equal(t, np.sort(t)) for t in s.truth[:10])


def test_seeded_and_reproducible(rng) -> None:
    cap = moving_clusters(rng)
    spec = CorruptionSpec(gaps=1, gap_frames=5, ghosts=2.0, jitter_mm=0.5, seed=9)
    a, b = corrupt(cap, spec), corrupt(cap, spec)
    for f in range(cap.n_frames):
        np.testing.assert_array_equal(a.points[f], b.points[f])
    c = corrupt(cap, CorruptionSpec(gaps=1, gap_frames=5, ghosts=2.0, jitter_mm=0.5, seed=10))
    assert any(
        a.points[f].shape != c.points[f].shape or not np.array_equal(a.points[f], c.points[f])
        for f in range(cap.n_frames)
    )


def test_gaps_longer_than_the_scene_are_refused_not_skipped(rng) -> None:
    """``--gaps 1 --gap-frames 600`` on a 200-frame take made no gap at all and scored as the
    gap-free run (a hostile run: same accuracy, ``recovery_rate`` null, exit 0); ``--occlude``
    and ``--leave`` already refuse what does not fit."""
    cap = moving_clusters(rng, frames=200)
    with pytest.raises(SceneError, match=r"--gaps 1 x 171 frames does not fit in 170 frames"):
        corrupt(cap, CorruptionSpec(gaps=1, gap_frames=171, protect_frames=30, seed=1))
    s = corrupt(cap, CorruptionSpec(gaps=1, gap_frames=170, protect_frames=30, seed=1))
    assert s.removed[30:].all(axis=0).any()  # the one gap that fits: every frame after init


def test_gaps_remove_contiguous_runs_after_protected_window(rng) -> None:
    cap = moving_clusters(rng, frames=200)
    s = corrupt(cap, CorruptionSpec(gaps=2, gap_frames=10, protect_frames=30, seed=1))
    assert not s.removed[:30].any()
    # Every gap event removes 2 markers per subject for 10 frames.
    per_frame = s.removed.sum(axis=1)
    assert set(np.unique(per_frame[30:])) <= {0, 4}
    assert per_frame[30:40].tolist() == [4] * 10
    for f in range(30, 200):
        gone = np.flatnonzero(s.removed[f])
        assert not np.isin(gone, s.truth[f]).any()
    # Truth of removed samples is kept for recovery scoring.
    assert np.isfinite(s.positions[s.removed]).all()


def test_ghosts_average_near_requested_rate(rng) -> None:
    cap = moving_clusters(rng, frames=600)
    s = corrupt(cap, CorruptionSpec(ghosts=3.0, protect_frames=50, seed=2))
    n_ghosts = np.array([(t < 0).sum() for t in s.truth])
    assert n_ghosts[:50].sum() == 0
    assert 1.5 < n_ghosts[50:].mean() < 4.5
    # Ghosts lie near the performers: within 150 mm of some true marker.
    f = int(np.argmax(n_ghosts))
    g = s.points[f][s.truth[f] < 0]
    d = np.linalg.norm(g[:, None] - cap.positions[f][None], axis=2).min(axis=1)
    assert (d < 150).all()


def test_downsample_and_dropouts(rng) -> None:
    cap = moving_clusters(rng, frames=400)
    s = corrupt(cap, CorruptionSpec(downsample=4, dropouts=0.1, seed=4))
    assert s.n_frames == 100 and s.rate == pytest.approx(30.0)
    assert 0.03 < s.removed.mean() < 0.2
    np.testing.assert_allclose(s.positions[1], cap.positions[4])


def test_ghost_columns_are_fed_with_truth_minus_one(rng) -> None:
    cap = moving_clusters(rng, subjects=1, frames=20)
    ghost = np.full((20, 1, 3), np.nan, dtype=np.float32)
    ghost[5:8, 0] = [0.0, 0.0, 500.0]
    both = Capture.concat_markers([cap, Capture(ghost, ("*0",), cap.rate)])
    plan, frames = iter_stream(both, CorruptionSpec(seed=0))
    assert plan.marker_names == cap.labels
    counts = [int((fr.truth < 0).sum()) for fr in frames]
    assert counts[5:8] == [1, 1, 1] and sum(counts) == 3


def test_bad_settings_raise() -> None:
    with pytest.raises(SceneError, match="downsample"):
        CorruptionSpec(downsample=0)
    with pytest.raises(SceneError, match="ghosts"):
        CorruptionSpec(ghosts=-1)


def test_occlude_hides_a_body_part_that_reappears_one_marker_at_a_time(rng) -> None:
    cap = moving_clusters(rng, subjects=2, markers=8, frames=400)
    spec = CorruptionSpec(occlude=3, occlude_frames=15, protect_frames=40, seed=5)
    s = corrupt(cap, spec)
    assert not s.removed[:40].any()
    assert len(s.occlusions) == 6  # 3 per subject
    firsts = [f0 for f0, _ in s.occlusions]
    for f0, order in s.occlusions:
        hidden = np.asarray(order)
        assert hidden.size >= 1
        assert len({int(s.marker_names[m][1]) for m in hidden}) == 1  # one subject ("S0:m3")
        # every marker within 120 mm of some hidden marker's centre is hidden: the part is
        # the 120 mm ball around one of them
        pos = s.positions[f0]
        cols = np.array(
            [i for i, n in enumerate(s.marker_names) if n[:2] == s.marker_names[hidden[0]][:2]]
        )
        balls = [
            set(cols[np.linalg.norm(pos[cols] - pos[c], axis=1) <= 120.0].tolist()) for c in hidden
        ]
        assert set(hidden.tolist()) in balls
        # hidden together for 15 frames, then back one at a time, 2 frames apart
        assert s.removed[f0 : f0 + 15, hidden].all()
        assert not s.removed[f0 - 1, hidden].any() or f0 - 1 in firsts
        back = [f0 + int(np.argmin(s.removed[f0:, m])) for m in hidden]
        assert back == [f0 + 15 + 2 * k for k in range(hidden.size)]
    for f in range(s.n_frames):
        assert not np.isin(np.flatnonzero(s.removed[f]), s.truth[f]).any()
    again = corrupt(cap, spec)
    assert again.occlusions == s.occlusions
    other = corrupt(cap, CorruptionSpec(occlude=3, occlude_frames=15, protect_frames=40, seed=6))
    assert other.occlusions != s.occlusions


def test_occlude_events_spread_over_the_stream(rng) -> None:
    cap = moving_clusters(rng, subjects=1, markers=6, frames=600)
    s = corrupt(cap, CorruptionSpec(occlude=4, occlude_frames=10, protect_frames=50, seed=2))
    firsts = sorted(f0 for f0, _ in s.occlusions)
    assert len(firsts) == 4 and firsts[0] >= 50
    # one event per quarter of the frames after the window: no two in one quarter
    quarters = np.floor((np.asarray(firsts) - 50) / ((600 - 50 - 10 - 2 * 5) / 4))
    assert len(set(quarters.tolist())) == 4


def test_occlude_that_cannot_fit_is_an_error(rng) -> None:
    cap = moving_clusters(rng, subjects=1, markers=6, frames=60)
    with pytest.raises(SceneError, match="--occlude"):
        corrupt(cap, CorruptionSpec(occlude=2, occlude_frames=40, protect_frames=20))
    with pytest.raises(SceneError, match="--occlude-frames must be >= 1"):
        CorruptionSpec(occlude=1, occlude_frames=0)


# ------------------------------------------------ what the user asked is done or said
def _mixed(rng, frames: int = 200) -> Capture:
    """Subject S0 with 8 markers beside S1 with 3."""
    big = moving_clusters(rng, subjects=1, markers=8, frames=frames)
    small = moving_clusters(rng, subjects=1, markers=3, frames=frames)
    small = Capture(small.positions + 2000.0, ("S1:m0", "S1:m1", "S1:m2"), small.rate)
    return Capture.concat_markers([big, small])


def test_more_gaps_than_any_subject_has_markers_are_refused(rng) -> None:
    """``--gaps 1000`` was taken as "every marker of each subject" without a word."""
    with pytest.raises(SceneError, match=r"--gaps 9: no subject has that many markers "
                       r"\(S0 8, S1 3\).* at most 8 here"):  # fmt: skip
        corrupt(_mixed(rng), CorruptionSpec(gaps=9, gap_frames=10, protect_frames=30))


def test_more_gaps_than_some_subject_has_are_done_and_said(rng) -> None:
    s = corrupt(_mixed(rng), CorruptionSpec(gaps=5, gap_frames=10, protect_frames=30, seed=1))
    assert s.notes == ["--gaps 5: S1 (3) has fewer markers: each of their gap events removes all "
                       "of them"]  # fmt: skip
    per_frame = s.removed[30:40].sum(axis=1)
    assert per_frame.tolist() == [5 + 3] * 10
    assert corrupt(_mixed(rng), CorruptionSpec(gaps=3, gap_frames=10)).notes == []


def test_leave_seconds_shorter_than_a_frame_are_refused(rng) -> None:
    """0.001 s at 120 Hz was made a one-frame (8.3 ms) absence without a word."""
    cap = moving_clusters(rng, frames=300)
    with pytest.raises(SceneError, match=r"--leave-seconds 0.001 is shorter than a frame "
                       r"\(8.33 ms at 120 Hz\)"):  # fmt: skip
        corrupt(cap, CorruptionSpec(leave=1, leave_seconds=0.001, protect_frames=30))
    s = corrupt(cap, CorruptionSpec(leave=1, leave_seconds=1 / 120, protect_frames=30))
    ((_, gone, back),) = s.departures
    assert back - gone == 1


def test_an_occlusion_drawn_where_the_subject_is_unseen_is_drawn_again(rng) -> None:
    """An event whose frame showed none of the subject's markers was dropped without a word
    (``--occlude 2`` made one occlusion, or none); it is drawn among the frames of its slice
    that show the subject, and a slice without any is noted."""
    cap = moving_clusters(rng, subjects=1, markers=6, frames=300)
    pos = cap.positions.copy()
    pos[40:290:2] = np.nan  # the subject is seen in every other frame only
    spec = CorruptionSpec(occlude=2, occlude_frames=5, protect_frames=40)
    for seed in range(6):  # (some seed draws an unseen frame)
        s = corrupt(cap.with_positions(pos), CorruptionSpec(**{**spec.__dict__, "seed": seed}))
        assert len(s.occlusions) == 2 and s.notes == [], seed
        assert all(np.isfinite(pos[f0, 0, 0]) for f0, _ in s.occlusions)
    pos[40:170] = np.nan  # absent through the first slice
    s = corrupt(cap.with_positions(pos), spec)
    assert len(s.occlusions) == 1
    assert s.notes == ["--occlude 2: S0 shows no marker in 1 slice of the frames an event is "
                       "drawn in (gone or occluded throughout): 1 of 2 events"]  # fmt: skip


def test_evaluate_prints_what_a_corruption_could_not_do(rng, tmp_path, capsys) -> None:
    import json

    from labeler_service.capture import write_capture
    from labeler_service.cli.main import main

    path = tmp_path / "mixed.npz"
    write_capture(_mixed(rng), path)
    argv = ["evaluate", str(path), "--method", "closest-point", "--init-frames", "30",
            "--gap-frames", "10", "--no-progress", "--json"]  # fmt: skip
    assert main([*argv, "--gaps", "5"]) == 0
    out, err = capsys.readouterr()
    assert "note: --gaps 5: S1 (3) has fewer markers" in err
    assert any("--gaps 5" in n for n in json.loads(out.splitlines()[-1])["notes"])
    assert main([*argv, "--gaps", "1000"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --gaps 1000: no subject has that many markers")


@pytest.mark.parametrize(
    ("spec", "what"),
    [
        (CorruptionSpec(gaps=2, gap_frames=10, protect_frames=30), "--gaps 2"),
        (CorruptionSpec(occlude=1, occlude_frames=10, protect_frames=30), "--occlude 1"),
    ],
)
def test_a_per_subject_corruption_of_unlabeled_tracks_only_is_refused(rng, spec, what) -> None:
    """A capture of unlabeled tracks only (``raw_unlabeled_kneel_to_run_240hz.c3d``): ``replay
    --gaps 2`` and ``evaluate --gaps 2`` ended in a traceback ("min() arg is an empty
    sequence"); ``--occlude`` made no event without a word."""
    tracks = moving_clusters(rng, subjects=1, markers=4, frames=200)
    cap = Capture(tracks.positions, ("*0", "*1", "*2", "*3"), tracks.rate)
    with pytest.raises(SceneError, match=f"{what}: the capture has no labeled marker"):
        corrupt(cap, spec)
