"""Rigid-body prediction (kernels/motion.py) on a fast arm at a low frame rate.

A simulated arm (trunk, upper arm, forearm with four markers along it, hand) winds up slowly in
the labeled init window (every segment moves on its own, so training finds one body per
segment), then circles the forearm about the elbow at 2.25 turns per second while the upper
arm rises, captured at 30 Hz: the forearm turns 27 degrees and the wrist travels ~120 mm
between frames (a tennis serve at 50 Hz moves the wrist 190-240 mm).
A per-marker constant-velocity prediction then misses each forearm marker by the arc's
sagitta and by the upper arm's lift; the forearm's rigid motion predicts all of them.
"""

from __future__ import annotations

import numpy as np

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.labeler import Labeler

RATE = 30.0
INIT = 12
FRAMES = 150
SHOULDER = np.array([0.0, 0.0, 1400.0])


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


def _arm(rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """``(FRAMES, 15, 3)`` positions (mm) and names of one performer."""
    trunk = np.array([[0, -150, -300], [0, 150, -300], [-80, 0, -100], [60, 0, -450.0]])
    upper = np.array([[0, 0, -120], [40, 0, -180], [0, 35, -250.0]])  # shoulder frame
    elbow = np.array([0.0, 0.0, -300.0])
    fore = np.array([[0, 0, 0], [30, 0, 90], [0, -30, 170], [25, 20, 250.0]])  # elbow frame
    hand = np.array([[0, 0, 320], [35, 0, 330.0]])
    names = [f"A:T{i}" for i in range(4)] + [f"A:U{i}" for i in range(3)]
    names += [f"A:F{i}" for i in range(4)] + ["A:H0", "A:H1"]
    t = np.arange(FRAMES) / RATE
    wind = np.clip((t - INIT / RATE) / 0.5, 0.0, 1.0)  # spin-up after the init window
    spin = 2 * np.pi * 2.25 * (t - INIT / RATE - 0.25) * wind
    out = np.empty((FRAMES, 13, 3))
    for f in range(FRAMES):
        Rt = _rot(2, 0.15 * np.sin(2 * t[f]))  # trunk sways
        Ru = Rt @ _rot(0, 0.3 * np.sin(1.3 * t[f]) - 0.4 * wind[f] * t[f])  # upper arm lifts
        Rf = Ru @ _rot(1, 0.25 * np.sin(3 * t[f]) + spin[f])  # forearm circles about the elbow
        sh = SHOULDER + Rt @ np.array([0.0, 200.0, 0.0])
        el = sh + Ru @ elbow
        out[f, :4] = SHOULDER + trunk @ Rt.T
        out[f, 4:7] = sh + upper @ Ru.T
        out[f, 7:11] = el + fore @ Rf.T
        out[f, 11:] = el + hand @ Rf.T
    out += rng.normal(0.0, 0.5, out.shape)
    return out, names


def _forearm_accuracy(config: LabelerConfig) -> float:
    rng = np.random.default_rng(7)
    pos, names = _arm(rng)
    lab = Labeler(names, RATE, config)
    correct = total = 0
    for f in range(FRAMES):
        order = rng.permutation(pos.shape[1])
        pts = pos[f, order].astype(np.float32)
        out = lab.process(pts, f / RATE, order if f < INIT else None)
        if f >= INIT:
            arm = order >= 7  # forearm and hand markers
            correct += int(np.count_nonzero(out.point_labels[arm] == order[arm]))
            total += int(np.count_nonzero(arm))
    return correct / total


def test_forearm_labels_hold_at_30hz_with_rigid_prediction():
    assert _forearm_accuracy(LabelerConfig()) >= 0.99


def test_per_marker_prediction_alone_loses_the_forearm():
    """The scene is hard for the paper's predictor: without the rigid-body prediction (and
    without the follow rule, which takes lost markers back on their own points) the forearm
    is not held (70 % when written, 88.9 % since), so the test above measures the prediction."""
    no_follow = LabelerConfig(body_prediction=False, acquire_follow=False)
    assert _forearm_accuracy(no_follow) < 0.9


def test_the_follow_rule_takes_back_forearm_markers_prediction_loses():
    """Through the whole frame (``kernels/follow.py`` hooked into ``step.py``): with only the
    per-marker prediction, markers that leave their gates are followed on their own points
    and taken back (88.9 -> 94.2 % when written)."""
    off = _forearm_accuracy(LabelerConfig(body_prediction=False, acquire_follow=False))
    on = _forearm_accuracy(LabelerConfig(body_prediction=False))
    assert on >= off + 0.03, (off, on)
