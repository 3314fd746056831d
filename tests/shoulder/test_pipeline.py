"""The whole study on a small synthetic shoulder: model, MG03, CLI, files, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.capture import Capture
from labeler_service.capture.io import read_capture, write_capture
from labeler_service.cli.main import main
from offline.shoulder.evaluation import adjusted_rand_index, read_truth
from offline.shoulder.model import MG03Baseline, ShoulderSkeleton, prepare_surface
from offline.shoulder.report import FORMAT, skeleton_dict
from offline.shoulder.simulate import build_body, simulate_motion


@pytest.fixture(scope="module")
def small():
    """~100 markers, 600 training frames (30 Hz, 20 s), a 300-frame test motion."""
    body = build_body(40.0)
    rng = np.random.default_rng(7)
    train = simulate_motion(body, "rom", 600, 30.0, noise_mm=1.5, gap_rate=0.5, random_state=rng)
    test = simulate_motion(body, "jumping_jack", 300, 30.0, noise_mm=1.5, random_state=rng)
    surf = prepare_surface(train.capture.positions)
    models = {
        k: ShoulderSkeleton(k, n_restarts=50, random_state=k).fit(train.capture.positions, surf)
        for k in (3, 4)
    }
    return body, train, test, models


def test_four_segments_find_the_bones(small):
    body, train, _, models = small
    m4 = models[4]
    assert m4.n_segments_ == 4
    assert adjusted_rand_index(body.segment, m4.labels_) > 0.85
    assert m4.is_chain_
    assert all(len(r) == 4 for r in m4.reduced_)
    np.testing.assert_allclose(m4.weights_.sum(axis=1), 1.0)


def test_fit_is_reproducible(small):
    _, train, _, models = small
    again = ShoulderSkeleton(4, n_restarts=50, random_state=4).fit(train.capture.positions)
    np.testing.assert_array_equal(again.labels_, models[4].labels_)
    np.testing.assert_allclose(again.joints_, models[4].joints_)
    assert again.reduced_[0].tolist() == models[4].reduced_[0].tolist()


def test_error_drops_from_three_to_four_and_joints_are_found(small):
    _, train, test, models = small
    for capture in (train.capture, test.capture):
        e3 = models[3].score(capture.positions, "full").avg
        e4 = models[4].score(capture.positions, "full").avg
        assert e4 < 0.85 * e3
        assert np.isfinite(models[4].score(capture.positions, "reduced").avg)
    R, t = models[4].pose(test.capture.positions)
    traj = models[4].joint_trajectories(R, t)
    # GH and elbow: the true joints nearest to some estimated joint on average
    for j in (1, 2):
        best = min(np.nanmean(np.linalg.norm(x - test.joints[:, j], axis=1)) for x in traj.values())
        assert best < 15.0


def test_mg03_is_worse_than_four_segments(small):
    _, train, test, models = small
    base = MG03Baseline(models[3]).fit(train.capture.positions)
    assert base.weights_.shape == (train.capture.n_markers, 4)
    ours = models[4].score(test.capture.positions, "reduced").avg
    assert ours < base.score(test.capture.positions, "reduced").avg


def test_a_given_pose_scores_as_the_pose_computed_inside(small):
    _, train, test, models = small
    m3, p_train, p_test = models[3], train.capture.positions, test.capture.positions
    assert m3.score_pose(p_test, *m3.pose(p_test, "reduced")) == m3.score(p_test, "reduced")
    own = MG03Baseline(m3).fit(p_train)
    given = MG03Baseline(m3).fit(p_train, m3.pose(p_train, "full"))
    np.testing.assert_array_equal(own.weights_, given.weights_)
    for mset in ("reduced", "full"):
        assert given.score(p_test, mset, m3.pose(p_test, mset)) == own.score(p_test, mset)


def test_skeleton_file_is_self_consistent(small):
    _, train, _, models = small
    d = skeleton_dict(models[4], train.capture.labels)
    assert d["format"] == FORMAT and d["n_segments"] == 4
    json.dumps(d)  # serialisable
    roots = [s for s in d["segments"] if s["parent"] is None]
    assert len(roots) == 1 and roots[0]["joint_mm"] is None
    owned = sorted(x for s in d["segments"] for x in s["markers"])
    assert owned == sorted(train.capture.labels)
    assert np.allclose(np.sum(d["weights"], axis=1), 1.0, atol=1e-3)


def test_model_validation(small):
    _, train, _, _ = small
    with pytest.raises(Exception, match="n_segments"):
        ShoulderSkeleton(1).fit(train.capture.positions)
    with pytest.raises(Exception, match="at least 10 frames"):
        prepare_surface(train.capture.positions[:5])
    with pytest.raises(ValueError, match="marker_set"):
        ShoulderSkeleton(2, n_restarts=2).fit(train.capture.positions).pose(
            train.capture.positions, "some"
        )


def test_train_shoulder_cli_end_to_end(tmp_path, capsys):
    sim = tmp_path / "sim"
    # 600 frames at 30 Hz: 20 s, long enough for the range of motion to cover the girdle
    assert main(["simulate-shoulder", str(sim), "--frames", "600", "--test-frames", "200",
                 "--spacing", "40", "--noise", "1.5", "--rate", "30"]) == 0  # fmt: skip
    capsys.readouterr()
    out = tmp_path / "out"
    jj = f"jj={sim / 'jumping_jack.c3d'}"
    code = main(["train", "shoulder", str(sim / "rom.c3d"), "--test", jj,
                 "--test", str(sim / "curls.c3d"), "--truth", str(sim / "truth.npz"),
                 "--k", "3", "4", "--restarts", "50", "--seed", "2",
                 "--out", str(out)])  # fmt: skip
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["ks"] == [3, 4]
    for name in ("report.md", "results.json", "skeleton_k3.json", "skeleton_k4.json", "faces.txt",
                 "error_train.png", "error_test_full.png", "segments_k4.png"):  # fmt: skip
        assert (out / name).is_file(), name
    r = json.loads((out / "results.json").read_text())
    assert set(r["errors"]) == {"rom", "jj", "curls"}
    assert r["errors"]["jj"]["full"]["4"]["avg"] < r["errors"]["jj"]["full"]["3"]["avg"]
    assert "rom/reduced: e4 <= 0.85 e3" in r["acceptance"]
    assert r["joints_vs_truth"]["4"]["rom"]["GH"]["mean_mm"] < 20.0
    truth = read_truth(sim / "truth.npz")
    assert r["segmentation"]["4"]["ari_vs_truth"] > 0.8 and len(truth.labels) == r["markers"]
    report = (out / "report.md").read_text()
    assert "Table 2 analogue" in report and "MG03" in report
    # the same faces file given back gives the same surface
    o2 = str(tmp_path / "o2")
    code = main(["train", "shoulder", str(sim / "rom.c3d"), "--faces", str(out / "faces.txt"),
                 "--k", "3", "--restarts", "5", "--no-plots", "--out", o2])  # fmt: skip
    assert code == 0
    r2 = json.loads((tmp_path / "o2" / "results.json").read_text())
    assert r2["faces"] == r["faces"]


def test_train_shoulder_cli_errors(tmp_path, capsys):
    assert main(["train", "shoulder", str(tmp_path / "none.c3d"), "--out", str(tmp_path)]) == 2
    assert "no such file" in capsys.readouterr().err
    sim = tmp_path / "sim"
    main(["simulate-shoulder", str(sim), "--frames", "50", "--test-frames", "20",
          "--spacing", "45"])  # fmt: skip
    capsys.readouterr()
    rom = str(sim / "rom.c3d")
    assert main(["train", "shoulder", rom, "--test", "x=", "--out", str(tmp_path / "o")]) == 2
    assert main(["train", "shoulder", rom, "--k", "1", "--out", str(tmp_path / "o")]) == 2
    # at most 3 markers per segment (k = 216 of 215 markers ran for minutes)
    assert main(["train", "shoulder", rom, "--k", "3", "500", "--out", str(tmp_path / "o")]) == 2
    assert "3 markers per segment" in capsys.readouterr().err
    other = tmp_path / "model.json"
    other.write_text("{}")
    assert main(["train", "shoulder", rom, "--truth", str(other), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not a shoulder truth file" in err and "allow_pickle" not in err
    assert main(["train", "shoulder", rom, "--faces", "/dev/null", "--out", str(tmp_path)]) == 2
    assert "not a regular file" in capsys.readouterr().err
    assert main(["train", "shoulder", rom, "--subject", "nobody", "--out", str(tmp_path)]) == 2
    assert "no subject 'nobody'" in capsys.readouterr().err


def test_train_shoulder_mistakes_are_one_line_errors(tmp_path, capsys):
    """A hostile run: an --out that is a file, a faces file not in UTF-8 and the truth file of
    another simulate-shoulder run each ended in a Python traceback (the last after training)."""
    sim, other = tmp_path / "sim", tmp_path / "other"
    for folder, frames in ((sim, "60"), (other, "80")):
        assert main(["simulate-shoulder", str(folder), "--frames", frames, "--test-frames", "20",
                     "--spacing", "45"]) == 0  # fmt: skip
    capsys.readouterr()
    rom = str(sim / "rom.c3d")
    base = ["train", "shoulder", rom, "--k", "3", "--restarts", "2", "--no-plots"]
    assert main([*base, "--out", rom]) == 2
    err = capsys.readouterr().err
    assert "exists and is not a folder" in err and "Traceback" not in err
    latin = tmp_path / "faces.txt"
    latin.write_bytes("caf\xe9 a b\n".encode("latin-1"))
    assert main([*base, "--faces", str(latin), "--out", str(tmp_path / "o1")]) == 2
    assert "not a UTF-8 text file" in capsys.readouterr().err
    assert main([*base, "--truth", str(other / "truth.npz"), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "cover 80 frames, the capture 60" in err, err
    # a truth file of another kind (a labeler's npz): its missing arrays named plainly (the
    # message read "no 'segment is not a file in the archive' in it")
    np.savez(tmp_path / "out.npz", labels=np.array(["a"]), positions=np.zeros((1, 1, 3)))
    assert main([*base, "--truth", str(tmp_path / "out.npz"), "--out", str(tmp_path / "o4")]) == 2
    err = capsys.readouterr().err
    assert "no 'segment', 'segment_names', 'joint_names', 'joint_segments' array" in err, err
    # a test motion in which no training marker is ever visible: its errors were NaN, printed
    # as the bare token strict JSON parsers refuse, and the run exited 0
    blank = read_capture(rom)
    blank = Capture(np.full_like(blank.positions, np.nan), blank.labels, blank.rate, source="x")
    write_capture(blank, tmp_path / "blank.c3d")
    assert main([*base, "--test", str(tmp_path / "blank.c3d"), "--out", str(tmp_path / "o5")]) == 2
    err = capsys.readouterr().err
    assert "no training marker is visible in any of its 60 frames" in err, err
    # FILE[:start[:stop]] as every other command takes a capture ("no such file" before)
    seg = [*base[:2], f"{rom}:0:50", *base[3:], "--test", f"seg={rom}:30:60"]
    assert main([*seg, "--out", str(tmp_path / "o6")]) == 0
    capsys.readouterr()
    assert set(json.loads((tmp_path / "o6" / "results.json").read_text())["errors"]) == {
        "rom",
        "seg",
    }
    assert main([*base, "--test", f"late={rom}:70", "--out", str(tmp_path / "o7")]) == 2
    assert "start 70 is past the capture's 60 frames" in capsys.readouterr().err
    for bad in ("nan", "-1", "0", "1", "inf"):  # each kept no triangle; the report said "<= nan"
        with pytest.raises(SystemExit) as stop:
            main([*base, "--max-strain", bad, "--out", str(tmp_path / "o3")])
        assert stop.value.code == 2
        assert "expected a finite ratio > 1" in capsys.readouterr().err
