"""The synthetic acceptance study of issue #5 at full size (slow: ~20-30 s)."""

from __future__ import annotations

import json

import pytest

from labeler_service.cli.main import main


@pytest.mark.slow
def test_synthetic_acceptance(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate-shoulder", str(sim), "--test-frames", "600"]) == 0
    out = tmp_path / "out"
    code = main(["train", "shoulder", str(sim / "rom.c3d"), "--test", str(sim / "swimming.c3d"),
                 "--truth", str(sim / "truth.npz"), "--k", "3", "4", "5", "--restarts", "300",
                 "--no-plots", "--out", str(out)])  # fmt: skip
    assert code == 0
    capsys.readouterr()
    r = json.loads((out / "results.json").read_text())
    assert len(r["acceptance"]) == 12
    # the rules recomputed from the raw errors (not the code's own pass flags)
    checked = 0
    for motion, sets in r["errors"].items():
        for mset, by_k in sets.items():
            e3, e4, e5 = (by_k[k]["avg"] for k in ("3", "4", "5"))
            mg03 = r["mg03"][motion][mset]["avg"]
            assert e4 <= 0.85 * e3, (motion, mset, e3, e4)
            assert abs(e5 - e4) <= 0.05 * e4, (motion, mset, e4, e5)
            assert e4 < mg03, (motion, mset, e4, mg03)
            checked += 3
    assert checked == 12
    assert all(rule["pass"] for rule in r["acceptance"].values())
    for motion in ("rom", "swimming"):
        joints = r["joints_vs_truth"]["4"][motion]
        assert all(j["matched"] and j["mean_mm"] <= 10.0 for j in joints.values()), joints
