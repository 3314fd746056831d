"""Multi-person scenes from single-person labeled takes.

No public, labeled, real multi-person optical capture exists, so the scenes the labeler is
scored on are *composed*: every take keeps its real markers, noise and occlusion gaps, but

1. it is cut to a window (``start``, ``frames``) after decimation to a common rate,
2. markers never visible, or visible in less than half of the window, are dropped,
3. it is turned by a yaw so that its mean heading faces the circle centre (plus a small seeded
   random offset); the heading is the mean over the window of ``left x up`` where ``left`` is
   the mean horizontal vector from every ``R*`` marker to its ``L*`` twin (``RSHO -> LSHO``),
4. its horizontal drift is removed: the per-frame median ``(x, y)`` of the visible markers,
   smoothed in time by a Gaussian of ``CENTRE_SMOOTH_S`` seconds (the body centre ``c_t``), is
   subtracted; the vertical motion is kept. Smoothing matters: the raw median jumps by
   centimetres when markers drop out or limbs swing, and subtracting it would make the whole
   body jump between frames, which no real performer does,
5. it is placed at angle ``phase + 2 pi k / n`` on a circle of radius ``radius`` around the
   origin (``phase`` seeded),
6. its labels get its subject name (the take's own prefix, else the file stem; duplicates
   become ``name_2``, ``name_3``).

With two takes at radius 300 mm the two people stand 600 mm apart facing each other: their arms
interleave, which is what makes closest-point labeling fail (seed 003, Sec. 1 and 4: the
5-person dog pile and 10-person hug at 120 Hz).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labeler_service.capture import Capture, read_capture, split_label
from labeler_service.errors import SceneError

#: A marker must be visible in at least this fraction of the window to be kept.
MIN_VISIBLE_FRACTION = 0.5
CENTRE_SMOOTH_S = 0.25  # Gaussian smoothing of the removed horizontal drift (seconds)
#: Half-width of the seeded random yaw offset added to "facing the centre" (degrees).
YAW_JITTER_DEG = 10.0


@dataclass(frozen=True)
class TakeSpec:
    """One performer: a labeled single-person take and where its window starts.

    ``path`` is read with :func:`read_capture` (``up`` = ``"y"`` for Y-up takes); instead of a
    path an in-memory ``capture`` may be given (tests, simulated takes). ``start`` is the first
    frame of the window in the take's own frame numbering (before decimation).
    """

    path: Path | None = None
    start: int = 0
    up: str = "z"
    capture: Capture | None = None

    def __post_init__(self) -> None:
        if (self.path is None) == (self.capture is None):
            raise SceneError("a take needs exactly one of a path or a capture")
        if isinstance(self.start, bool) or not isinstance(self.start, int | np.integer):
            raise SceneError(f"take start must be an integer frame, got {self.start!r}")
        if self.start < 0:
            raise SceneError(f"take start must be >= 0, got {self.start}")
        if self.up not in ("z", "y"):
            raise SceneError(f"unknown up axis {self.up!r} (use 'z' or 'y')")

    @classmethod
    def parse(cls, text: str) -> TakeSpec:
        """``FILE[:start[:up]]`` -> TakeSpec, e.g. ``walk.c3d:240:y``."""
        parts = str(text).split(":")
        if len(parts) > 3 or not parts[0]:
            raise SceneError(f"bad take {text!r}: expected FILE[:start[:up]]")
        start = 0
        if len(parts) >= 2 and parts[1] != "":
            try:
                start = int(parts[1])
            except ValueError:
                raise SceneError(
                    f"bad take {text!r}: start {parts[1]!r} is not a frame number"
                ) from None
            if start < 0:
                raise SceneError(f"bad take {text!r}: start must be >= 0")
        up = parts[2].lower() if len(parts) == 3 and parts[2] else "z"
        if up not in ("z", "y"):
            raise SceneError(f"bad take {text!r}: unknown up axis {parts[2]!r} (use z or y)")
        return cls(path=Path(parts[0]), start=start, up=up)

    @property
    def name(self) -> str:
        if self.capture is not None:
            return self.capture.source or "capture"
        return str(self.path)

    def load(self) -> Capture:
        if self.capture is not None:
            if self.up == "y":
                x, y, z = (self.capture.positions[..., i] for i in range(3))
                return self.capture.with_positions(np.stack([x, -z, y], axis=-1))
            return self.capture
        assert self.path is not None
        return read_capture(self.path, up=self.up)


TakeLike = TakeSpec | Capture | str | Path


def _as_spec(take: TakeLike) -> TakeSpec:
    if isinstance(take, TakeSpec):
        return take
    if isinstance(take, Capture):
        return TakeSpec(capture=take)
    if isinstance(take, str | Path):
        return TakeSpec.parse(str(take))
    raise SceneError(f"cannot use {type(take).__name__} as a take")


def decimation_step(take_rate: float, rate: float, name: str = "take") -> int:
    """Integer step that brings ``take_rate`` to ``rate``; a non-integer ratio is an error."""
    if not (math.isfinite(rate) and rate > 0):
        raise SceneError(f"--rate must be a positive number of Hz, got {rate}")
    ratio = take_rate / rate
    step = round(ratio)
    if step < 1 or abs(ratio - step) > 1e-6 * max(1.0, ratio):
        raise SceneError(
            f"{name}: cannot decimate {take_rate:g} Hz to {rate:g} Hz "
            f"(ratio {ratio:.4g} is not a whole number)"
        )
    return int(step)


def body_centre(positions: np.ndarray, sigma_frames: float = 0.0) -> np.ndarray:
    """``(F, 2)`` horizontal body centre: per-frame median ``x, y`` of the visible markers.

    Frames where nothing is visible are linearly interpolated from their neighbours. With
    ``sigma_frames > 0`` the track is smoothed by a Gaussian of that width (in frames).
    """
    f = positions.shape[0]
    vis = ~np.isnan(positions).any(axis=2)
    ok = vis.any(axis=1)
    if not ok.any():
        raise SceneError("take has no visible marker in the window")
    centre = np.full((f, 2), np.nan)
    with np.errstate(all="ignore"):
        for axis in (0, 1):
            centre[ok, axis] = np.nanmedian(positions[ok, :, axis], axis=1)
    if not ok.all():
        t: np.ndarray = np.arange(f)
        for axis in (0, 1):
            centre[~ok, axis] = np.interp(t[~ok], t[ok], centre[ok, axis])
    if sigma_frames > 0:
        from scipy.ndimage import gaussian_filter1d

        # Smooth around the straight-line drift so that the ends do not lag behind a walk.
        t = np.arange(f, dtype=np.float64)
        trend = np.polynomial.polynomial.polyfit(t, centre, 1)  # (2, 2): intercept, slope
        line = trend[0] + t[:, None] * trend[1]
        centre = line + gaussian_filter1d(centre - line, sigma_frames, axis=0, mode="nearest")
    return centre


def heading(capture: Capture) -> float | None:
    """Mean facing direction (radians, about +Z) over the capture, or None if unknown.

    ``left`` is the mean horizontal vector ``L* - R*`` over every left/right marker pair
    (``LSHO/RSHO``, ``LASI/RASI``, ...); facing = ``left x up`` = ``(left_y, -left_x)``. The
    per-frame unit headings are averaged on the circle.
    """
    names = [split_label(label)[1] for label in capture.labels]
    index = {n: i for i, n in enumerate(names)}
    pairs = [
        (i, index["R" + n[1:]])
        for i, n in enumerate(names)
        if len(n) > 1 and n[0] == "L" and "R" + n[1:] in index
    ]
    if not pairs:
        return None
    li = np.array([p[0] for p in pairs])
    ri = np.array([p[1] for p in pairs])
    pos = capture.positions.astype(np.float64)
    left = pos[:, li, :2] - pos[:, ri, :2]  # (F, P, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)  # all-NaN frames -> NaN
        left = np.nanmean(left, axis=1)  # (F, 2)
    forward = np.stack([left[:, 1], -left[:, 0]], axis=1)
    norm = np.linalg.norm(forward, axis=1)
    good = np.isfinite(norm) & (norm > 1e-6)
    if not good.any():
        return None
    unit = forward[good] / norm[good, None]
    mean = unit.mean(axis=0)
    if np.linalg.norm(mean) < 1e-3:
        return None
    return float(math.atan2(mean[1], mean[0]))


def _subject_name(cap: Capture, fallback: str) -> str:
    subjects = [s for s in cap.subjects if s]
    if len(subjects) > 1:
        raise SceneError(
            f"{fallback}: expected a single-person take, found subjects {', '.join(subjects)}"
        )
    name = subjects[0] if subjects else Path(fallback).stem
    return name.replace(":", "_") or "subject"


def _unique(names: Sequence[str]) -> list[str]:
    out: list[str] = []
    count: dict[str, int] = {}
    for n in names:
        count[n] = count.get(n, 0) + 1
        candidate = n if count[n] == 1 else f"{n}_{count[n]}"
        while candidate in out:
            count[n] += 1
            candidate = f"{n}_{count[n]}"
        out.append(candidate)
    return out


def _window(spec: TakeSpec, cap: Capture, step: int, frames: int) -> Capture:
    available = max(0, -(-(cap.n_frames - spec.start) // step))
    if available < frames:
        at = f" from frame {spec.start}" if spec.start else ""
        dec = f" after decimation by {step}" if step > 1 else ""
        raise SceneError(
            f"{spec.name}: only {available} frames available{at} at {cap.rate / step:g} Hz{dec}; "
            f"{frames} requested"
        )
    return cap.frames(spec.start, None, step).frames(0, frames)


def compose_scene(
    takes: Sequence[TakeLike],
    radius: float,
    frames: int,
    seed: int,
    rate: float | None = None,
) -> Capture:
    """Places single-person takes on a circle so that they interact (see the module docstring).

    ``takes`` are :class:`TakeSpec` (or ``"FILE[:start[:up]]"`` strings, paths, or in-memory
    :class:`Capture` objects). ``radius`` is in mm, ``frames`` the window length at the output
    rate, ``rate`` (Hz) decimates every take by an integer factor; without it all takes must
    share one rate. The result is reproducible for a given ``seed``.
    """
    specs = [_as_spec(t) for t in takes]
    if not specs:
        raise SceneError("compose needs at least one take")
    if not (isinstance(radius, int | float | np.floating | np.integer)) or not (
        math.isfinite(float(radius)) and radius >= 0
    ):
        raise SceneError(f"--radius must be a finite distance >= 0 mm, got {radius}")
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise SceneError(f"--frames must be a positive integer, got {frames}")
    rng = np.random.default_rng(seed)

    loaded = [s.load() for s in specs]
    if rate is None:
        rates = {round(c.rate, 6) for c in loaded}
        if len(rates) > 1:
            listing = ", ".join(
                f"{s.name} {c.rate:g} Hz" for s, c in zip(specs, loaded, strict=True)
            )
            raise SceneError(f"takes have different rates ({listing}): pass --rate HZ to decimate")
        out_rate = loaded[0].rate
    else:
        out_rate = float(rate)

    n = len(specs)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    jitter = np.deg2rad(rng.uniform(-YAW_JITTER_DEG, YAW_JITTER_DEG, size=n))
    names = _unique([_subject_name(c, s.name) for s, c in zip(specs, loaded, strict=True)])

    parts: list[Capture] = []
    notes: list[str] = []
    for k, (spec, cap, name) in enumerate(zip(specs, loaded, names, strict=True)):
        step = decimation_step(cap.rate, out_rate, spec.name) if rate is not None else 1
        ghosts = cap.ghost_mask
        if ghosts.any():
            cap = cap.select(np.flatnonzero(~ghosts))
            notes.append(f"{name}: dropped {int(ghosts.sum())} unlabeled tracks")
        if cap.n_markers == 0:
            raise SceneError(f"{spec.name}: no labeled markers")
        notes += [f"{name}: {x}" for x in cap.notes]
        win = _window(spec, cap, step, frames)
        win = win.with_positions(win.positions, notes=()).without_empty()
        notes += [f"{name}: {x}" for x in win.notes]
        frac = win.visible.mean(axis=0) if win.n_markers else np.zeros(0)
        sparse = np.flatnonzero(frac < MIN_VISIBLE_FRACTION)
        if sparse.size:
            notes.append(
                f"{name}: dropped markers visible in < {MIN_VISIBLE_FRACTION:.0%} of the window: "
                + ", ".join(f"{win.labels[i]} ({frac[i]:.0%})" for i in sparse)
            )
            win = win.select(np.flatnonzero(frac >= MIN_VISIBLE_FRACTION))
        if win.n_markers == 0:
            raise SceneError(f"{spec.name}: no marker is visible in the chosen window")

        theta = phase + 2.0 * math.pi * k / n
        face = heading(win)
        if face is None:
            notes.append(f"{name}: no left/right marker pairs, heading unknown: not turned")
            yaw = float(jitter[k])
        else:
            yaw = (theta + math.pi) - face + float(jitter[k])
        # turn first, then remove the drift: the per-axis median is not rotation-equivariant,
        # so measuring the centre after the turn puts it exactly on the placement point
        pos = win.positions.astype(np.float64)
        c, s = math.cos(yaw), math.sin(yaw)
        x, y = pos[..., 0].copy(), pos[..., 1].copy()
        pos[..., 0] = c * x - s * y
        pos[..., 1] = s * x + c * y
        pos[..., :2] -= body_centre(pos, CENTRE_SMOOTH_S * out_rate)[:, None, :]
        pos[..., 0] += radius * math.cos(theta)
        pos[..., 1] += radius * math.sin(theta)
        placed = win.with_positions(pos.astype(np.float32), rate=out_rate, notes=())
        parts.append(placed.with_subject(name))
        notes.append(
            f"{name}: from {spec.name} frame {spec.start}"
            + (f" every {step}" if step > 1 else "")
            + f", placed at {math.degrees(theta) % 360:.1f} deg, yaw {math.degrees(yaw) % 360:.1f}"
        )

    scene = Capture.concat_markers(parts, source="compose: " + " + ".join(s.name for s in specs))
    return scene.with_positions(
        scene.positions,
        notes=(*notes, f"composed {n} takes on a {radius:g} mm circle, seed {seed}"),
    )
