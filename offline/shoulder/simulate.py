"""Synthetic dense shoulder capture with ground truth (Hong et al. 2009, Sec. 3.1, simulated).

A right upper body is modelled as a 4-bone chain in a rest pose (mm, Z up, X lateral to the
right, Y anterior):

=========  ==================  =========================================
bone       parent joint        markers
=========  ==================  =========================================
chest      (root, 6 dof)       right half of an elliptic torso cylinder
girdle     SC joint (3 dof)    upper lateral torso (clavicle / scapula)
upper_arm  GH joint (3 dof)    cylinder around the humerus
forearm    elbow (3 dof)       cylinder around radius / ulna
=========  ==================  =========================================

Markers sit on a staggered grid (``spacing`` mm; 215 markers at the default 27 mm). Near each
joint the skin is blended: a marker's position is the linear blend of its two bones' transforms
(on the torso the girdle's share rises from 0 to 1 over 40 mm; the top of the upper arm takes up
to 0.25 of the girdle, skin around the elbow up to 0.3 of the neighbour), so the surface is not
piecewise rigid, as on a person; under large joint angles blended skin folds, which the
near-rigid triangle filter of :mod:`triangles` is there for. The girdle follows the arm with a
scapulo-humeral rhythm plus an independent shrug, which is what a 3-segment skeleton cannot
express. Soft-tissue artefact is smooth in time (low-pass 1.5 Hz) and in space (Gaussian
kernel, 30 mm: skin slides in patches), ``noise_mm`` std per axis, plus 0.3 mm white
measurement noise.

Motions (120 Hz): ``rom`` (range of motion, training), ``jumping_jack``, ``swimming``, ``curls``.
Ground truth per marker (true segment, blend weights, rest position) and per frame (world
positions of the SC, GH and elbow joint centres) is returned with each motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation

from labeler_service.capture import Capture
from labeler_service.capture.model import rate_problem
from labeler_service.errors import SceneError

SEGMENT_NAMES = ("chest", "girdle", "upper_arm", "forearm")
JOINT_NAMES = ("SC", "GH", "elbow")
#: (parent, child) segment indices of each joint in :data:`JOINT_NAMES`.
JOINT_SEGMENTS = ((0, 1), (1, 2), (2, 3))
MOTIONS = ("rom", "jumping_jack", "swimming", "curls")

# rest-pose joint centres (mm)
_SC = np.array([25.0, 40.0, 1400.0])
_GH = np.array([190.0, 0.0, 1385.0])
_ABD0 = np.deg2rad(50.0)  # rest abduction of the arm from hanging
_U0 = np.array([np.sin(_ABD0), 0.0, -np.cos(_ABD0)])  # arm axis in rest pose
_L_UPPER, _L_FORE = 290.0, 250.0
_SPINE = np.array([0.0, -40.0, 1150.0])
_ELBOW = _GH + _L_UPPER * _U0


@dataclass(frozen=True)
class ShoulderBody:
    """Rest-pose marker layout and skin of the synthetic shoulder.

    ``rest`` (M, 3) mm; ``weights`` (M, 4) rows sum to 1 (true blend weights over
    :data:`SEGMENT_NAMES`); ``segment`` (M,) argmax of ``weights``; ``joints`` (3, 3) rest-pose
    joint centres in :data:`JOINT_NAMES` order.
    """

    rest: np.ndarray
    weights: np.ndarray
    segment: np.ndarray
    joints: np.ndarray

    @property
    def n_markers(self) -> int:
        return int(self.rest.shape[0])

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(f"M{i + 1:03d}" for i in range(self.n_markers))


@dataclass(frozen=True)
class ShoulderMotion:
    """One simulated motion: the capture and its ground truth joint centres ``(F, 3, 3)``."""

    name: str
    capture: Capture
    joints: np.ndarray


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to ``axis`` (and to each other)."""
    a = axis / np.linalg.norm(axis)
    ref = np.array([0.0, 1.0, 0.0]) if abs(a[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def _cylinder(
    start: np.ndarray, axis: np.ndarray, radius: float, s0: float, s1: float, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """Grid of points on a cylinder; returns points and their distance ``s`` along the axis."""
    e1, e2 = _frame(axis)
    n_around = max(6, round(2 * np.pi * radius / spacing))
    n_along = max(2, round((s1 - s0) / spacing) + 1)
    pts, ss = [], []
    for i, s in enumerate(np.linspace(s0, s1, n_along)):
        offset = 0.5 * (i % 2)  # staggered rows: near-equilateral triangles
        for j in range(n_around):
            phi = 2 * np.pi * (j + offset) / n_around
            pts.append(start + s * axis + radius * (np.cos(phi) * e1 + np.sin(phi) * e2))
            ss.append(s)
    return np.asarray(pts), np.asarray(ss)


def build_body(spacing: float = 27.0) -> ShoulderBody:
    """The rest-pose marker layout (about 215 markers at the default 27 mm spacing)."""
    if not 15.0 <= spacing <= 60.0:
        raise SceneError(f"marker spacing must be within 15..60 mm, got {spacing}")
    # torso: right half of an elliptic cylinder, upper chest and shoulder top
    a_x, b_y = 170.0, 115.0
    z_lo, z_hi = 1270.0, 1395.0
    phis = []
    phi = np.deg2rad(-65.0)
    while phi <= np.deg2rad(65.0) + 1e-9:  # equal arc-length steps
        phis.append(phi)
        speed = np.hypot(a_x * np.sin(phi), b_y * np.cos(phi))
        phi += spacing / speed
    n_rows = max(2, round((z_hi - z_lo) / spacing) + 1)
    rows: list[list[float]] = []
    for i, z in enumerate(np.linspace(z_lo, z_hi, n_rows)):
        for j in range(len(phis) - (i % 2)):
            p = phis[j] if i % 2 == 0 else 0.5 * (phis[j] + phis[j + 1])
            # y > 0 in front: phi = 0 is the lateral side (x = a_x)
            rows.append([a_x * np.cos(p), b_y * np.sin(p), z])
    torso = np.asarray(rows)
    # girdle share: upper lateral torso, blended over 40 mm
    g = _smoothstep((torso[:, 0] - 75.0) / 40.0) * _smoothstep((torso[:, 2] - 1305.0) / 40.0)
    w_torso = np.zeros((len(torso), 4))
    w_torso[:, 0], w_torso[:, 1] = 1.0 - g, g

    upper, s_up = _cylinder(_GH, _U0, 44.0, 45.0, _L_UPPER - 40.0, spacing)
    w_up = np.zeros((len(upper), 4))
    to_girdle = 0.25 * (1.0 - _smoothstep((s_up - 45.0) / 30.0))  # deltoid blends with the girdle
    to_fore = _smoothstep((s_up - (_L_UPPER - 70.0)) / 30.0) * 0.3
    w_up[:, 1], w_up[:, 3] = to_girdle, to_fore
    w_up[:, 2] = 1.0 - to_girdle - to_fore

    fore, s_fo = _cylinder(_ELBOW, _U0, 34.0, 20.0, _L_FORE - 60.0, spacing)
    w_fo = np.zeros((len(fore), 4))
    to_upper = 0.3 * (1.0 - _smoothstep((s_fo - 20.0) / 30.0))
    w_fo[:, 2], w_fo[:, 3] = to_upper, 1.0 - to_upper

    rest = np.concatenate([torso, upper, fore])
    weights = np.concatenate([w_torso, w_up, w_fo])
    weights /= weights.sum(axis=1, keepdims=True)
    return ShoulderBody(
        rest=rest,
        weights=weights,
        segment=np.argmax(weights, axis=1).astype(np.intp),
        joints=np.stack([_SC, _GH, _ELBOW]),
    )


# ----------------------------------------------------------------------------- motion
def _smooth_random(rng: np.random.Generator, n: int, rate: float, cutoff: float) -> np.ndarray:
    """Zero-mean, unit-std smooth noise (white noise low-passed at ``cutoff`` Hz)."""
    pad = int(2.0 * rate / cutoff)  # filter start-up transients die out inside the padding
    x = rng.standard_normal(n + 2 * pad)
    sos = butter(2, cutoff / (0.5 * rate), output="sos")
    y = sosfiltfilt(sos, x)[pad:-pad]
    return y / max(float(np.std(y)), 1e-12)


def _angles(name: str, n: int, rate: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Joint angle curves (radians) of one motion; keys described in :func:`_pose`."""
    t = np.arange(n) / rate
    deg = np.deg2rad
    z = np.zeros(n)

    def wander(amp: float, cutoff: float = 0.4) -> np.ndarray:
        return amp * _smooth_random(rng, n, rate, cutoff)

    if name == "rom":
        # a slow sweep through elevation, plane of elevation, twist, elbow and shrug
        ph = rng.uniform(0, 2 * np.pi, 6)
        abd = deg(60) + deg(65) * np.sin(2 * np.pi * 0.11 * t + ph[0])
        flex = deg(35) + deg(60) * np.sin(2 * np.pi * 0.07 * t + ph[1])
        twist = deg(45) * np.sin(2 * np.pi * 0.17 * t + ph[2])
        elbow = deg(65) + deg(60) * np.sin(2 * np.pi * 0.13 * t + ph[3])
        pron = deg(50) * np.sin(2 * np.pi * 0.19 * t + ph[4])
        shrug = deg(12) * np.sin(2 * np.pi * 0.23 * t + ph[5]) + wander(deg(3))
        trunk = np.stack([wander(deg(6), 0.2), wander(deg(6), 0.2), wander(deg(10), 0.2)], 1)
        root = np.stack([wander(40, 0.2), wander(40, 0.2), wander(15, 0.3)], 1)
    elif name == "jumping_jack":
        f = 0.9
        c = 0.5 * (1 - np.cos(2 * np.pi * f * t))
        abd = deg(10) + deg(150) * c + wander(deg(4))
        flex = deg(10) + wander(deg(6))
        twist = deg(20) * c + wander(deg(5))
        elbow = deg(15) + deg(10) * c
        pron = wander(deg(10))
        shrug = deg(8) * c
        trunk = np.stack([wander(deg(2)), wander(deg(2)), wander(deg(3))], 1)
        root = np.stack([wander(10), wander(10), 60 * np.abs(np.sin(2 * np.pi * f * t))], 1)
    elif name == "swimming":
        f = 0.5
        ang = 2 * np.pi * f * t
        abd = deg(10) + deg(20) * np.sin(ang) ** 2 + wander(deg(4))
        flex = deg(90) + deg(95) * np.sin(ang - np.pi / 2)  # front crawl arm circle
        twist = deg(40) * np.cos(ang)
        elbow = deg(40) + deg(35) * np.sin(ang) ** 2
        pron = deg(30) * np.sin(ang)
        shrug = deg(6) * np.sin(ang)
        trunk = np.stack([wander(deg(3)), wander(deg(3)), deg(15) * np.sin(ang)], 1)
        root = np.stack([wander(15), wander(15), wander(10)], 1)
    elif name == "curls":
        f = 0.45
        c = 0.5 * (1 - np.cos(2 * np.pi * f * t))
        abd = deg(12) + wander(deg(4))
        flex = deg(10) + deg(15) * c
        twist = deg(-10) + wander(deg(5))
        elbow = deg(10) + deg(125) * c
        pron = deg(60) * c - deg(20)
        shrug = deg(3) * c + wander(deg(2))
        trunk = np.stack([wander(deg(2)), wander(deg(3)), wander(deg(3))], 1)
        root = np.stack([wander(8), wander(8), wander(5)], 1)
    else:
        raise SceneError(f"unknown shoulder motion {name!r} (choose from {', '.join(MOTIONS)})")
    return {
        "tilt": wander(deg(6), 0.3),
        "abd": abd, "flex": flex, "twist": twist, "elbow": elbow, "pron": pron,
        "shrug": shrug, "trunk": trunk, "root": root, "carry": z + deg(6) * np.sin(elbow),
    }  # fmt: skip


def _about(R: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """4x4 transforms of a rotation ``R`` (F,3,3) about a rest-space ``pivot``."""
    T = np.zeros((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = pivot - R @ pivot
    T[:, 3, 3] = 1.0
    return T


def _pose(a: dict[str, np.ndarray]) -> np.ndarray:
    """World transforms ``(F, 4, 4, 4)`` [frame, bone] of the chain (rest space -> world).

    Arm: abduction about -Y (anterior) beyond the 50 deg rest pose, flexion about +X, axial
    twist about the arm axis. Girdle: 40 % of the arm elevation (scapulo-humeral rhythm) plus
    the shrug about -Y at the SC joint, 20 % of flexion as protraction about +Z, a small
    random tilt about the clavicle. Elbow: flexion
    about the axis normal to the arm in the abduction plane, pronation about the forearm, a
    small carrying-angle change (so its centre is identifiable).
    """
    n = a["abd"].shape[0]
    y_axis, x_axis, z_axis = np.eye(3)[1], np.eye(3)[0], np.eye(3)[2]

    def rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
        return Rotation.from_rotvec(np.outer(angle, axis)).as_matrix()

    def rv(v: np.ndarray) -> np.ndarray:
        return Rotation.from_rotvec(v).as_matrix()

    elev = a["abd"] - _ABD0
    r_arm = rot(-y_axis, elev) @ rot(x_axis, a["flex"]) @ rot(_U0, a["twist"])
    girdle_rot = rot(-y_axis, 0.40 * (np.maximum(a["abd"], 0.0) - _ABD0) + a["shrug"])
    clav = (_GH - _SC) / np.linalg.norm(_GH - _SC)
    r_gird = rot(z_axis, 0.20 * a["flex"]) @ girdle_rot @ rot(clav, a["tilt"])
    flex_axis = np.cross(_U0, y_axis)
    flex_axis /= np.linalg.norm(flex_axis)
    r_elb = rot(-y_axis, a["elbow"]) @ rot(flex_axis, a["carry"]) @ rot(_U0, a["pron"])
    root = np.zeros((n, 4, 4))
    root[:, :3, :3] = rv(a["trunk"])
    # trunk rotation about a point on the spine, then the whole body translates
    root[:, :3, 3] = a["root"] + _SPINE - root[:, :3, :3] @ _SPINE
    root[:, 3, 3] = 1.0
    t_gird = root @ _about(r_gird, _SC)
    t_arm = t_gird @ _about(r_arm, _GH)
    t_fore = t_arm @ _about(r_elb, _ELBOW)
    return np.stack([root, t_gird, t_arm, t_fore], axis=1)


def _skin(body: ShoulderBody, T: np.ndarray) -> np.ndarray:
    """Marker positions ``(F, M, 3)`` by linear blend skinning of the true bones."""
    rest_h = np.concatenate([body.rest, np.ones((body.n_markers, 1))], axis=1)
    per_bone = np.einsum("fbij,mj->fbmi", T[:, :, :3, :], rest_h)  # (F, B, M, 3)
    return np.einsum("mb,fbmi->fmi", body.weights, per_bone)


#: Frame rates the motions are simulated at (their angle noise is low-passed at up to a few
#: Hz: below 10 Hz the filter is undefined; NaN or inf crashed it).
MIN_RATE_HZ = 10.0
#: Most occlusion gaps per marker per 1000 frames (gaps last 10-60 frames: 25 leave about
#: 1/8 of the samples; 2000 left 99.8 % missing).
MAX_GAP_RATE = 25.0


def check_motion(
    n_frames: int, rate: float, noise_mm: float, gap_rate: float, frames_name: str = "n_frames"
) -> None:
    """Refuses what :func:`simulate_motion` cannot simulate (``frames_name``: the frame
    count's name in the message, e.g. a command's option)."""
    if n_frames < 10:
        raise SceneError(f"{frames_name} must be >= 10 frames, got {n_frames}")
    why = rate_problem(rate, low=MIN_RATE_HZ)
    if why is not None:
        raise SceneError(f"rate must be within the simulator's range: rate {why}")
    if not (math.isfinite(noise_mm) and noise_mm >= 0):
        raise SceneError(f"noise must be a finite distance >= 0 mm, got {noise_mm}")
    if not (math.isfinite(gap_rate) and 0 <= gap_rate <= MAX_GAP_RATE):
        raise SceneError(
            f"gap rate must be 0-{MAX_GAP_RATE:g} gaps per marker per 1000 frames, got {gap_rate}"
        )


def simulate_motion(
    body: ShoulderBody,
    name: str,
    n_frames: int,
    rate: float = 120.0,
    noise_mm: float = 2.5,
    gap_rate: float = 0.0,
    random_state: int | np.random.Generator | None = None,
) -> ShoulderMotion:
    """Simulates one motion of ``body``: skinned markers (:func:`_skin`) plus soft-tissue noise.

    ``gap_rate`` is the expected number of occlusion gaps (10-60 frames) per marker per 1000
    frames, to exercise missing-sample handling.
    """
    check_motion(n_frames, rate, noise_mm, gap_rate)
    rng = np.random.default_rng(random_state)
    T = _pose(_angles(name, n_frames, rate, rng))  # (F, 4, 4, 4)
    pos = _skin(body, T)
    if noise_mm > 0:
        m = body.n_markers
        soft = np.stack([_smooth_random(rng, n_frames, rate, 1.5) for _ in range(m * 3)], 1)
        soft = soft.reshape(n_frames, m, 3)
        d2 = ((body.rest[:, None] - body.rest[None]) ** 2).sum(-1)
        kernel = np.exp(-d2 / (2.0 * 30.0**2))
        soft = np.einsum("mk,fki->fmi", kernel, soft)
        soft /= soft.std(axis=0, keepdims=True)
        pos += noise_mm * soft
        pos += 0.3 * rng.standard_normal(pos.shape)
    if gap_rate > 0:
        n_gaps = rng.poisson(gap_rate * n_frames / 1000.0, size=body.n_markers)
        for m, k in enumerate(n_gaps):
            for _ in range(k):
                length = int(rng.integers(10, 61))
                start = int(rng.integers(0, max(1, n_frames - length)))
                pos[start : start + length, m] = np.nan
    joints = np.stack(
        [
            np.einsum("fij,j->fi", T[:, p, :3, :], np.append(body.joints[j], 1.0))
            for j, (p, _) in enumerate(JOINT_SEGMENTS)
        ],
        axis=1,
    )
    cap = Capture(
        positions=pos.astype(np.float32),
        labels=tuple(f"synth:{x}" for x in body.labels),
        rate=rate,
        source=f"simulate-shoulder:{name}",
        notes=(f"synthetic shoulder, noise {noise_mm} mm",),
    )
    return ShoulderMotion(name=name, capture=cap, joints=joints)


def truth_arrays(body: ShoulderBody, motions: list[ShoulderMotion]) -> dict[str, np.ndarray]:
    """The ground-truth sidecar (``truth.npz``) content; format in docs/shoulder.md."""
    out: dict[str, np.ndarray] = {
        "labels": np.asarray([f"synth:{x}" for x in body.labels], dtype=str),
        "segment": body.segment,
        "weights": body.weights,
        "rest": body.rest,
        "segment_names": np.asarray(SEGMENT_NAMES, dtype=str),
        "joint_names": np.asarray(JOINT_NAMES, dtype=str),
        "joint_segments": np.asarray(JOINT_SEGMENTS, dtype=np.intp),
        "joint_rest": body.joints,
    }
    for m in motions:
        out[f"joints:{m.name}"] = m.joints
    return out
