"""Articulated body model of the simulator: 15 segments, 51 Plug-in-Gait/CMU-like markers.

Body frame: x forward, y left, z up; lengths are fractions of the body height ``H`` (Winter's
anthropometric table: thigh 0.245 H, shank 0.246 H, upper arm 0.186 H, forearm 0.146 H,
hand 0.108 H, hip height 0.53 H, neck base 0.81 H). Every segment has a rest frame aligned with
the body frame and a joint to its parent; a pose is three angles per joint
(flexion, abduction, rotation) with the per-joint signs of :data:`SIGNS`, so positive flexion is
"forward" for hips, shoulders, elbows and the spine, "backward" for knees, and positive abduction
is "away from the midline" on both sides.

Markers sit on the skin: their rest positions in :data:`MARKERS` are bone landmarks (ASIS, C7,
epicondyles, malleoli, ...) a few centimetres off the bone, plus a per-performer placement jitter
(real marker placement varies by ~5 mm between sessions). Left/right asymmetries (``RBAK``,
different heights of ``UPA``/``FRM``/``THI``/``TIB``) are there on purpose, as in Plug-in-Gait,
so the two sides are distinguishable. Segments carry 3-7 markers, so each is a rigid body in the
sense of seed 003 (Sec. 3.1: rigid bodies of three to eight markers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SEGMENTS = (
    "pelvis",
    "torso",
    "head",
    "l_upperarm",
    "l_forearm",
    "l_hand",
    "r_upperarm",
    "r_forearm",
    "r_hand",
    "l_thigh",
    "l_shank",
    "l_foot",
    "r_thigh",
    "r_shank",
    "r_foot",
)
SEG = {name: i for i, name in enumerate(SEGMENTS)}


def segment_kind(segment: str) -> str:
    """``"l_thigh"`` -> ``"thigh"``; ``"pelvis"`` -> ``"pelvis"`` (the side-free kind)."""
    return segment.split("_", 1)[1] if "_" in segment else segment


PARENT = np.array([-1, 0, 1, 1, 3, 4, 1, 6, 7, 0, 9, 10, 0, 12, 13], dtype=np.intp)

# joint position of each segment in its parent's rest frame (units of H; left side y > 0)
JOINT = np.array(
    [
        [0.0, 0.0, 0.0],  # pelvis origin = hip-joint midpoint (placed by the root)
        [0.0, 0.0, 0.05],  # lumbar
        [0.0, 0.0, 0.23],  # neck
        [0.0, 0.115, 0.19],  # left shoulder
        [0.0, 0.0, -0.186],  # left elbow
        [0.0, 0.0, -0.146],  # left wrist
        [0.0, -0.115, 0.19],
        [0.0, 0.0, -0.186],
        [0.0, 0.0, -0.146],
        [0.0, 0.05, 0.0],  # left hip
        [0.0, 0.0, -0.245],  # left knee
        [0.0, 0.0, -0.246],  # left ankle
        [0.0, -0.05, 0.0],
        [0.0, 0.0, -0.245],
        [0.0, 0.0, -0.246],
    ]
)

# per-joint signs (flexion about y, abduction about x, rotation about z), see module docstring
SIGNS = np.array(
    [
        [1, -1, 1],  # pelvis: pitch forward, roll left, (yaw is the root's)
        [1, -1, 1],  # lumbar: bend forward, lean left, twist left
        [1, -1, 1],  # neck
        [-1, 1, 1],  # left shoulder: forward, out, internal
        [-1, 0, 1],  # left elbow
        [-1, 1, 0],  # left wrist
        [-1, -1, -1],
        [-1, 0, -1],
        [-1, -1, 0],
        [-1, 1, 1],  # left hip: forward, out
        [1, 0, 0],  # left knee: flexion moves the shank backward
        [-1, 1, 0],  # left ankle: dorsiflexion
        [-1, -1, -1],
        [1, 0, 0],
        [-1, -1, 0],
    ],
    dtype=np.float64,
)

# (name, segment, rest position in the segment frame, units of H). Left side only for pairs;
# the right twin mirrors y unless listed in _RIGHT_ONLY / _ASYM below.
_LEFT_MARKERS: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("LASI", "pelvis", (0.045, 0.07, 0.045)),
    ("LPSI", "pelvis", (-0.06, 0.028, 0.06)),
    ("LSHO", "torso", (-0.005, 0.12, 0.215)),
    ("LFHD", "head", (0.065, 0.035, 0.12)),
    ("LBHD", "head", (-0.045, 0.035, 0.115)),
    ("LUPA", "upperarm", (-0.012, 0.03, -0.09)),
    ("LUPB", "upperarm", (0.03, 0.015, -0.125)),
    ("LELB", "upperarm", (0.0, 0.028, -0.186)),
    ("LFRM", "forearm", (-0.01, 0.028, -0.07)),
    ("LWRA", "forearm", (0.018, 0.01, -0.146)),
    ("LWRB", "forearm", (-0.016, 0.01, -0.146)),
    ("LFIN", "hand", (0.0, 0.014, -0.08)),
    ("LHM2", "hand", (0.024, 0.006, -0.055)),
    ("LHM5", "hand", (-0.024, 0.01, -0.045)),
    ("LTHI", "thigh", (0.0, 0.05, -0.12)),
    ("LTHA", "thigh", (0.055, 0.02, -0.09)),
    ("LKNE", "thigh", (0.0, 0.042, -0.245)),
    ("LTIB", "shank", (0.0, 0.038, -0.12)),
    ("LSHN", "shank", (0.04, 0.0, -0.08)),
    ("LANK", "shank", (0.0, 0.035, -0.246)),
    ("LHEE", "foot", (-0.035, 0.0, -0.02)),
    ("LTOE", "foot", (0.1, 0.0, -0.025)),
    ("LMT5", "foot", (0.075, 0.035, -0.03)),
)
_MIDLINE: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("C7", "torso", (-0.045, 0.0, 0.235)),
    ("T10", "torso", (-0.075, 0.0, 0.095)),
    ("CLAV", "torso", (0.045, 0.0, 0.205)),
    ("STRN", "torso", (0.085, 0.0, 0.13)),
    ("RBAK", "torso", (-0.075, -0.055, 0.16)),  # asymmetric extra (Plug-in-Gait)
)
# right-side heights that differ from the left twin (Plug-in-Gait places them asymmetrically)
_ASYM_Z = {"RUPA": -0.11, "RFRM": -0.085, "RTHI": -0.15, "RTIB": -0.14}


def _marker_table() -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    names: list[str] = []
    segs: list[int] = []
    local: list[tuple[float, float, float]] = []
    for name, seg, (x, y, z) in _MIDLINE:
        names.append(name)
        segs.append(SEG[seg])
        local.append((x, y, z))
    for name, seg, (x, y, z) in _LEFT_MARKERS:
        for side in ("l", "r"):
            label = name if side == "l" else "R" + name[1:]
            full = seg if seg in ("pelvis", "torso", "head") else f"{side}_{seg}"
            names.append(label)
            segs.append(SEG[full])
            local.append((x, y if side == "l" else -y, _ASYM_Z.get(label, z)))
    return tuple(names), np.asarray(segs, dtype=np.intp), np.asarray(local, dtype=np.float64)


MARKER_NAMES, MARKER_SEGMENT, MARKER_LOCAL = _marker_table()

# points that may touch the ground (not markers): heel and toe soles, knee caps, in H units
CONTACTS = (
    (SEG["l_foot"], (-0.035, 0.0, -0.039)),
    (SEG["l_foot"], (0.11, 0.0, -0.039)),
    (SEG["r_foot"], (-0.035, 0.0, -0.039)),
    (SEG["r_foot"], (0.11, 0.0, -0.039)),
    (SEG["l_shank"], (0.035, 0.0, -0.01)),
    (SEG["r_shank"], (0.035, 0.0, -0.01)),
)


@dataclass(frozen=True)
class Body:
    """One performer's dimensions: joint offsets and marker positions in mm (rest frames)."""

    height: float  # mm
    joints: np.ndarray  # (segments, 3) mm, in the parent's frame
    markers: np.ndarray  # (markers, 3) mm, in the own segment's frame
    contacts: np.ndarray  # (contacts, 3) mm
    contact_segments: np.ndarray  # (contacts,)


def make_body(
    rng: np.random.Generator,
    height_range: tuple[float, float] = (1500.0, 1950.0),
    placement_mm: float = 5.0,
) -> Body:
    """A seeded body: height uniform in ``height_range`` (mm), girth factor ~ N(1, 0.07),
    markers jittered by ``placement_mm`` (s.d. per axis) around their landmarks."""
    height = float(rng.uniform(*height_range))
    girth = float(np.clip(rng.normal(1.0, 0.07), 0.85, 1.2))
    scale = np.array([girth, girth, 1.0])
    joints = JOINT * height * scale
    markers = MARKER_LOCAL * height * scale + rng.normal(0.0, placement_mm, MARKER_LOCAL.shape)
    csegs = np.array([c[0] for c in CONTACTS], dtype=np.intp)
    contacts = np.array([c[1] for c in CONTACTS]) * height * scale
    return Body(height, joints, markers, contacts, csegs)


def rotations(angles: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """``(F, 3)`` joint angles (rad) -> ``(F, 3, 3)`` matrices ``Rz(rot) @ Rx(abd) @ Ry(flex)``."""
    a = angles * signs
    f = a[:, 0]
    b = a[:, 1]
    r = a[:, 2]
    cf, sf = np.cos(f), np.sin(f)
    cb, sb = np.cos(b), np.sin(b)
    cr, sr = np.cos(r), np.sin(r)
    n = angles.shape[0]
    ry = np.zeros((n, 3, 3))
    ry[:, 0, 0], ry[:, 0, 2], ry[:, 1, 1], ry[:, 2, 0], ry[:, 2, 2] = cf, sf, 1.0, -sf, cf
    rx = np.zeros((n, 3, 3))
    rx[:, 0, 0], rx[:, 1, 1], rx[:, 1, 2], rx[:, 2, 1], rx[:, 2, 2] = 1.0, cb, -sb, sb, cb
    rz = np.zeros((n, 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = cr, -sr, sr, cr, 1.0
    return rz @ rx @ ry


def forward_kinematics(
    body: Body, root: np.ndarray, yaw: np.ndarray, angles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Segment frames for every frame.

    ``root`` ``(F, 3)`` is the pelvis origin in mm, ``yaw`` ``(F,)`` the heading (rad about +Z),
    ``angles`` ``(F, segments, 3)`` the joint angles. Returns rotations ``(F, S, 3, 3)`` and
    origins ``(F, S, 3)``: ``R_s = R_parent R_joint``, ``o_s = o_parent + R_parent j_s``.
    """
    n = root.shape[0]
    s = len(SEGMENTS)
    rot = np.empty((n, s, 3, 3))
    org = np.empty((n, s, 3))
    heading = rotations(np.stack([np.zeros(n), np.zeros(n), yaw], axis=1), np.ones(3))
    rot[:, 0] = heading @ rotations(angles[:, 0], SIGNS[0])
    org[:, 0] = root
    for k in range(1, s):
        p = PARENT[k]
        rot[:, k] = rot[:, p] @ rotations(angles[:, k], SIGNS[k])
        org[:, k] = org[:, p] + rot[:, p] @ body.joints[k]
    return rot, org


def place_points(
    rot: np.ndarray, org: np.ndarray, segments: np.ndarray, local: np.ndarray
) -> np.ndarray:
    """World positions ``(F, P, 3)`` of points fixed in segments: ``o_s + R_s p``."""
    return org[:, segments] + np.einsum("fpij,pj->fpi", rot[:, segments], local)
