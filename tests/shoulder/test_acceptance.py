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
    failed = [name for name, rule in r["acceptance"].items() if not rule["pass"]]
    assert not failed, failed
    assert len(r["acceptance"]) == 12
    for motion in ("rom", "swimming"):
        joints = r["joints_vs_truth"]["4"][motion]
        assert all(j["matched"] and j["mean_mm"] <= 10.0 for j in joints.values()), joints
