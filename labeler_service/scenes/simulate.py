"""Simulated multi-person captures: articulated performers walking, hugging or piling up.

What the tests and the demo use when no real data is present, built to be hard for a
closest-point tracker and fair to a structure-based labeler (seed 003):

1. **Bodies** (:mod:`.sim.body`): 15 rigid segments, 51 markers on a Plug-in-Gait/CMU-like
   layout (3-7 per segment), seeded heights 1.5-1.95 m and girths.
2. **Motion** (:mod:`.sim.motion`): forward kinematics of smooth joint-angle trajectories
   within joint limits; root height from ground contact (the lowest sole, knee or marker
   touches the floor) plus a lift for performers lying on the pile. A separated phase of at
   least 50 frames and 0.5 s opens every scene.
3. **Measurement** (:mod:`.sim.occlusion`): soft-tissue wobble (a few mm, smooth), 0.5 mm
   jitter, occlusion gaps whose hazard grows with the number of other performers' markers
   nearby, and short-lived ghost points in ``*N`` columns.

Labels are ``P1:C7``, ``P1:LASI``, ...; ghosts ``*0``, ``*1``, ...
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter1d

from labeler_service.capture import Capture
from labeler_service.capture.model import rate_problem
from labeler_service.errors import SceneError
from labeler_service.scenes.corrupt import MAX_GHOSTS
from labeler_service.scenes.sim import SCENARIOS
from labeler_service.scenes.sim.body import (
    MARKER_NAMES,
    MARKER_SEGMENT,
    SEGMENTS,
    Body,
    forward_kinematics,
    make_body,
    place_points,
    segment_kind,
)
from labeler_service.scenes.sim.motion import Motion, plan_motion
from labeler_service.scenes.sim.occlusion import (
    OcclusionModel,
    ghost_points,
    neighbour_stats,
    occlusion_mask,
    wobble,
)

MAX_PERFORMERS = 10
#: Highest rate simulated (Hz): a full-frame optical system's; below the captures' limit
#: (:data:`~labeler_service.capture.model.MAX_RATE_HZ`, windowed high-speed modes).
MAX_SIM_RATE_HZ = 2000.0
#: Soft-tissue wobble s.d. per axis (mm): more on fleshy segments.
WOBBLE_MM = {"thigh": 2.0, "upperarm": 1.8, "pelvis": 1.5, "torso": 1.2}
WOBBLE_DEFAULT_MM = 1.0
#: Marker centre clearance above the floor (mm): a 14 mm marker lying on the floor.
FLOOR_CLEARANCE_MM = 8.0


def _wobble_amplitude() -> np.ndarray:
    """Wobble s.d. (mm) of every marker, from the kind of its segment."""
    kinds = [segment_kind(SEGMENTS[s]) for s in MARKER_SEGMENT]
    return np.array([WOBBLE_MM.get(k, WOBBLE_DEFAULT_MM) for k in kinds])


def pose_markers(body: Body, motion: Motion, rate: float) -> np.ndarray:
    """Noise-free marker positions ``(F, 51, 3)`` mm: forward kinematics + ground contact."""
    f = motion.yaw.shape[0]
    root = np.zeros((f, 3))
    root[:, :2] = motion.root_xy
    rot, org = forward_kinematics(body, root, motion.yaw, motion.angles)
    markers = place_points(rot, org, MARKER_SEGMENT, body.markers)
    contacts = place_points(rot, org, body.contact_segments, body.contacts)
    lowest = np.minimum(
        contacts[..., 2].min(axis=1), markers[..., 2].min(axis=1) - FLOOR_CLEARANCE_MM
    )
    z = -lowest
    if f > 3:
        z = gaussian_filter1d(z, max(0.5, 0.012 * rate), mode="nearest")
    markers[..., 2] += (z + motion.lift)[:, None]
    return markers


def _validate(performers, seconds, scenario, seed, rate, ghosts) -> int:
    if isinstance(performers, bool) or not isinstance(performers, int | np.integer):
        raise SceneError(f"--performers must be an integer, got {performers!r}")
    if not 1 <= performers <= MAX_PERFORMERS:
        raise SceneError(f"--performers must be 1..{MAX_PERFORMERS}, got {performers}")
    if scenario not in SCENARIOS:
        raise SceneError(f"unknown scenario {scenario!r} (use {', '.join(SCENARIOS)})")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise SceneError(f"--seed must be an integer, got {seed!r}")
    if not (
        isinstance(seconds, int | float | np.number) and math.isfinite(seconds) and seconds > 0
    ):
        raise SceneError(f"--seconds must be a positive number, got {seconds!r}")
    why = rate_problem(rate, high=MAX_SIM_RATE_HZ)
    if why is not None:
        raise SceneError(f"--rate {why} (the simulator's range)")
    if not (isinstance(ghosts, int | float | np.number) and 0 <= ghosts <= MAX_GHOSTS):
        raise SceneError(
            f"--ghosts must be a mean number of points per frame, 0 to {MAX_GHOSTS:g}, got {ghosts}"
        )
    frames = round(seconds * rate)
    if frames < 2:
        raise SceneError(f"{seconds:g} s at {rate:g} Hz is {frames} frame(s): need at least 2")
    if frames > 200_000:
        raise SceneError(f"{frames} frames is too long for one scene (max 200000)")
    return int(frames)


def simulate_scene(
    performers: int,
    seconds: float,
    scenario: str,
    seed: int,
    rate: float = 120.0,
    ghosts: float = 1.0,
    occlusion: OcclusionModel | None = None,
    jitter_mm: float = 0.5,
) -> Capture:
    """A labeled multi-person scene; see the module docstring. Reproducible for a ``seed``.

    ``performers`` 1-10 named ``P1..PN``; ``scenario`` one of ``walk``, ``hug``, ``pile``;
    ``ghosts`` the mean number of ghost points per frame.
    """
    frames = _validate(performers, seconds, scenario, seed, rate, ghosts)
    model = occlusion or OcclusionModel()
    root = np.random.SeedSequence(int(seed))
    body_ss, motion_ss, noise_ss = root.spawn(3)
    body_rng = np.random.default_rng(body_ss)
    bodies = [make_body(body_rng) for _ in range(performers)]
    heights = np.array([b.height for b in bodies])
    t = np.arange(frames, dtype=np.float64) / rate
    motions = plan_motion(scenario, heights, t, rate, np.random.default_rng(motion_ss))
    clean = np.concatenate(
        [pose_markers(b, m, rate) for b, m in zip(bodies, motions, strict=True)], axis=1
    )
    n_markers = len(MARKER_NAMES)
    owner = np.repeat(np.arange(performers), n_markers)

    rng = np.random.default_rng(noise_ss)
    amp = np.tile(_wobble_amplitude(), performers)
    skin = clean + wobble(rng, frames, rate, amp)
    measured = skin + rng.normal(0.0, jitter_mm, skin.shape)
    stride = max(1, round(rate / 60.0))
    count, closest = neighbour_stats(clean, owner, model.near_mm, stride)
    missing = occlusion_mask(rng, count, closest, rate, model)
    measured[missing] = np.nan
    ghost = ghost_points(rng, skin, rate, ghosts)

    labels = [f"P{k + 1}:{name}" for k in range(performers) for name in MARKER_NAMES]
    labels += [f"*{i}" for i in range(ghost.shape[1])]
    positions = np.concatenate([measured, ghost], axis=1).astype(np.float32)
    notes = [
        f"simulated {scenario}: {performers} performers, {seconds:g} s at {rate:g} Hz, seed {seed}",
        "heights (mm): " + ", ".join(f"P{k + 1} {h:.0f}" for k, h in enumerate(heights)),
        f"occluded {missing.mean():.1%} of marker samples; {ghost.shape[1]} ghost columns",
    ]
    return Capture(
        positions=positions,
        labels=tuple(labels),
        rate=rate,
        source=f"simulate:{scenario}:n{performers}:seed{seed}",
        notes=tuple(notes),
    )


__all__ = ["MAX_PERFORMERS", "SCENARIOS", "simulate_scene"]
