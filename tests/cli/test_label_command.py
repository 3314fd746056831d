"""``mocap-labeler label``: batch labeling through the online pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main


@pytest.fixture
def take(rng, tmp_path):
    truth, names = articulated(rng, subjects=2, frames=160)
    pos = truth.copy()
    pos[100:110, 3] = np.nan  # a short occlusion
    path = tmp_path / "take.npz"
    write_capture(Capture(pos, names, 120.0, source="take"), path)
    return path, pos, names, truth


def test_label_without_model_trains_on_first_frames(take, tmp_path, capsys):
    src, pos, names, truth = take
    out = tmp_path / "out.npz"
    assert main(["label", str(src), str(out), "--init-frames", "40", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["agreement_with_input_labels"] == 1.0
    res = read_capture(out)
    assert res.labels[: len(names)] == names
    # observed samples are the input's; the occluded one is recovered close to the truth
    np.testing.assert_allclose(res.positions[120, : len(names)], pos[120], atol=1e-4)
    err = np.linalg.norm(res.positions[100:110, 3] - truth[100:110, 3], axis=1)
    held = np.linalg.norm(truth[99, 3] - truth[100:110, 3], axis=1)  # last seen, held still
    assert np.isfinite(err).all() and err.max() < 10.0, err  # rigid body: Kabsch recovery
    assert err.mean() < 0.5 * held.mean(), (err, held)


def test_label_names_the_markers_its_init_window_never_showed(take, tmp_path, capsys):
    """A marker hidden through the whole init window cannot be learned by the labeled start
    and stays unlabeled to the end; ``label`` said nothing of it (a hostile run: the BTS gait
    take from frame 239, 14 of 22 markers never labeled, "agreement 38.8 %" and exit 0)."""
    src, pos, names, _ = take
    hidden = pos.copy()
    hidden[:60, 5] = np.nan  # not in the 40 init frames; visible from frame 60 on
    path = tmp_path / "late.npz"
    write_capture(Capture(hidden, names, 120.0, source="late"), path)
    out = tmp_path / "out.npz"
    assert main(["label", str(path), str(out), "--init-frames", "40", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["unseen_at_init"] == [names[5]]
    assert main(["label", str(path), str(tmp_path / "o2.npz"), "--init-frames", "40"]) == 0
    text = capsys.readouterr().out
    want = "1 marker never visible in the 40 init frames, so never labeled from this start"
    assert f"{want}: {names[5]}" in text
    # a take whose window shows every marker names none
    assert main(["label", str(src), str(tmp_path / "o3.npz"), "--init-frames", "40", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["unseen_at_init"] == []


def test_label_of_a_y_up_take_writes_in_its_axes(take, tmp_path, capsys):
    """``--up y`` reads the take rotated to Z up; OUT is written back in IN's axes, so the
    labeled file overlays the input (it came out rotated by 90 degrees)."""
    _, pos, names, _ = take
    yup = np.stack([pos[..., 0], pos[..., 2], -pos[..., 1]], axis=-1)  # Z up -> Y up
    src = tmp_path / "yup.npz"
    write_capture(Capture(yup, names, 120.0, source="yup"), src)
    out = tmp_path / "out.npz"
    assert main(["label", str(src), str(out), "--init-frames", "40", "--up", "y", "--json"]) == 0
    assert (
        json.loads(capsys.readouterr().out.strip().splitlines()[-1])["agreement_with_input_labels"]
        == 1.0
    )
    res = read_capture(out)
    np.testing.assert_allclose(res.positions[120, : len(names)], yup[120], atol=1e-3)


def test_unlabeled_points_stay_in_their_input_track(take, tmp_path, capsys):
    """Two ghost tracks far from the performers: each comes out as one ``*N`` column holding
    its whole trajectory (they were dealt to columns in the shuffled order of each frame, so
    a column jumped between the two)."""
    _, pos, names, _ = take
    n = pos.shape[0]
    t = np.arange(n, dtype=np.float32)[:, None]
    g0 = np.hstack([5000 + t, np.full((n, 1), 4000, np.float32), np.full((n, 1), 900, np.float32)])
    g1 = np.hstack(
        [-5000 - t, np.full((n, 1), -4000, np.float32), np.full((n, 1), 900, np.float32)]
    )
    src = tmp_path / "ghosts.npz"
    cap = Capture(np.concatenate([pos, g0[:, None], g1[:, None]], axis=1),
                  (*names, "*0", "*1"), 120.0, source="g")  # fmt: skip
    write_capture(cap, src)
    out = tmp_path / "out.npz"
    assert main(["label", str(src), str(out), "--init-frames", "40", "--no-progress"]) == 0
    capsys.readouterr()
    res = read_capture(out)
    m = len(names)
    for j, g in ((m, g0), (m + 1, g1)):
        col = res.labels.index(f"*{j}")
        np.testing.assert_allclose(res.positions[:, col], g, atol=1e-3)


@pytest.mark.parametrize("start", ["auto", "labeler", "model"])
def test_label_runs_the_labeled_start_evaluate_runs(take, tmp_path, capsys, start):
    """``--labeled-start`` as in ``evaluate``: ``auto`` (default) trains a window model on the
    init frames and labels through it; the summary says which start ran."""
    src, _, names, _ = take
    out = tmp_path / "out.npz"
    args = ["label", str(src), str(out), "--init-frames", "40", "--json"]
    assert main([*args, "--labeled-start", start]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["labeled_start"] == ("labeler" if start == "labeler" else "model")
    assert summary["agreement_with_input_labels"] >= 0.999
    assert read_capture(out).labels[: len(names)] == names


def test_label_with_model(take, tmp_path, capsys):
    src, _, names, _ = take
    model = tmp_path / "m.json"
    assert main(["train", "structure", str(src), "--out", str(model)]) == 0
    out = tmp_path / "out.npz"
    args = ["label", str(src), str(out), "--model", str(model), "--init-frames", "1", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["agreement_with_input_labels"] >= 0.999
    assert summary["markers"] == len(names)
    assert summary["labeled_start"] is None  # a model file is its own start
    # the frames the figures count, and the frames the file holds (init frames included)
    n = read_capture(out).n_frames
    assert summary["frames_written"] == n and summary["init_frames"] == 1
    assert summary["frames"] == n - 1
    assert main([*args, "--labeled-start", "model"]) == 2
    assert "--labeled-start model trains its model on the init frames" in capsys.readouterr().err


def test_label_errors_are_clean(take, tmp_path, capsys):
    src, pos, _, _ = take
    raw = tmp_path / "raw.npz"
    write_capture(Capture(pos, tuple(f"*{i}" for i in range(pos.shape[1])), 120.0), raw)
    assert main(["label", str(raw), str(tmp_path / "o.npz")]) == 2
    assert "no labeled markers" in capsys.readouterr().err
    assert main(["label", str(src), str(tmp_path / "o.npz"), "--init-frames", "500"]) == 2
    assert "init frames" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert main(["label", str(src), str(tmp_path / "o.npz"), "--model", str(bad)]) == 2
    assert "not a subject model" in capsys.readouterr().err


def test_label_that_labels_nothing_is_an_error_but_writes_its_output(tmp_path, capsys):
    """A model that matches nothing in the capture (here: only two random points per frame)
    must not look like success: one line naming the input, exit 2, the output still written -
    unless that would replace an earlier output, which stays as it was."""
    from labeler_service.scenes.simulate import simulate_scene

    scene = simulate_scene(2, 2.0, "walk", 1, rate=120.0)
    src = tmp_path / "scene.c3d"
    write_capture(scene, src)
    model = tmp_path / "m.json"
    assert main(["train", "structure", str(src), "--out", str(model)]) == 0
    rng = np.random.default_rng(0)
    noise = Capture(rng.normal(0, 2000, (120, 2, 3)).astype(np.float32), ("*0", "*1"), 120.0)
    raw = tmp_path / "noise.c3d"
    write_capture(noise, raw)
    out = tmp_path / "out.c3d"
    capsys.readouterr()
    assert main(["label", str(raw), str(out), "--model", str(model)]) == 2
    err = capsys.readouterr().err
    assert "no point was labeled" in err and str(raw) in err
    # the likeliest cause first: a model fits the performers it was trained on
    assert "another person's distances differ" in err and "train structure" in err
    assert out.exists()
    # a good earlier OUT is not replaced by a run that labels nothing
    assert main(["label", str(src), str(out), "--model", str(model)]) == 0
    good = out.read_bytes()
    capsys.readouterr()
    assert main(["label", str(raw), str(out), "--model", str(model)]) == 2
    assert f"{out} left as it was" in capsys.readouterr().err
    assert out.read_bytes() == good


@pytest.fixture
def slow_warm_up(monkeypatch):
    """The kernels' warm-up made slow (a first run's compilation) and the notice made early."""
    import time

    from labeler_service.cli import label as label_cmd
    from labeler_service.labeling.labeler import Labeler

    warm = Labeler.warmup

    def slow(self) -> None:
        time.sleep(0.5)
        warm(self)

    monkeypatch.setattr(Labeler, "warmup", slow)
    monkeypatch.setattr(label_cmd, "NOTICE_AFTER_S", 0.05)


def test_a_slow_warm_up_says_the_kernels_are_compiling(take, tmp_path, capsys, slow_warm_up):
    """The first run after an install compiles the kernels for about a minute: said on stderr
    instead of a silent minute."""
    src = take[0]
    assert main(["label", str(src), str(tmp_path / "o.npz"), "--init-frames", "40"]) == 0
    assert "compiling the labeling kernels" in capsys.readouterr().err


def test_evaluate_says_the_kernels_are_compiling_without_a_progress_bar(take, capsys, slow_warm_up):
    """``evaluate --no-progress`` (or into a file) printed nothing during a first run's minute
    of compiling: the warm-up before the run says it too, as ``label`` does."""
    args = ["evaluate", str(take[0]), "--init-frames", "40", "--no-progress", "--json"]
    assert main(args) == 0
    assert "compiling the labeling kernels" in capsys.readouterr().err


def test_label_names_a_model_subject_without_a_name_in_its_summary(rng, tmp_path, capsys):
    """A model whose subject is named ``""`` (its markers' labels carry no prefix) printed its
    summary line as ``  : labeled from ...``."""
    truth, names = articulated(rng, subjects=1, frames=300)
    bare = [n.split(":")[-1] for n in names]
    take = tmp_path / "bare.npz"
    write_capture(Capture(truth, bare, 120.0, source="bare"), take)
    model = tmp_path / "m.json"
    assert main(["train", "structure", str(take), "--out", str(model)]) == 0
    data = json.loads(model.read_text())
    data["subjects"][0]["name"] = ""
    model.write_text(json.dumps(data))
    capsys.readouterr()
    assert main(["label", str(take), str(tmp_path / "out.npz"), "--model", str(model)]) == 0
    text = capsys.readouterr().out
    assert "  (markers without a subject prefix): labeled from " in text, text
    assert "  : " not in text
