"""The raw-take benchmark's track scoring: tracks are runs of one column, a label change along
a track is an error unless the old label went to another point of that frame."""

from __future__ import annotations

import numpy as np
from benchmark_scripts import load_benchmark

raw = load_benchmark("raw_unlabeled")


def test_runs_split_a_column_at_its_gaps():
    vis = np.array([[1, 1], [1, 0], [0, 1], [1, 1]], dtype=bool)
    track = raw._runs(vis)
    assert track[0, 0] == track[1, 0] != track[3, 0]  # column 0: frames 0-1, then 3
    assert track[0, 1] != track[2, 1] == track[3, 1]  # column 1: frame 0, then 2-3
    assert (track[~vis] == -1).all()
    assert np.unique(track[vis]).size == 4


def test_a_change_is_an_error_unless_the_old_label_moved_elsewhere():
    vis = np.ones((6, 2), dtype=bool)
    label = np.array([[0, 1], [0, 1], [-1, 1], [2, 1], [2, 0], [2, 0]])
    scores, _, _ = raw.track_scores(label, vis, long_frames=6)
    # column 0: 0 -> (unlabeled) -> 2 while label 0 is nowhere: an error;
    # column 1: 1 -> 0 in frame 4: label 1 is nowhere either: an error
    assert scores["label_changes"] == 2 and scores["label_change_errors"] == 2
    label[4:, 0] = 1  # the old label 1 went to column 0: the raw data had joined two markers
    scores, _, long = raw.track_scores(label, vis, long_frames=6)
    assert scores["label_changes"] == 3  # column 0 now also changes 2 -> 1, an error
    assert scores["label_change_errors"] == 2  # column 1's change is not an error any more
    assert long.all() and scores["labeled_fraction"] == round(11 / 12, 4)


def test_short_tracks_are_left_out_of_the_long_fraction():
    vis = np.array([[1, 1], [1, 0], [1, 0]], dtype=bool)
    label = np.array([[0, -1], [0, -1], [0, -1]])
    scores, _, long = raw.track_scores(label, vis, long_frames=2)
    assert scores["labeled_fraction_long_tracks"] == 1.0
    assert scores["labeled_fraction"] == 0.75 and not long[0, 1]


def test_agreement_reads_each_track_by_the_other_runs_most_frequent_label():
    vis = np.ones((5, 3), dtype=bool)
    vis[2, 2] = False  # column 2: two tracks, frames 0-1 and 3-4
    ref = np.array([[-1, -1, -1], [-1, -1, -1], [0, 1, -1], [0, 1, 2], [0, 3, 2]])
    # column 0 reads 0 from frame 0 (agrees, 2 samples before the reference's first label);
    # column 1 reads 0 where the reference has 1 (its most frequent label on that track);
    # column 2's first track has no reference label: not counted
    label = np.array([[0, 0, 5], [0, 0, 5], [0, 0, -1], [0, 1, 2], [0, 1, 2]])
    out = raw.track_agreement(label, ref, vis, rate=10.0)
    assert out["reference_first_label_s"] == 0.2
    assert out["samples_on_reference_tracks"] == 12
    assert out["agree"] == 9 and out["disagree"] == 3
    assert out["agree_before_reference_boot"] == 2 and out["disagree_before_reference_boot"] == 2
    assert out["worst_pairs"] == [[1, 0, 3]]
