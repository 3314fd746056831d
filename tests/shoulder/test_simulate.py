"""The synthetic dense shoulder: layout, skinning, ground truth, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.cli.main import main
from labeler_service.errors import SceneError
from offline.shoulder.simulate import (
    JOINT_SEGMENTS,
    MOTIONS,
    build_body,
    simulate_motion,
    truth_arrays,
)


def test_body_layout_and_weights():
    body = build_body()
    assert 190 <= body.n_markers <= 240
    np.testing.assert_allclose(body.weights.sum(axis=1), 1.0)
    assert set(np.unique(body.segment)) == {0, 1, 2, 3}
    # blending only between a bone and its parent or child
    for w in body.weights:
        nz = np.flatnonzero(w > 1e-9)
        assert nz.size <= 2 and (nz.size == 1 or nz[1] - nz[0] == 1)
    d = np.linalg.norm(body.rest[:, None] - body.rest[None], axis=2)
    np.fill_diagonal(d, np.inf)
    assert 20.0 < np.median(d.min(axis=1)) < 35.0  # ~27 mm spacing
    with pytest.raises(SceneError, match="spacing"):
        build_body(5.0)


@pytest.mark.parametrize("name", MOTIONS)
def test_motion_is_rigid_where_it_should_be(name):
    body = build_body(45.0)
    m = simulate_motion(body, name, 150, noise_mm=0.0, random_state=1)
    pos = m.capture.positions.astype(np.float64)
    assert pos.shape == (150, body.n_markers, 3) and np.isfinite(pos).all()
    # bone lengths between joint centres stay constant (ground truth is a rigid chain)
    for a, b in ((0, 1), (1, 2)):
        length = np.linalg.norm(m.joints[:, a] - m.joints[:, b], axis=1)
        assert np.ptp(length) < 1e-6
    # distances inside one bone's pure markers stay constant
    pure = np.flatnonzero((body.weights.max(axis=1) > 0.999) & (body.segment == 3))
    d = np.linalg.norm(pos[:, pure[0]] - pos[:, pure[1]], axis=1)
    assert np.ptp(d) < 1e-3


def test_noise_gaps_and_seed():
    body = build_body(45.0)
    a = simulate_motion(body, "curls", 300, noise_mm=2.0, gap_rate=5, random_state=3)
    b = simulate_motion(body, "curls", 300, noise_mm=2.0, gap_rate=5, random_state=3)
    np.testing.assert_array_equal(a.capture.positions, b.capture.positions)
    assert 0.001 < np.isnan(a.capture.positions[..., 0]).mean() < 0.3
    clean = simulate_motion(body, "curls", 300, noise_mm=0.0, random_state=3)
    diff = np.linalg.norm(a.capture.positions - clean.capture.positions, axis=2)
    assert 1.0 < np.nanmean(diff) < 6.0
    with pytest.raises(SceneError, match="unknown shoulder motion"):
        simulate_motion(body, "golf", 100)
    with pytest.raises(SceneError, match=">= 10 frames"):
        simulate_motion(body, "rom", 5)
    for kw, why in (({"rate": float("nan")}, "rate must be"), ({"rate": 1e-3}, "rate must be"),
                    ({"noise_mm": float("nan")}, "noise must be"),
                    ({"gap_rate": 2000.0}, "gap rate must be")):  # fmt: skip
        with pytest.raises(SceneError, match=why):
            simulate_motion(body, "rom", 100, **kw)
    t = truth_arrays(body, [a])
    assert t["joints:curls"].shape == (300, 3, 3)
    np.testing.assert_array_equal(t["joint_segments"], JOINT_SEGMENTS)


def test_simulate_shoulder_cli(tmp_path, capsys):
    code = main(["simulate-shoulder", str(tmp_path), "--frames", "60", "--test-frames", "30",
                 "--spacing", "45", "--format", "npz"])  # fmt: skip
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(summary["captures"]) == set(MOTIONS)
    for name in MOTIONS:
        assert (tmp_path / f"{name}.npz").is_file()
    with np.load(tmp_path / "truth.npz") as z:
        assert z["joints:rom"].shape == (60, 3, 3)
        assert z["labels"].shape[0] == summary["markers"]
    assert main(["simulate-shoulder", str(tmp_path), "--spacing", "3"]) == 2


def test_simulate_shoulder_refuses_before_writing(tmp_path, capsys):
    """A refused argument leaves the folder as it was (``--test-frames 3`` had written a new
    ``rom`` capture beside an earlier run's test captures and truth), naming the option."""
    out = tmp_path / "sim"
    for args, why in (
        (["--test-frames", "3"], "--test-frames must be >= 10"),
        (["--rate", "nan"], "rate must be"),
        (["--rate", "inf"], "rate must be"),
        (["--noise", "nan"], "noise must be"),
        (["--gap-rate", "2000"], "gap rate"),
    ):
        assert main(["simulate-shoulder", str(out), "--frames", "30", *args]) == 2
        assert why in capsys.readouterr().err
        assert not out.exists()
