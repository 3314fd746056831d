"""Error anatomy: kinds of errors, unseen markers, the longest swap, worst markers, raster."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic import moving_clusters

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main
from labeler_service.evaluation.scoring import (
    CORRECT,
    CROSS_SUBJECT,
    NOT_VISIBLE,
    SAME_SUBJECT,
    UNLABELED,
    Scorer,
    score_labeler,
)
from labeler_service.labeling.frame import LabeledFrame
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt


class _Scripted:
    """Gives the true labels, then applies ``edit(f, truth, labels)`` to them in place."""

    def __init__(self, stream, edit) -> None:
        self.stream, self.edit, self.f = stream, edit, 0
        self.marker_names = stream.marker_names

    def process(self, points, t, labels=None) -> LabeledFrame:
        f = self.f
        self.f += 1
        truth = self.stream.truth[f]
        out = truth.copy()
        self.edit(f, truth, out)
        m = len(self.marker_names)
        return LabeledFrame(
            t, out.astype(np.int32), np.full((m, 3), np.nan, np.float32), np.zeros(m, np.uint8)
        )

    def warmup(self) -> None:
        pass

    def body_extent(self) -> np.ndarray:
        return np.full(len(self.marker_names), np.nan)


def _swap(out, truth, a, b) -> None:
    ia, ib = np.flatnonzero(truth == a), np.flatnonzero(truth == b)
    if ia.size and ib.size:
        out[ia], out[ib] = b, a


@pytest.fixture
def stream(rng):
    # two subjects S0 (markers 0-5) and S1 (6-11); marker 2 absent in frames 40-44
    cap = moving_clusters(rng, frames=100)
    pos = cap.positions.copy()
    pos[40:45, 2] = np.nan
    return corrupt(cap.with_positions(pos), CorruptionSpec(ghosts=1.0, protect_frames=20, seed=1))


def test_error_kinds_are_counted_and_add_up(stream) -> None:
    g = next(f for f in range(75, 100) if (stream.truth[f] < 0).any())

    def edit(f, truth, out):
        if 30 <= f < 50:  # markers 2 and 3 of S0 swapped: same subject
            _swap(out, truth, 2, 3)
        if f == 60:  # marker 0 (S0) given marker 7 (S1): cross subject
            out[truth == 0] = 7
        if f in (70, 71):  # marker 5 unlabeled
            out[truth == 5] = -1
        if f == g:  # every ghost takes label 11
            out[truth < 0] = 11

    s = score_labeler(_Scripted(stream, edit), stream, init_frames=20, method="x")
    assert s.visible == 80 * 12 - 5
    # frames 30-49 minus the five where marker 2 is absent (marker 3 is then labeled right)
    assert s.errors["same_subject"] == 30
    assert s.errors["cross_subject"] == 1
    assert s.errors["unlabeled"] == 2
    assert s.errors["ghost_taken"] == int((stream.truth[g] < 0).sum()) > 0
    wrong = sum(s.errors[k] for k in ("same_subject", "cross_subject", "unlabeled"))
    assert s.accuracy == pytest.approx(1 - wrong / s.visible)
    # the absent frames of marker 2 neither end its swap run nor count in it; marker 3's run
    # is ended by its correct frames 40-44
    assert s.max_swap_frames == 15
    assert s.max_swap == {"marker": "S0:m2", "first_frame": 30, "last_frame": 49}
    top = s.worst_markers[0]
    assert top["marker"] == "S0:m2" and top["errors"] == 15 and top["same_subject"] == 15
    assert [w["marker"] for w in s.worst_markers[:2]] == ["S0:m2", "S0:m3"]
    assert len(s.worst_markers) == 4  # m3, m2, m0 (cross), m5 (unlabeled)


def test_raster_codes(stream) -> None:
    def edit(f, truth, out):
        if f == 30:
            _swap(out, truth, 2, 3)
            out[truth == 0] = 7
            out[truth == 5] = -1

    s = score_labeler(_Scripted(stream, edit), stream, init_frames=20, method="x")
    r = s.raster
    assert r.shape == (100, 12)
    assert (r[:20] == NOT_VISIBLE).all()  # init window is not scored
    assert r[30, 2] == r[30, 3] == SAME_SUBJECT
    assert r[30, 0] == CROSS_SUBJECT and r[30, 5] == UNLABELED and r[30, 1] == CORRECT
    assert (r[40:45, 2] == NOT_VISIBLE).all()


def test_a_wrong_then_unlabeled_frame_ends_the_swap(stream) -> None:
    def edit(f, truth, out):
        if 30 <= f < 60 and f != 45:
            _swap(out, truth, 0, 1)
        if f == 45:
            out[truth == 0] = -1
            out[truth == 1] = -1

    s = score_labeler(_Scripted(stream, edit), stream, init_frames=20, method="x")
    assert s.max_swap_frames == 15
    assert s.errors["unlabeled"] == 2


def test_unseen_at_init_counted_and_kept_in_accuracy(rng) -> None:
    cap = moving_clusters(rng, frames=100)
    pos = cap.positions.copy()
    pos[:25, 4] = np.nan  # marker 4 first appears at frame 25, after the 20-frame window
    stream = corrupt(cap.with_positions(pos), CorruptionSpec(protect_frames=20, seed=0))

    def edit(f, truth, out):
        out[truth == 4] = -1  # never labeled, like a marker the labeler never learned

    s = score_labeler(_Scripted(stream, edit), stream, init_frames=20, method="x")
    assert s.unseen_at_init == 75
    assert s.errors["unlabeled"] == 75
    assert s.accuracy == pytest.approx(1 - 75 / (80 * 12 - 5))
    assert s.accuracy_seen == 1.0
    assert s.worst_markers[0]["seen_at_init"] is False


def test_a_model_start_counts_unseen_only_the_markers_the_model_lacks(stream) -> None:
    """Started from a model with no init frame (``evaluate --model M --init-frames 0``): every
    sample read ``unseen_at_init`` (no init frame showed any marker) and ``accuracy_seen`` was
    null, where ``label --model`` said none was unseen. The model's markers are learned; only
    the markers it lacks are unseen."""
    m = len(stream.marker_names)
    known = np.ones(m, dtype=bool)
    known[3] = False  # the model's training never showed marker 3

    def scored(known: np.ndarray):
        sc = Scorer(stream.marker_names, init_frames=0, n_frames=stream.n_frames, learned=known)
        lab = _Scripted(stream, lambda *a: None)
        for f in range(stream.n_frames):
            sc.add(f, stream.truth[f], lab.process(stream.points[f], 0.0))
        return sc.result()

    s = scored(known)
    visible3 = sum(int((t == 3).sum()) for t in stream.truth)
    assert s.unseen_at_init == visible3 > 0
    assert s.accuracy_seen == 1.0
    assert scored(np.ones(m, dtype=bool)).unseen_at_init == 0


def test_lost_frame_counts_every_visible_point_unlabeled(stream) -> None:
    sc = Scorer(stream.marker_names, init_frames=20, n_frames=stream.n_frames)
    for f in range(stream.n_frames):
        out = None if f == 50 else _Scripted(stream, lambda *a: None)
        if out is not None:
            out.f = f
            out = out.process(stream.points[f], 0.0)
        sc.add(f, stream.truth[f], out)
    s = sc.result()
    assert s.errors["unlabeled"] == int((stream.truth[50] >= 0).sum())
    assert s.per_frame_accuracy[50] == 0.0


def test_cli_json_has_anatomy_and_plot_writes_raster(tmp_path, rng, capsys) -> None:
    cap = moving_clusters(rng, subjects=2, markers=6, frames=200)
    path = write_capture(cap, tmp_path / "t.c3d")
    plot = tmp_path / "acc.png"
    args = ["evaluate", str(path), "--method", "closest-point", "--json", "--init-frames", "20"]
    assert main([*args, "--occlude", "1", "--plot", str(plot)]) == 0
    io = capsys.readouterr()
    rep = json.loads(io.out.strip().splitlines()[-1])
    assert {"visible", "errors", "unseen_at_init", "max_swap_frames", "worst_markers"} <= rep.keys()
    assert rep["visible"] > 0
    assert set(rep["errors"]) == {"same_subject", "cross_subject", "unlabeled", "ghost_taken"}
    assert rep["settings"]["occlude"] == 1
    assert (tmp_path / "acc_errors.png").stat().st_size > 1000
    assert rep["errors_plot"] == str(tmp_path / "acc_errors.png")
    assert f"wrote {plot} and {tmp_path / 'acc_errors.png'}" in io.err


def test_plot_of_a_take_without_errors_warns_nothing(tmp_path, rng, capsys) -> None:
    """A hostile run: more markers than the raster draws (80) and none with an error left no
    row to draw, and matplotlib warned on stderr "Attempting to set identical low and high
    ylims makes transformation singular" (pytest makes the warning an error)."""
    cap = moving_clusters(rng, subjects=9, markers=10, frames=120, speed_mm_s=50.0)
    path = write_capture(cap, tmp_path / "t.c3d")
    plot = tmp_path / "acc.png"
    args = ["evaluate", str(path), "--method", "closest-point", "--json", "--init-frames", "20"]
    assert main([*args, "--plot", str(plot)]) == 0
    io = capsys.readouterr()
    rep = json.loads(io.out.strip().splitlines()[-1])
    assert rep["markers"] == 90 and rep["accuracy"] == 1.0  # no row with an error
    assert (tmp_path / "acc_errors.png").stat().st_size > 1000
    assert "Warning" not in io.err


def test_text_output_names_the_worst_markers(tmp_path, rng, capsys) -> None:
    cap = moving_clusters(rng, subjects=3, markers=8, frames=300, spacing_mm=60.0, speed_mm_s=900.0)
    path = write_capture(Capture(cap.positions, cap.labels, 120.0), tmp_path / "t.c3d")
    assert main(["evaluate", str(path), "--method", "closest-point", "--downsample", "4",
                 "--init-frames", "10"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "visible samples scored" in out and "worst markers:" in out
