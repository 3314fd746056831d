"""Motion of the simulated performers: root paths, headings and joint-angle trajectories.

Every trajectory is smooth: min-jerk ramps between key poses, sinusoidal gait, and low-pass
filtered noise ("fidget") on every joint, all vectorised over frames. Three scenarios:

* ``walk``: each performer walks a loop (a circle through the middle of the room), starting
  at staggered times, so paths cross near the centre.
* ``hug``: performers walk in from a wide circle, wrap their arms around their neighbours and
  sway together as a group (seed 003's 10-person hug).
* ``pile``: performers walk in, kneel or crouch, and some lie over the others (seed 003's
  5-person dog pile): low, dense, interleaved.

Every scenario starts with a *separated phase* (at least 50 frames and 0.5 s) where everybody
stands well apart and moves arms and legs: seed 003 (Sec. 4) trains its structure and motion
models on the first 50 frames, assuming no interaction there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from labeler_service.scenes.sim.body import SEG, SEGMENTS, segment_kind

#: Horizontal clearance between neighbours on the start circle (mm).
START_SPACING = 1300.0


@dataclass(frozen=True)
class Motion:
    """One performer's motion: pelvis ``xy`` (F, 2) mm, heading ``yaw`` (F,) rad, joint
    ``angles`` (F, segments, 3) rad, and ``lift`` (F,) mm added above ground contact."""

    root_xy: np.ndarray
    yaw: np.ndarray
    angles: np.ndarray
    lift: np.ndarray


def separated_seconds(rate: float) -> float:
    """Length of the initial no-contact phase: >= 50 frames and >= 0.5 s, plus a margin."""
    return max(50.0 / rate, 0.5) + 0.25


def min_jerk(x: np.ndarray) -> np.ndarray:
    """``10 x^3 - 15 x^4 + 6 x^5`` on ``clip(x, 0, 1)``: a smooth 0 -> 1 ramp."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def smooth_noise(rng: np.random.Generator, n: int, rate: float, shape: tuple, hz: float):
    """Gaussian-filtered white noise with unit s.d., ``(n, *shape)``; bandwidth about ``hz``."""
    sigma = rate / (2.0 * math.pi * hz)
    pad = int(4 * sigma) + 1
    white = rng.standard_normal((n + 2 * pad, *shape))
    out = gaussian_filter1d(white, sigma, axis=0, mode="wrap")[pad : pad + n]
    sd = out.std(axis=0, keepdims=True) if n > 1 else np.ones((1, *shape))
    return out / np.where(sd > 0, sd, 1.0)


def _rest_pose(n: int) -> np.ndarray:
    """Standing, arms slightly out, elbows and knees a little bent (degrees)."""
    a = np.zeros((n, len(SEGMENTS), 3))
    for side in ("l", "r"):
        a[:, SEG[f"{side}_upperarm"]] = (0.0, 14.0, 0.0)
        a[:, SEG[f"{side}_forearm"]] = (12.0, 0.0, 0.0)
        a[:, SEG[f"{side}_shank"]] = (3.0, 0.0, 0.0)
    return a


# fidget amplitudes (deg, s.d.) per joint: (flexion, abduction, rotation)
_FIDGET = {
    "pelvis": (2.0, 1.5, 0.0),
    "torso": (4.0, 3.0, 5.0),
    "head": (8.0, 6.0, 12.0),
    "upperarm": (12.0, 8.0, 10.0),
    "forearm": (12.0, 0.0, 8.0),
    "hand": (10.0, 8.0, 0.0),
    "thigh": (4.0, 3.0, 3.0),
    "shank": (4.0, 0.0, 0.0),
    "foot": (3.0, 2.0, 0.0),
}
# joint limits (deg): (min, max) for flexion, abduction, rotation
_LIMITS = {
    "pelvis": ((-20, 60), (-20, 20), (-30, 30)),
    "torso": ((-25, 90), (-30, 30), (-40, 40)),
    "head": ((-40, 60), (-35, 35), (-70, 70)),
    "upperarm": ((-50, 170), (8, 150), (-70, 90)),
    "forearm": ((0, 150), (0, 0), (-60, 80)),
    "hand": ((-60, 60), (-20, 30), (0, 0)),
    "thigh": ((-25, 130), (-15, 45), (-40, 40)),
    "shank": ((0, 150), (0, 0), (0, 0)),
    "foot": ((-45, 30), (-20, 20), (0, 0)),
}


def _fidget(
    rng: np.random.Generator, n: int, rate: float, scale: np.ndarray, hz: float = 0.7
) -> np.ndarray:
    """Low-pass joint-angle noise (deg) with the :data:`_FIDGET` s.d. times ``scale`` (F,)."""
    amp = np.array([_FIDGET[segment_kind(s)] for s in SEGMENTS])  # (S, 3)
    noise = smooth_noise(rng, n, rate, (len(SEGMENTS), 3), hz=hz)
    return noise * amp[None] * scale[:, None, None]


def _clip(a: np.ndarray, soft: float = 3.0) -> np.ndarray:
    """Joint limits as a *smooth* clamp (softplus of width ``soft`` deg at both bounds), so a
    limited angle never has a velocity jump."""
    lo = np.array([[lim[0] for lim in _LIMITS[segment_kind(s)]] for s in SEGMENTS], dtype=float)
    hi = np.array([[lim[1] for lim in _LIMITS[segment_kind(s)]] for s in SEGMENTS], dtype=float)
    fixed = lo == hi
    above = lo + soft * np.logaddexp(0.0, (a - lo) / soft)
    out = hi - soft * np.logaddexp(0.0, (hi - above) / soft)
    return np.where(fixed, lo, out)


def _gait(phase: np.ndarray, amp: np.ndarray) -> np.ndarray:
    """Walking joint angles (deg) for gait ``phase`` (rad, left leg) and amplitude 0..1."""
    n = phase.shape[0]
    a = np.zeros((n, len(SEGMENTS), 3))
    for side, ph in (("l", phase), ("r", phase + math.pi)):
        a[:, SEG[f"{side}_thigh"], 0] = amp * (8.0 + 22.0 * np.sin(ph))
        a[:, SEG[f"{side}_shank"], 0] = amp * 27.0 * (1.0 + np.cos(ph - math.pi / 4))
        a[:, SEG[f"{side}_foot"], 0] = amp * 8.0 * np.sin(ph - math.pi / 2)
        a[:, SEG[f"{side}_upperarm"], 0] = amp * 16.0 * np.sin(ph + math.pi)
        a[:, SEG[f"{side}_forearm"], 0] = amp * 8.0 * (1.0 + np.sin(ph + math.pi))
    a[:, SEG["torso"], 2] = -amp * 5.0 * np.sin(phase)
    a[:, SEG["pelvis"], 1] = amp * 3.0 * np.sin(2 * phase)
    return a


def _warmup(t: np.ndarray, end: float, rng: np.random.Generator) -> np.ndarray:
    """Arm and leg movement in the separated phase so that segments move relative to each
    other while the labeler trains (seed 003 Sec. 4: 'enough motion between rigid bodies')."""
    n = t.shape[0]
    a = np.zeros((n, len(SEGMENTS), 3))
    w = 1.0 - min_jerk((t - end) / 0.8)
    ph = rng.uniform(0, 2 * math.pi, size=6)
    for i, side in enumerate(("l", "r")):
        a[:, SEG[f"{side}_upperarm"], 0] = w * 12.0 * np.sin(2 * math.pi * 0.8 * t + ph[i])
        a[:, SEG[f"{side}_upperarm"], 1] = w * 10.0 * (1 + np.sin(2 * math.pi * 0.7 * t + ph[2]))
        a[:, SEG[f"{side}_forearm"], 0] = w * 12.0 * (1 + np.sin(2 * math.pi * 1.0 * t + ph[3]))
        a[:, SEG[f"{side}_thigh"], 0] = w * 8.0 * np.sin(2 * math.pi * 0.8 * t + ph[4] + i * 2)
        a[:, SEG[f"{side}_shank"], 0] = w * 10.0 * (1 + np.sin(2 * math.pi * 0.8 * t + ph[5]))
    return a


def _phase(speed: np.ndarray, height: float, rate: float) -> np.ndarray:
    """Gait phase (rad) from walking speed (mm/s): stride length ~ 0.75 H."""
    return 2.0 * math.pi * np.cumsum(speed) / rate / (0.75 * height)


def _speed(xy: np.ndarray, rate: float) -> np.ndarray:
    v = np.gradient(xy, axis=0) * rate if xy.shape[0] > 1 else np.zeros_like(xy)
    return np.linalg.norm(v, axis=1)


def _start_radius(n: int) -> float:
    if n <= 1:
        return 1800.0
    return max(1800.0, START_SPACING / (2.0 * math.sin(math.pi / n)))


def _walk(k, n, height, t, rate, rng, layout) -> Motion:
    r0, phase0, order = layout
    sep = separated_seconds(rate)
    beta = phase0 + 2 * math.pi * k / n + rng.uniform(-0.2, 0.2)
    rho = r0 / 1.9 * rng.uniform(0.95, 1.05)
    centre = (r0 - rho) * np.array([math.cos(beta), math.sin(beta)])
    v = rng.uniform(1000.0, 1400.0)
    sigma = rng.choice([-1.0, 1.0])
    start = sep + order[k] / max(n, 1) * 3.0
    # walking time with a 1 s smooth start: integral of min_jerk
    dt = 1.0 / rate
    accel = min_jerk((t - start) / 1.0)
    tau = np.cumsum(accel) * dt
    psi = beta + sigma * v / rho * tau
    xy = centre + rho * np.stack([np.cos(psi), np.sin(psi)], axis=1)
    yaw = psi + sigma * math.pi / 2
    speed = v * accel
    amp = np.clip(speed / 1200.0, 0.0, 1.0)
    a = _rest_pose(len(t)) + _gait(_phase(speed, height, rate), amp)
    a += _warmup(t, sep, rng) + _fidget(rng, len(t), rate, 1.0 - 0.4 * amp)
    yaw = yaw + np.deg2rad(3.0) * smooth_noise(rng, len(t), rate, (), 0.5)
    return Motion(xy, yaw, np.deg2rad(_clip(a)), np.zeros(len(t)))


def _approach(k, n, t, rate, rng, layout, r_final):
    """Walk in along a radius from the start circle; returns xy, yaw, speed, arrival time."""
    r0, phase0, _ = layout
    sep = separated_seconds(rate)
    theta = phase0 + 2 * math.pi * k / n + rng.uniform(-0.08, 0.08)
    start = sep + rng.uniform(0.0, 0.6)
    mean_speed = rng.uniform(600.0, 800.0)
    duration = (r0 - r_final) / mean_speed
    s = min_jerk((t - start) / duration)
    radius = r0 - (r0 - r_final) * s
    direction = np.array([math.cos(theta), math.sin(theta)])
    xy = radius[:, None] * direction
    speed = _speed(xy, rate)
    yaw = np.full(len(t), theta + math.pi)
    return xy, yaw, speed, start + duration, direction


def _hug_pose(n_people: int, high: bool, rng: np.random.Generator) -> np.ndarray:
    """Arms around the partner (2 people) or the neighbours (3+), degrees.

    ``high`` arms go over the others' shoulders, low arms around their waists, so arms of
    neighbours layer instead of crossing at one height (as people do in a group hug).
    """
    if n_people <= 2:
        arm = (80.0, 55.0, 10.0, 75.0) if high else (60.0, 25.0, 30.0, 80.0)
    else:
        arm = (30.0, 95.0, 10.0, 45.0) if high else (40.0, 45.0, 30.0, 55.0)
    flex, abd, rot, elbow = arm
    a = np.zeros((len(SEGMENTS), 3))
    for side in ("l", "r"):
        a[SEG[f"{side}_upperarm"]] = (
            flex + rng.normal(0, 5),
            abd + rng.normal(0, 5),
            rot + rng.normal(0, 6),
        )
        a[SEG[f"{side}_forearm"]] = (elbow + rng.normal(0, 6), 0.0, 10.0)
        a[SEG[f"{side}_hand"]] = (10.0, 0.0, 0.0)
        a[SEG[f"{side}_shank"]] = (8.0, 0.0, 0.0)
        a[SEG[f"{side}_thigh"]] = (4.0, rng.uniform(0, 6), 0.0)
    a[SEG["torso"]] = (16.0 + rng.normal(0, 4), 0.0, 0.0)
    a[SEG["head"]] = (10.0, rng.normal(0, 8), rng.normal(0, 15))
    return a


def _hug(k, n, height, t, rate, rng, layout, shared) -> Motion:
    r_final = 220.0 if n <= 2 else 500.0 / (2.0 * math.sin(math.pi / n))
    if n == 1:
        r_final = 0.0
    xy, yaw, speed, arrive, direction = _approach(k, n, t, rate, rng, layout, r_final)
    f = len(t)
    hold = min_jerk((t - (arrive - 0.7)) / 1.4)
    target = _hug_pose(n, k % 2 == 0, rng)
    base = _rest_pose(f) + _gait(_phase(speed, height, rate), np.clip(speed / 1200.0, 0, 1))
    a = base * (1.0 - hold)[:, None, None] + target[None] * hold[:, None, None]
    a += _warmup(t, separated_seconds(rate), rng)
    a += _fidget(rng, f, rate, 1.0 - 0.3 * hold)
    # group sway (shared by everyone) + individual squeeze and shuffle
    sway_xy, sway_bend = shared
    a[:, SEG["torso"], 1] += hold * sway_bend
    squeeze = hold * (-40.0 + 30.0 * smooth_noise(rng, f, rate, (), 0.4))
    xy = xy + (squeeze[:, None] * direction) + hold[:, None] * sway_xy
    xy = xy + hold[:, None] * 25.0 * smooth_noise(rng, f, rate, (2,), 0.5)
    yaw = yaw + hold * np.deg2rad(6.0) * smooth_noise(rng, f, rate, (), 0.4)
    return Motion(xy, yaw, np.deg2rad(_clip(a)), np.zeros(f))


def _pile_pose(mode: str, rng: np.random.Generator) -> np.ndarray:
    """Kneeling, crouching or lying forward over the pile (degrees)."""
    a = np.zeros((len(SEGMENTS), 3))
    if mode == "kneel":
        legs = ((15.0, 8.0, 0.0), (105.0, 0.0, 0.0), (-30.0, 0.0, 0.0))
        torso = 55.0
    elif mode == "crouch":
        legs = ((100.0, 12.0, 0.0), (120.0, 0.0, 0.0), (20.0, 0.0, 0.0))
        torso = 40.0
    else:  # lie forward onto the others
        legs = ((50.0, 10.0, 0.0), (70.0, 0.0, 0.0), (-20.0, 0.0, 0.0))
        torso = 75.0
    for side in ("l", "r"):
        for seg, val in zip(("thigh", "shank", "foot"), legs, strict=True):
            a[SEG[f"{side}_{seg}"]] = np.asarray(val) + rng.normal(0, 5, 3) * (val != 0)
        a[SEG[f"{side}_upperarm"]] = (95.0 + rng.normal(0, 15), 30.0 + rng.normal(0, 10), 10.0)
        a[SEG[f"{side}_forearm"]] = (35.0 + rng.normal(0, 10), 0.0, 0.0)
    a[SEG["torso"]] = (torso + rng.normal(0, 6), rng.normal(0, 6), rng.normal(0, 8))
    a[SEG["head"]] = (-15.0, 0.0, rng.normal(0, 20))
    return a


def _pile(k, n, height, t, rate, rng, layout, modes) -> Motion:
    r_final = 0.0 if n == 1 else max(380.0, 420.0 / (2.0 * math.sin(math.pi / n)))
    xy, yaw, speed, arrive, direction = _approach(k, n, t, rate, rng, layout, r_final)
    f = len(t)
    down = min_jerk((t - (arrive - 0.3)) / 1.5)
    target = _pile_pose(modes[k], rng)
    base = _rest_pose(f) + _gait(_phase(speed, height, rate), np.clip(speed / 1200.0, 0, 1))
    a = base * (1.0 - down)[:, None, None] + target[None] * down[:, None, None]
    a += _warmup(t, separated_seconds(rate), rng)
    # struggling on the pile: larger, slower torso and arm movement
    struggle = _fidget(rng, f, rate, 1.0 + 0.6 * down, hz=0.5)
    a += struggle
    lift = np.zeros(f)
    if modes[k] == "lie":
        lift = down * rng.uniform(200.0, 400.0)
        xy = xy - (down * 150.0)[:, None] * direction
    xy = xy + down[:, None] * 60.0 * smooth_noise(rng, f, rate, (2,), 0.3)
    yaw = yaw + down * np.deg2rad(12.0) * smooth_noise(rng, f, rate, (), 0.3)
    return Motion(xy, yaw, np.deg2rad(_clip(a)), lift)


def plan_motion(
    scenario: str, heights: np.ndarray, t: np.ndarray, rate: float, rng: np.random.Generator
) -> list[Motion]:
    """Root paths and joint angles of every performer for one scenario."""
    n = len(heights)
    layout = (_start_radius(n), rng.uniform(0, 2 * math.pi), rng.permutation(n))
    if scenario == "walk":
        return [_walk(k, n, heights[k], t, rate, rng, layout) for k in range(n)]
    if scenario == "hug":
        direction = rng.normal(size=2)
        direction /= np.linalg.norm(direction)
        sway = 45.0 * np.sin(2 * math.pi * 0.35 * t + rng.uniform(0, 6.3))[:, None] * direction
        bend = 5.0 * np.sin(2 * math.pi * 0.35 * t + rng.uniform(0, 6.3))
        return [_hug(k, n, heights[k], t, rate, rng, layout, (sway, bend)) for k in range(n)]
    if scenario == "pile":
        modes = rng.choice(["kneel", "crouch", "lie"], size=n, p=[0.4, 0.3, 0.3])
        if n >= 2 and "lie" not in modes:
            modes[rng.integers(n)] = "lie"
        return [_pile(k, n, heights[k], t, rate, rng, layout, modes) for k in range(n)]
    raise ValueError(f"unknown scenario {scenario!r}")
