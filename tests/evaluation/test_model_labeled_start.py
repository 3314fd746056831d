"""A model start with labeled init frames (``evaluate``/``label --model M --init-frames N``):
a marker those frames never showed is labeled from its template once it appears. The plain
labeler of the model (``Labeler.from_model``) has no state for such a marker and never labeled
it; in a 5-person pile its free points then went to other performers (95.1 % after 12 labeled
frames, 99.7 % through the booting labeler)."""

from __future__ import annotations

import numpy as np
from labeling.walks import split_walk

from labeler_service.evaluation.scoring import evaluate

HIDDEN_FRAMES = 60  # the marker appears 0.5 s after the stream starts (120 Hz)
INIT = 12


def _walk_with_a_late_marker():
    model, cap = split_walk(3, 6.0, seed=5, rate=120.0)
    late = cap.labels.index("P2:LFRM")
    pos = cap.positions.copy()
    pos[:HIDDEN_FRAMES, late] = np.nan
    return model, cap.with_positions(pos)


def test_a_marker_the_labeled_frames_never_showed_is_labeled_when_it_appears():
    model, cap = _walk_with_a_late_marker()
    visible = int(np.isfinite(cap.positions[HIDDEN_FRAMES:, cap.labels.index("P2:LFRM"), 0]).sum())
    assert visible > 100
    report, _ = evaluate(cap, methods=["online"], init_frames=INIT, seed=1, model=model)
    wrong = {w["marker"]: w["errors"] for w in report["worst_markers"]}
    # the plain labeler of the model left it unlabeled in every frame (errors == visible)
    assert wrong.get("P2:LFRM", 0) <= 0.1 * visible
    assert report["accuracy"] >= 0.99


def test_the_model_start_benchmark_summarizes_worst_and_mean_per_group_and_cell():
    from benchmark_scripts import load_benchmark

    ms = load_benchmark("model_start")
    row = {"group": "tune", "cell": "rate", "max_swap_frames": 0, "ghost_labeled_rate": None}
    rows = [
        row | {"scene": "a", "accuracy_seen": 0.99},
        row | {"scene": "b", "accuracy_seen": 0.97, "max_swap_frames": 12},
        row | {"scene": "c", "cell": "half", "accuracy_seen": 0.5, "ghost_labeled_rate": 0.01},
    ]
    s = ms.summarize(rows)
    assert s["tune"]["rate"]["worst_scene"] == "b"
    assert s["tune"]["rate"]["mean_accuracy_seen"] == 0.98
    assert s["tune"]["rate"]["max_swap_frames"] == 12
    assert s["tune"]["half"]["ghost_labeled_rate_max"] == 0.01
