"""The evaluate harness and its JSON contract."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic import moving_clusters

from labeler_service.capture import write_capture
from labeler_service.cli.main import main
from labeler_service.errors import MocapError, SceneError
from labeler_service.evaluation.scoring import evaluate, resolve_methods, score_labeler
from labeler_service.labeling.frame import LabeledFrame, MarkerState
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt

CONTRACT_KEYS = {
    "accuracy",
    "baseline_accuracy",
    "ghost_labeled_rate",
    "recovery_mean_mm",
    "recovery_p95_mm",
    "recovery_mean_ratio",
    "ms_per_frame_p50",
    "ms_per_frame_p99",
    "frames",
    "subjects",
    "markers",
}


class _Oracle:
    """Labels with the truth it is handed, recovers removed markers with a fixed error."""

    def __init__(
        self, stream, error_mm: float = 0.0, wrong_every: int = 0, wrong_before: int | None = None
    ) -> None:
        self.stream, self.error, self.wrong_every, self.f = stream, error_mm, wrong_every, 0
        self.wrong_before = wrong_before
        self.marker_names = stream.marker_names

    def warmup(self) -> None:
        pass

    def body_extent(self) -> np.ndarray:
        # Like the online labeler: bodies exist only after the training window.
        value = 100.0 if self.f > 0 else np.nan
        return np.full(len(self.marker_names), value)

    def process(self, points, t, labels=None) -> LabeledFrame:
        f = self.f
        self.f += 1
        truth = self.stream.truth[f].copy()
        early = self.wrong_before is None or f < self.wrong_before
        if self.wrong_every and f % self.wrong_every == 0 and early:
            truth[truth >= 0] = -1
        m = len(self.marker_names)
        state = np.zeros(m, np.uint8)
        pos = np.full((m, 3), np.nan, np.float32)
        seen = truth[truth >= 0]
        state[seen] = MarkerState.OBSERVED
        gone = np.flatnonzero(self.stream.removed[f])
        state[gone] = MarkerState.RECOVERED
        pos[gone] = self.stream.positions[f, gone] + np.array([self.error, 0, 0])
        return LabeledFrame(t, truth.astype(np.int32), pos, state)


def test_scores_count_only_after_init_window(rng) -> None:
    cap = moving_clusters(rng, frames=100)
    stream = corrupt(cap, CorruptionSpec(gaps=1, gap_frames=5, protect_frames=20, seed=0))
    perfect = score_labeler(_Oracle(stream, error_mm=3.0), stream, init_frames=20, method="x")
    assert perfect.accuracy == 1.0
    assert perfect.recovery_mean_mm == pytest.approx(3.0, abs=1e-3)
    assert perfect.recovery_mean_ratio == pytest.approx(0.03, abs=1e-4)
    assert perfect.recovery_rate == 1.0
    assert np.isnan(perfect.per_frame_accuracy[:20]).all()  # the init window is not scored
    assert (perfect.per_frame_accuracy[20:] == 1.0).all()
    flawed = score_labeler(_Oracle(stream, wrong_every=10), stream, init_frames=20, method="x")
    # Frames 20, 30, ..., 90 get every label wrong: 8 of 80 scored frames.
    assert flawed.accuracy == pytest.approx(1 - 8 / 80, abs=0.01)
    # wrong only inside the init window (frames 0, 3, ..., 18): nothing scored is wrong
    early = _Oracle(stream, wrong_every=3, wrong_before=20)
    assert score_labeler(early, stream, init_frames=20, method="x").accuracy == 1.0


def test_recovery_counts_stay_out_of_the_summary(rng) -> None:
    cap = moving_clusters(rng, frames=100)
    stream = corrupt(cap, CorruptionSpec(gaps=1, gap_frames=5, protect_frames=20, seed=0))
    score = score_labeler(_Oracle(stream), stream, init_frames=20, method="x")
    removed = int(stream.removed[20:].sum())
    assert score.removed == score.recovered == removed > 0
    assert not {"removed", "recovered"} & score.summary().keys()


def test_evaluate_report_has_contract_keys(rng) -> None:
    cap = moving_clusters(rng, frames=150)
    report, scores = evaluate(cap, methods=["closest-point"], ghosts=1.0, init_frames=30)
    assert report.keys() >= CONTRACT_KEYS
    assert report["method"] == "closest-point"
    assert report["accuracy"] > 0.9
    assert report["frames"] == 120 and report["subjects"] == 2 and report["markers"] == 12
    assert report["recovery_mean_mm"] is None  # the baseline recovers nothing: no number
    assert scores["closest-point"].per_frame_accuracy.shape == (150,)


def test_report_keeps_the_labeler_and_the_baseline_apart(rng) -> None:
    """Crowded fast clusters: the online labeler is right where the closest-point baseline
    swaps, so ``accuracy`` and ``baseline_accuracy`` must come from different methods."""
    cap = moving_clusters(rng, subjects=3, markers=8, frames=480, spacing_mm=60.0,
                          speed_mm_s=900.0)  # fmt: skip
    report, scores = evaluate(cap, methods=["online", "closest-point"], init_frames=30,
                              downsample=4)  # fmt: skip
    assert report["method"] == "online"
    online, base = scores["online"].accuracy, scores["closest-point"].accuracy
    assert report["accuracy"] == pytest.approx(online, abs=1e-6) and online >= 0.99
    assert report["baseline_accuracy"] == pytest.approx(base, abs=1e-6) and base < 0.95
    assert report["methods"]["closest-point"]["accuracy"] == report["baseline_accuracy"]
    assert report["methods"]["online"]["accuracy"] == report["accuracy"]


def test_unknown_method_and_short_capture(rng) -> None:
    with pytest.raises(MocapError, match="unknown method"):
        resolve_methods(["nearest"])
    cap = moving_clusters(rng, frames=40)
    with pytest.raises(SceneError, match="init window"):
        evaluate(cap, methods=["closest-point"], init_frames=50)


def test_cli_json_last_line_and_downsampling_hurts_baseline(tmp_path, rng, capsys) -> None:
    cap = moving_clusters(rng, subjects=3, markers=8, frames=480, spacing_mm=60.0, speed_mm_s=900.0)
    path = write_capture(cap, tmp_path / "t.c3d")
    args = ["evaluate", str(path), "--method", "closest-point", "--json", "--init-frames", "20"]
    assert main(args) == 0
    full = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main([*args, "--downsample", "4", "--plot", str(tmp_path / "p.png")]) == 0
    low = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert low["accuracy"] < full["accuracy"]
    assert (tmp_path / "p.png").stat().st_size > 1000
