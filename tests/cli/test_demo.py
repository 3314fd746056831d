"""``mocap-labeler demo``, shortened with ``--frames``: the whole job in the suite."""

from __future__ import annotations

import json
import re

import pytest

from labeler_service.capture import read_capture
from labeler_service.cli.main import main


@pytest.mark.parametrize(
    ("data", "start"),
    [("found", ["--start", "labeled"]), ("none", ["--start", "labeled"]), ("found", [])],
)
def test_short_demo_prints_accuracy_and_writes_its_report(
    request, tmp_path, capsys, monkeypatch, data, start
):
    if data == "found":
        request.getfixturevalue("real_dir")  # skips with a reason when the captures are absent
    else:  # a fresh clone without the real captures: the built-in simulator
        (tmp_path / "empty").mkdir()
        monkeypatch.setenv("MOCAP_DATA_DIR", str(tmp_path / "empty"))
    out = tmp_path / "demo"
    where = str(out)
    if not start:  # as `make demo` runs it: a relative --out (its settings file names the
        # model relative to the working folder, which the service once read from the file's)
        monkeypatch.chdir(tmp_path)
        where = "demo"
    assert main(["demo", "--frames", "240", "--speed", "4", "--out", where, *start]) == 0
    text = capsys.readouterr().out
    m = re.search(r"^accuracy\s+([0-9.]+) % of visible markers labeled correctly$", text, re.M)
    assert m, text
    report = json.loads((out / "report.json").read_text())
    assert float(m.group(1)) == pytest.approx(100 * report["accuracy"], abs=0.006)
    assert report["labeler"] == "online" and report["frames"] == 240
    assert ("simulated" in report["scene"]) == (data == "none")
    if not start:  # the default, the production path: no labels, performers booted from models
        assert report["init_frames"] == 0 and "accuracy_after_boot" in report
    else:  # the paper's labeled window of 50 frames
        assert report["init_frames"] == 50 and report["accuracy"] >= 0.97
    assert report["frames_received"] >= 0.95 * (report["frames_sent"] - report["init_frames"])
    for name in ("latency_histogram.png", "accuracy_over_time.png"):
        assert (out / name).stat().st_size > 1000
    labeled = read_capture(out / "labeled.c3d")
    assert labeled.n_frames == report["frames_received"]
    assert labeled.rate == pytest.approx(report["rate"])


def test_start_options_resolve_to_one_start():
    """``--start labeled`` is the window; without ``--start``, ``--init-frames`` decides (0: the
    boot, no labels; N: the window); contradictions are our error, not a silent choice."""
    from labeler_service.cli.demo import DEFAULT_INIT_FRAMES, DEFAULT_START, resolve_start
    from labeler_service.errors import MocapError

    default = 0 if DEFAULT_START == "boot" else DEFAULT_INIT_FRAMES
    assert resolve_start(None, None) == (DEFAULT_START, default)
    assert resolve_start("labeled", None) == ("window", 50)
    assert resolve_start("window", 12) == ("window", 12)
    assert resolve_start(None, 50) == ("window", 50)
    assert resolve_start(None, None, "baseline") == ("window", 50)  # no boot without a model
    assert resolve_start(None, 0) == ("boot", 0)
    assert resolve_start("boot", None) == ("boot", 0)
    with pytest.raises(MocapError, match="sends no labels"):
        resolve_start("boot", 50)
    # the least it takes, per labeler (it said ">= 1", then refused 1 and 2 for the online one)
    with pytest.raises(MocapError, match="needs labeled frames: --init-frames >= 3"):
        resolve_start("labeled", 0)
    with pytest.raises(MocapError, match="needs labeled frames: --init-frames >= 1"):
        resolve_start("labeled", 0, "baseline")
    # the online labeler trains on 3+ labeled frames: fewer ran the demo with every frame
    # dropped ("training failed") and exit 0; the closest-point baseline needs one
    for n in (1, 2):
        with pytest.raises(MocapError, match="must be >= 3, got"):
            resolve_start(None, n)
        assert resolve_start(None, n, "baseline") == ("window", n)
    assert resolve_start(None, 3) == ("window", 3)


def test_simulated_demo_boots_its_performers_from_a_model_of_the_same_people(
    tmp_path, capsys, monkeypatch
):
    """``demo --start boot`` without real captures: the model is trained on the same simulated
    performers after the scene's frames (a model of other simulated people booted no one)."""
    (tmp_path / "empty").mkdir()
    monkeypatch.setenv("MOCAP_DATA_DIR", str(tmp_path / "empty"))
    out = tmp_path / "demo"
    args = ["demo", "--start", "boot", "--frames", "480", "--speed", "2", "--out", str(out)]
    assert main(args) == 0
    assert "boot" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["init_frames"] == 0 and "simulated" in report["scene"]
    booted = [s for s in report["boot_s"].values() if s is not None]
    assert len(booted) >= 2, report["boot_s"]
    assert report["accuracy_after_boot"] is None or report["accuracy_after_boot"] >= 0.97
