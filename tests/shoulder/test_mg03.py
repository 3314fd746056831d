"""MG03 (Mohr and Gleicher's extra shoulder bone) against an independent construction, and the
acceptance rules recomputed from raw errors rather than read from the code's ``pass`` flags.

The construction: a three-bone chain (trunk -> upper arm about the shoulder -> forearm about the
elbow) with known transforms, and a marker set of which some ride *exactly* on the halfway bone
-- the trunk's rotation followed by half of the shoulder's relative rotation (same axis, half
the angle), pivoting at the shoulder centre -- and some blend it with the upper arm. Given the
true pose, MG03 must find those weights and reproduce every marker to numerical precision; a
halfway bone at the elbow, or halving the trunk-to-forearm rotation, cannot.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from offline.shoulder.evaluation import acceptance
from offline.shoulder.model import MG03Baseline
from offline.shoulder.synthesis import skin


def _rotations(rng, n, scale):
    return Rotation.from_rotvec(rng.normal(scale=scale, size=(n, 3))).as_matrix()


def _about(R_parent, t_parent, R_rel, joint):
    """A child rotating by ``R_rel`` relative to its parent about ``joint`` (rest space)."""
    R = R_parent @ R_rel
    J = np.einsum("fij,j->fi", R_parent, joint) + t_parent
    return R, J - np.einsum("fij,j->fi", R, joint)


def _chain_with_halfway_markers(rng, n=240):
    shoulder, elbow = np.array([0.0, 180.0, 0.0]), np.array([0.0, 480.0, 0.0])
    R0 = _rotations(rng, n, 0.15)
    t0 = rng.normal(scale=40.0, size=(n, 3))
    rel1 = _rotations(rng, n, 0.9)  # the shoulder turns a lot
    rel2 = Rotation.from_rotvec(np.outer(np.sin(np.linspace(0, 6, n)), [1.2, 0, 0])).as_matrix()
    R1, t1 = _about(R0, t0, rel1, shoulder)
    R2, t2 = _about(R1, t1, rel2, elbow)
    # the halfway bone, built here from the rotation vector (not with the code's helper)
    half = Rotation.from_rotvec(0.5 * Rotation.from_matrix(rel1).as_rotvec()).as_matrix()
    Rh, th = _about(R0, t0, half, shoulder)
    R = np.stack([R0, R1, R2], axis=1)
    t = np.stack([t0, t1, t2], axis=1)
    rest = np.concatenate([
        rng.normal(scale=50.0, size=(4, 3)) + [0, 0, 0],  # trunk
        rng.normal(scale=30.0, size=(4, 3)) + [0, 330, 0],  # upper arm
        rng.normal(scale=30.0, size=(4, 3)) + [0, 620, 0],  # forearm
        rng.normal(scale=30.0, size=(5, 3)) + shoulder,  # the girdle: the halfway bone
    ])  # fmt: skip
    W = np.zeros((17, 4))
    W[0:4, 0] = W[4:8, 1] = W[8:12, 2] = 1.0
    W[12:15, 3] = 1.0
    W[15] = [0, 0.3, 0, 0.7]
    W[16] = [0.4, 0, 0, 0.6]
    pos = skin(rest, W, np.concatenate([R, Rh[:, None]], 1), np.concatenate([t, th[:, None]], 1))
    skeleton = SimpleNamespace(
        chain_=[0, 1, 2],
        joints_=np.stack([np.full(3, np.nan), shoulder, elbow]),
        surface_=SimpleNamespace(rest=rest),
        pose=lambda positions, marker_set="full": (R, t),
    )
    return skeleton, pos, W


def test_mg03_reproduces_a_motion_made_of_the_halfway_bone(rng):
    skeleton, pos, W = _chain_with_halfway_markers(rng)
    mg = MG03Baseline(skeleton, frame_step=2).fit(pos)
    np.testing.assert_allclose(mg.weights_, W, atol=1e-6)
    synth = mg.synthesize(pos, "full")
    assert np.abs(synth - pos).max() < 1e-6
    assert mg.score(pos, "full").max < 1e-6
    # the girdle markers need the halfway bone: the 3-bone chain alone cannot place them
    three = MG03Baseline(skeleton, frame_step=2).fit(pos)
    three.weights_ = mg.weights_.copy()
    three.weights_[:, 1] += three.weights_[:, 3]
    three.weights_[:, 3] = 0.0
    assert np.abs(three.synthesize(pos, "full") - pos)[:, 12:].max() > 20.0


def _rules(errors, mg03):
    """The acceptance rules of issue #5, written out again: name -> passed."""
    out = {}
    for motion, sets in errors.items():
        for mset, by_k in sets.items():
            e = {int(k): v["avg"] for k, v in by_k.items()}
            out[f"{motion}/{mset}: e4 <= 0.85 e3"] = e[4] <= 0.85 * e[3]
            out[f"{motion}/{mset}: abs(e5 - e4) <= 5% e4"] = abs(e[5] - e[4]) <= 0.05 * e[4]
            out[f"{motion}/{mset}: ours(4) < MG03"] = e[4] < mg03[motion][mset]["avg"]
    return out


@pytest.mark.parametrize(
    ("e3", "e4", "e5", "m"),
    [
        (10.0, 8.0, 8.2, 9.0),  # all pass
        (10.0, 9.0, 9.0, 9.5),  # e4 not 15 % better than e3
        (10.0, 8.0, 9.0, 9.0),  # e5 drifts 12 %
        (10.0, 8.0, 8.0, 7.9),  # MG03 better
        (10.0, 8.5, 8.9, 8.5),  # boundaries: 8.5 <= 0.85 * 10 holds, 8.5 < 8.5 does not
    ],
)
def test_acceptance_flags_follow_the_raw_errors(e3, e4, e5, m):
    errors = {"rom": {"full": {"3": {"avg": e3}, "4": {"avg": e4}, "5": {"avg": e5}}}}
    mg03 = {"rom": {"full": {"avg": m}}}
    got = acceptance(errors, mg03)
    expected = _rules(errors, mg03)
    assert set(got) == set(expected)
    assert {k: bool(v["pass"]) for k, v in got.items()} == expected
