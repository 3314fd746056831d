"""A synthetic subject with twin markers: a trunk and one arm whose forearm carries two wrist
markers placed symmetrically about the forearm's axis (a radius and an ulna marker), an elbow
and a finger marker on that axis. Every distance of the radius marker to the elbow and the
finger equals the ulna marker's, and the four forearm markers lie in one plane (no chirality):
only quadruples across the shoulder tell the two apart."""

from __future__ import annotations

import numpy as np

from labeler_service.capture import Capture

MARKERS = ("T0", "T1", "T2", "T3", "T4", "Shoulder", "Elbow", "Radius", "Ulna", "Finger", "Foot")
#: the trunk's markers and a foot rigid with it (human proportions: the subject's extent, head
#: to foot, is what a witness's reach is measured against)
TRUNK = np.array(
    [[0, 0, 0], [160, 0, -20], [40, 130, -150], [-60, 90, 140], [90, -40, -260]], dtype=float
)
FOOT = np.array([60.0, 0.0, -1300.0])
JOINT = np.array([220.0, 0.0, 0.0])  # shoulder, in the trunk's frame
UPPER, FOREARM, HALF_WIDTH, HAND = 280.0, 250.0, 40.0, 90.0


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def twin_capture(seed: int, frames: int = 240, rate: float = 120.0) -> Capture:
    """The subject moving smoothly through random poses: the trunk turns about the vertical
    and walks, the arm swings within +-50 degrees of hanging down and the forearm turns (pro-
    and supination) within +-30 degrees, so the wrist markers never pass to the other side."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate
    f1, f2, f4 = rng.uniform(0.2, 0.6, 3)
    p1, p2, p3, p4 = rng.uniform(0, 2 * np.pi, 4)
    pos = np.zeros((frames, len(MARKERS), 3))
    for k, tk in enumerate(t):
        R = _rot(np.array([0.0, 0.0, 1.0]), 0.8 * np.sin(2 * np.pi * 0.1 * tk + p1))
        origin = np.array([300.0 * tk, 50.0 * np.sin(tk), 1300.0])
        trunk = TRUNK @ R.T + origin
        joint = JOINT @ R.T + origin
        swing = np.radians(50.0) * np.sin(2 * np.pi * f1 * tk + p2)
        lift = np.radians(45.0) * np.sin(2 * np.pi * f2 * tk + p3)
        down = np.array([0.0, 0.0, -1.0])
        a = _rot(np.array([1.0, 0.0, 0.0]), swing) @ _rot(np.array([0.0, 1.0, 0.0]), lift) @ down
        a = R @ a
        elbow = joint + UPPER * a
        u = R @ _rot(np.array([1.0, 0.0, 0.0]), swing + np.radians(20.0)) @ down
        # the forearm's width direction: perpendicular to its axis, turned by pro/supination
        v0 = np.cross(u, R @ np.array([1.0, 0.0, 0.0]))
        v0 /= np.linalg.norm(v0)
        turn = np.radians(30.0) * np.sin(2 * np.pi * f4 * tk + p4)
        v = _rot(u, turn) @ v0
        wrist = elbow + FOREARM * u
        pos[k, :5] = trunk
        pos[k, 5] = joint
        pos[k, 6] = elbow
        pos[k, 7] = wrist + HALF_WIDTH * v
        pos[k, 8] = wrist - HALF_WIDTH * v
        pos[k, 9] = wrist + HAND * u
        pos[k, 10] = FOOT @ R.T + origin
    pos += rng.normal(0.0, 0.3, pos.shape)
    return Capture(pos.astype(np.float32), tuple(f"P:{m}" for m in MARKERS), rate, source="twin")
