"""Multi-person scenes from single-person labeled takes.

No public, labeled, real multi-person optical capture exists, so the scenes the labeler is
scored on are *composed*: every take keeps its real markers, noise and occlusion gaps, but

1. its vertical axis is found (Z or Y up: detected from the body's extent over time when that
   is unambiguous, else it must be given) and one subject is picked from a multi-subject file,
2. it is resampled to the output rate (linear interpolation between the take's samples, any
   rate at or below the take's own) and cut to a window (``start``, ``frames``); a take that
   ends before the window does leaves the volume: its markers vanish,
3. markers never visible, or visible in less than half of the frames the take covers, are
   dropped,
4. it is turned by a yaw so that its mean heading faces the circle centre (plus a small seeded
   random offset); the heading is the mean over the window of ``left x up`` where ``left`` is
   the mean horizontal vector from every right marker to its left twin (``RSHO -> LSHO``,
   ``Shoulder_R -> Shoulder_L``, ``r knee -> l knee``, ...), or, without such pairs, the
   horizontal principal axes of the body,
5. its horizontal drift is removed: the per-frame median ``(x, y)`` of the visible markers,
   smoothed in time by a Gaussian of ``CENTRE_SMOOTH_S`` seconds (the body centre ``c_t``), is
   subtracted; the vertical motion is kept. Smoothing matters: the raw median jumps by
   centimetres when markers drop out or limbs swing, and subtracting it would make the whole
   body jump between frames, which no real performer does,
6. it is placed at angle ``phase + 2 pi k / n`` on a circle of radius ``radius`` around the
   origin (``phase`` seeded),
7. its labels get its subject name (the take's own prefix, else the file stem; duplicates
   become ``name_2``, ``name_3``).

Every decision that could be wrong (up axis, facing method, resampling, leaving) is written in
the scene's ``notes``. With two takes at radius 300 mm the two people stand 600 mm apart facing
each other: their arms interleave, which is what makes closest-point labeling fail (seed 003,
Sec. 1 and 4: the 5-person dog pile and 10-person hug at 120 Hz).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labeler_service.capture import Capture, read_capture, side_pairs, split_label
from labeler_service.capture.io import max_npz_bytes, npz_bytes, split_spec
from labeler_service.capture.model import MAX_COORD_MM, rate_problem
from labeler_service.errors import SceneError
from labeler_service.wording import plural

#: A marker must be visible in at least this fraction of the window to be kept.
MIN_VISIBLE_FRACTION = 0.5
#: Largest ``--radius``: half the distance past which readers map coordinates to missing.
MAX_RADIUS_MM = MAX_COORD_MM / 2
CENTRE_SMOOTH_S = 0.25  # Gaussian smoothing of the removed horizontal drift (seconds)
#: Half-width of the seeded random yaw offset added to "facing the centre" (degrees).
YAW_JITTER_DEG = 10.0
#: Up-axis detection: the taller of Y and Z (median per-frame body extent) wins when it is at
#: least this many times the other ...
UP_EXTENT_RATIO = 1.5
#: ... or when it is the only one whose per-frame lowest marker stays above the floor (the
#: 5th percentile of the per-frame minimum is at least this, mm; floors are at 0 in labs).
FLOOR_MM = -100.0
UP_AXES = ("auto", "z", "y")


@dataclass(frozen=True)
class TakeSpec:
    """One performer: a labeled take, where its window starts, its up axis and subject.

    ``path`` is read with :func:`read_capture`; instead of a path an in-memory ``capture`` may
    be given (tests, simulated takes). ``start`` is the first frame of the window in the take's
    own frame numbering (before resampling). ``up`` is ``"z"``, ``"y"`` (rotated to Z up) or
    ``"auto"`` (detected, see :func:`detect_up`; an ambiguous take is an error asking for it).
    ``subject`` picks one subject of a multi-subject file (required there).
    """

    path: Path | None = None
    start: int = 0
    up: str = "auto"
    capture: Capture | None = None
    subject: str | None = None

    def __post_init__(self) -> None:
        if (self.path is None) == (self.capture is None):
            raise SceneError("a take needs exactly one of a path or a capture")
        if isinstance(self.start, bool) or not isinstance(self.start, int | np.integer):
            raise SceneError(f"take start must be an integer frame, got {self.start!r}")
        if self.start < 0:
            raise SceneError(f"take start must be >= 0, got {self.start}")
        if self.up not in UP_AXES:
            raise SceneError(f"unknown up axis {self.up!r} (use 'z', 'y' or 'auto')")
        if self.subject is not None and (not self.subject or ":" in self.subject):
            raise SceneError(f"invalid subject name {self.subject!r}")

    @classmethod
    def parse(cls, text: str) -> TakeSpec:
        """``FILE[:start[:up[:subject]]]`` -> TakeSpec, e.g. ``walk.c3d:240:y`` or
        ``two.c3d:0::Viktor`` (an empty field keeps its default: 0, auto). FILE may hold
        colons: the longest prefix that is a capture file on disk is the file
        (:func:`split_spec`)."""
        syntax = "FILE[:start[:up[:subject]]]"
        path, fields = split_spec(str(text), 3)
        if len(fields) > 3 and path and Path(path).is_file():
            raise SceneError(
                f"bad take {text!r}: too many ':' fields after {path}: expected {syntax}"
            )
        if len(fields) > 3 or not path:
            raise SceneError(f"bad take {text!r}: expected {syntax}")
        parts = [path, *fields]
        start = 0
        if len(parts) >= 2 and parts[1] != "":
            try:
                start = int(parts[1])
            except ValueError:
                missing = "" if Path(path).exists() else f" (and no file {text!r} exists)"
                raise SceneError(
                    f"bad take {text!r}: start {parts[1]!r} is not a frame number{missing}"
                ) from None
            if start < 0:
                raise SceneError(f"bad take {text!r}: start must be >= 0")
        up = parts[2].lower() if len(parts) >= 3 and parts[2] else "auto"
        if up not in UP_AXES:
            raise SceneError(f"bad take {text!r}: unknown up axis {parts[2]!r} (use z, y or auto)")
        subject = parts[3] if len(parts) == 4 and parts[3] else None
        return cls(path=Path(parts[0]), start=start, up=up, subject=subject)

    @property
    def name(self) -> str:
        if self.capture is not None:
            return self.capture.source or "capture"
        return str(self.path)

    def load(self) -> tuple[Capture, list[str]]:
        """The take in Z up, reduced to its subject, and notes on the up axis and subject."""
        if self.capture is not None:
            cap = self.capture
        else:
            assert self.path is not None
            cap = read_capture(self.path)
        notes: list[str] = []
        cap = self._pick_subject(cap, notes)
        up = self.up
        if up == "auto":
            up, why = detect_up(cap, self.name)
            notes.append(f"up axis {up} (detected: {why})")
        else:
            notes.append(f"up axis {up} (given)")
        if up == "y":
            x, y, z = (cap.positions[..., i] for i in range(3))
            cap = cap.with_positions(np.stack([x, -z, y], axis=-1))
        return cap, notes

    def _pick_subject(self, cap: Capture, notes: list[str]) -> Capture:
        subjects = [s for s in cap.subjects if s]
        if not cap.subjects:
            raise SceneError(
                f"{self.name}: no labeled marker ({int(cap.ghost_mask.sum())} unlabeled tracks "
                "*N): compose places labeled single-person takes; label this one first "
                "(label --model)"
            )
        if self.subject is None:
            if len(subjects) > 1:
                raise SceneError(
                    f"{self.name}: expected a single-person take, found subjects "
                    f"{', '.join(subjects)}: pick one with FILE:start:up:SUBJECT"
                )
            return cap
        if self.subject not in subjects:
            raise SceneError(
                f"{self.name}: no subject {self.subject!r} (found {', '.join(subjects) or 'none'})"
            )
        cols = np.concatenate([cap.subject_columns(self.subject), np.flatnonzero(cap.ghost_mask)])
        if len(subjects) > 1:
            others = ", ".join(s for s in subjects if s != self.subject)
            notes.append(f"subject {self.subject} picked (left out: {others})")
        return cap.select(np.sort(cols))


TakeLike = TakeSpec | Capture | str | Path


def _as_spec(take: TakeLike) -> TakeSpec:
    if isinstance(take, TakeSpec):
        return take
    if isinstance(take, Capture):
        return TakeSpec(capture=take)
    if isinstance(take, str | Path):
        return TakeSpec.parse(str(take))
    raise SceneError(f"cannot use {type(take).__name__} as a take")


def resample(cap: Capture, start: int, rate: float, frames: int, name: str = "take") -> Capture:
    """``frames`` frames at ``rate`` Hz from the take's frame ``start`` on, by linear
    interpolation between neighbouring samples (a sample between a visible and a missing one is
    missing). A rate above the take's own is an error (no upsampling). Frames after the end of
    the take are missing: the performer has left. A whole ratio lands on the take's samples
    exactly (plain decimation)."""
    why = rate_problem(rate)
    if why is not None:
        raise SceneError(f"--rate {why}")
    if rate > cap.rate * (1 + 1e-9):
        raise SceneError(
            f"{name}: cannot resample {cap.rate:g} Hz up to {rate:g} Hz (choose a rate at or "
            f"below the lowest take rate)"
        )
    if start >= cap.n_frames:
        raise SceneError(f"{name}: start frame {start} is past its last frame {cap.n_frames - 1}")
    step = cap.rate / rate
    at = start + np.arange(frames, dtype=np.float64) * step
    i0 = np.floor(at + 1e-9).astype(np.int64)
    w = at - i0
    w[w < 1e-9] = 0.0
    inside = (i0 < cap.n_frames) & ((w == 0.0) | (i0 + 1 < cap.n_frames))
    # float32 out, float64 only for the frames inside the take (a scene longer than its take
    # is mostly missing: its memory is the output's)
    pos = np.full((frames, cap.n_markers, 3), np.nan, dtype=np.float32)
    src = cap.positions.astype(np.float64)
    k = np.flatnonzero(inside)
    a = src[i0[k]]
    b = src[np.minimum(i0[k] + 1, cap.n_frames - 1)]
    wk = w[k][:, None, None]
    # w == 0 takes the sample as is (b may be missing or past the end)
    pos[k] = np.where(wk == 0.0, a, (1.0 - wk) * a + wk * b)
    return cap.with_positions(pos, rate=float(rate))


def detect_up(cap: Capture, name: str = "take") -> tuple[str, str]:
    """``("z" | "y", reason)``: the take's vertical axis, from the body's extent over time.

    For each of Y and Z: the median over frames of the body's extent along it (max - min of the
    visible markers: a standing or moving person is taller than wide) and whether the lowest
    marker stays above the floor (5th percentile of the per-frame minimum >= ``FLOOR_MM``).
    The answer is the axis that is ``UP_EXTENT_RATIO`` times taller and above the floor, or
    else the only axis above the floor. Anything else is ambiguous: a :class:`SceneError` asks
    for ``:z`` or ``:y``.
    """
    pos = cap.positions[:, ~cap.ghost_mask]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)  # all-NaN frames
        hi, lo = np.nanmax(pos, axis=1), np.nanmin(pos, axis=1)  # (F, 3)
    ok = np.isfinite(hi).all(axis=1)
    if ok.sum() < 1:
        raise SceneError(f"{name}: no visible marker: cannot tell its up axis")
    extent = np.median(hi[ok] - lo[ok], axis=0)
    floor = np.percentile(lo[ok], 5, axis=0)
    ey, ez = float(extent[1]), float(extent[2])
    above = {"y": bool(floor[1] >= FLOOR_MM), "z": bool(floor[2] >= FLOOR_MM)}
    facts = (
        f"median body extent y {ey:.0f} mm, z {ez:.0f} mm; lowest marker "
        f"y {floor[1]:.0f} mm, z {floor[2]:.0f} mm"
    )
    tall = "z" if ez >= ey else "y"
    ratio = max(ey, ez) / max(min(ey, ez), 1e-9)
    if ratio >= UP_EXTENT_RATIO and above[tall]:
        return tall, facts
    if above["y"] != above["z"]:
        return ("y" if above["y"] else "z"), facts + " (the other axis goes below the floor)"
    raise SceneError(
        f"{name}: cannot tell whether Y or Z is up ({facts}): append :z or :y to the take"
    )


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
    if sigma_frames > 0 and f >= 2:  # (a straight line through one frame is no fit)
        from scipy.ndimage import gaussian_filter1d

        # Smooth around the straight-line drift so that the ends do not lag behind a walk.
        t = np.arange(f, dtype=np.float64)
        trend = np.polynomial.polynomial.polyfit(t, centre, 1)  # (2, 2): intercept, slope
        line = trend[0] + t[:, None] * trend[1]
        centre = line + gaussian_filter1d(centre - line, sigma_frames, axis=0, mode="nearest")
    return centre


def heading(capture: Capture) -> float | None:
    """Mean facing direction (radians, about +Z) over the capture, or None if unknown.

    ``left`` is the mean horizontal vector ``left - right`` over every twin marker pair
    (:func:`side_pairs`: ``LSHO/RSHO``, ``Shoulder_L/Shoulder_R``, ...); facing = ``left x up``
    = ``(left_y, -left_x)``. The per-frame unit headings are averaged on the circle.
    """
    names = [split_label(label)[1] for label in capture.labels]
    pairs = side_pairs(names)
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


def principal_heading(capture: Capture) -> tuple[float, str] | None:
    """Facing from the body's horizontal principal axes, for takes without twin markers.

    Per frame, the widest horizontal axis of the marker cloud is taken as left-right, so the
    facing line is across it; lines are averaged as axes (doubled angles). The sign (front or
    back) comes from the direction of horizontal travel when the take travels more than
    300 mm along that line, else it is unknown (``+`` kept) and the returned note says so.
    """
    pos = capture.positions.astype(np.float64)[..., :2]
    vis = np.logical_not(np.isnan(pos).any(axis=2))
    angles, weights = [], []
    for f in range(pos.shape[0]):
        p = pos[f, vis[f]]
        if p.shape[0] < 3:
            continue
        q = p - p.mean(axis=0)
        evals, evecs = np.linalg.eigh(q.T @ q / p.shape[0])
        if evals[1] <= 1e-9:
            continue
        wide = evecs[:, 1]
        angles.append(math.atan2(wide[1], wide[0]) - math.pi / 2)  # across the widest axis
        weights.append(1.0 - evals[0] / evals[1])  # anisotropy: a round cloud says nothing
    if not angles:
        return None
    a = np.asarray(angles)
    w = np.asarray(weights)
    c, s = float(np.sum(w * np.cos(2 * a))), float(np.sum(w * np.sin(2 * a)))
    if math.hypot(c, s) < 1e-6 * max(w.sum(), 1e-9):
        return None
    face = 0.5 * math.atan2(s, c)
    ok = vis.any(axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        centre = np.nanmean(np.where(vis[..., None], pos, np.nan), axis=1)[ok]
    travel = centre[-1] - centre[0] if centre.shape[0] > 1 else np.zeros(2)
    along = float(travel @ np.array([math.cos(face), math.sin(face)]))
    if abs(along) > 300.0:
        if along < 0:
            face += math.pi
        return face, "facing from principal axes, front = direction of travel"
    return face, "facing from principal axes, front/back unknown"


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


def _check_size(frames: int, caps: Sequence[Capture], names: Sequence[str]) -> None:
    """Refuses, before any take is resampled, a scene larger than a capture the project reads
    (:func:`~labeler_service.capture.io.max_npz_bytes`, 1.3 GB: a 10-minute, 10-person take at
    240 Hz), counted as its NPZ is (:func:`~labeler_service.capture.io.npz_bytes`: positions,
    labels and headers, so that the most frames it names are read back): ``--frames
    10000000`` asked numpy for 8.7 GiB per take and ended in a MemoryError traceback.
    Composing takes about three times the scene's size (a 187 MB scene: 0.55 GB more at its
    peak). ``names``: the subjects the takes are given, as the scene labels them."""
    labels = [
        f"{name}:{split_label(label)[1]}"
        for c, name in zip(caps, names, strict=True)
        for label, ghost in zip(c.labels, c.ghost_mask, strict=True)
        if not ghost
    ]
    markers = len(labels)
    size = npz_bytes(frames, labels)
    cap = max_npz_bytes()
    if size <= cap:
        return
    most = max(0, cap - npz_bytes(0, labels)) // max(1, markers * 3 * 4)
    raise SceneError(
        f"--frames {frames} of {plural(markers, 'marker')} is a {size / 1e9:.3g} GB scene "
        f"(float32 positions and labels, as an NPZ holds them), more than the {cap / 1e9:.3g} "
        f"GB a capture is read within (MOCAP_MAX_NPZ_BYTES): compose at most {most} frames"
    )


def compose_scene(
    takes: Sequence[TakeLike],
    radius: float,
    frames: int,
    seed: int,
    rate: float | None = None,
) -> Capture:
    """Places single-person takes on a circle so that they interact (see the module docstring).

    ``takes`` are :class:`TakeSpec` (or ``"FILE[:start[:up[:subject]]]"`` strings, paths, or
    in-memory :class:`Capture` objects). ``radius`` is in mm, ``frames`` the window length at
    the output rate, ``rate`` (Hz) resamples every take (at or below each take's own rate);
    without it all takes must share one rate. The result is reproducible for a given ``seed``.
    """
    specs = [_as_spec(t) for t in takes]
    if not specs:
        raise SceneError("compose needs at least one take")
    if not (isinstance(radius, int | float | np.floating | np.integer)) or not (
        math.isfinite(float(radius)) and radius >= 0
    ):
        raise SceneError(f"--radius must be a finite distance >= 0 mm, got {radius}")
    if radius > MAX_RADIUS_MM:
        # (1e8 mm wrote a scene that every reader maps to missing: beyond MAX_COORD_MM)
        raise SceneError(
            f"--radius {radius:g} mm is past {MAX_RADIUS_MM:g} mm: the scene's coordinates would "
            f"leave the {MAX_COORD_MM / 1e6:g} km that captures are read within"
        )
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise SceneError(f"--frames must be a positive integer, got {frames}")
    if rate is not None and rate_problem(rate) is not None:  # (before any take is read)
        raise SceneError(f"--rate {rate_problem(rate)}")
    rng = np.random.default_rng(seed)

    loaded = [s.load() for s in specs]
    if rate is None:
        rates = {round(c.rate, 6) for c, _ in loaded}
        if len(rates) > 1:
            listing = ", ".join(
                f"{s.name} {c.rate:g} Hz" for s, (c, _) in zip(specs, loaded, strict=True)
            )
            raise SceneError(
                f"takes have different rates ({listing}): pass --rate HZ to resample "
                f"(at most {min(rates):g})"
            )
        out_rate = loaded[0][0].rate
    else:
        out_rate = float(rate)
    names = _unique([_subject_name(c, s.name) for s, (c, _) in zip(specs, loaded, strict=True)])
    _check_size(frames, [c for c, _ in loaded], names)

    n = len(specs)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    jitter = np.deg2rad(rng.uniform(-YAW_JITTER_DEG, YAW_JITTER_DEG, size=n))

    parts: list[Capture] = []
    notes: list[str] = []
    for k, (spec, (cap, load_notes), name) in enumerate(zip(specs, loaded, names, strict=True)):
        notes += [f"{name}: {x}" for x in load_notes]
        ghosts = cap.ghost_mask
        if ghosts.any():
            cap = cap.select(np.flatnonzero(~ghosts))
            notes.append(f"{name}: dropped {int(ghosts.sum())} unlabeled tracks")
        if cap.n_markers == 0:
            raise SceneError(f"{spec.name}: no labeled markers")
        notes += [f"{name}: {x}" for x in cap.notes]
        win = resample(cap, spec.start, out_rate, frames, spec.name)
        # frames the take covers (after its end the performer has left the volume)
        covered = min(
            frames,
            int(math.floor((cap.n_frames - 1 - spec.start) * out_rate / cap.rate + 1e-9)) + 1,
        )
        if covered < frames:
            notes.append(
                f"{name}: the take ends at scene frame {covered} of {frames}: the performer "
                "leaves the volume (markers vanish)"
            )
        win = win.with_positions(win.positions, notes=()).without_empty()
        notes += [f"{name}: {x}" for x in win.notes]
        if win.n_markers == 0:
            raise SceneError(f"{spec.name}: no marker is visible in the chosen window")
        frac = win.visible[:covered].mean(axis=0)
        sparse = np.flatnonzero(frac < MIN_VISIBLE_FRACTION)
        if sparse.size == win.n_markers:
            # (it said "no marker is visible" of a take whose markers were all there, late)
            first = int(np.flatnonzero(win.visible[:covered].any(axis=1))[0])
            at = spec.start + first * cap.rate / out_rate
            where = (
                f"the first appears at take frame ~{at:.0f}: start the take there or compose "
                "fewer --frames"
                if first > 0
                else "they come and go: compose fewer --frames or another segment"
            )
            raise SceneError(
                f"{spec.name}: every marker is visible in fewer than {MIN_VISIBLE_FRACTION:.0%} "
                f"of the {covered} scene frames the take covers (best {frac.max():.0%}), so none "
                f"is kept; {where}"
            )
        if sparse.size:
            notes.append(
                f"{name}: dropped markers visible in < {MIN_VISIBLE_FRACTION:.0%} of the "
                f"{covered} frames the take covers: "
                + ", ".join(f"{win.labels[i]} ({frac[i]:.0%})" for i in sparse)
            )
            win = win.select(np.flatnonzero(frac >= MIN_VISIBLE_FRACTION))

        theta = phase + 2.0 * math.pi * k / n
        inside = win.frames(0, covered)
        face = heading(inside)
        if face is not None:
            how = "facing from left/right marker pairs"
        else:
            fallback = principal_heading(inside)
            face, how = fallback if fallback is not None else (None, "")
        if face is None:
            notes.append(f"{name}: no left/right pairs and no principal axis: not turned")
            yaw = float(jitter[k])
        else:
            notes.append(f"{name}: {how}")
            yaw = (theta + math.pi) - face + float(jitter[k])
        # turn first, then remove the drift: the per-axis median is not rotation-equivariant,
        # so measuring the centre after the turn puts it exactly on the placement point. The
        # frames after the take's end are missing (NaN stays NaN): only the covered ones are
        # placed, in float64
        part = win.positions[:covered].astype(np.float64)
        c, s = math.cos(yaw), math.sin(yaw)
        x, y = part[..., 0].copy(), part[..., 1].copy()
        part[..., 0] = c * x - s * y
        part[..., 1] = s * x + c * y
        del x, y
        part[..., :2] -= body_centre(part, CENTRE_SMOOTH_S * out_rate)[:, None]
        part[..., 0] += radius * math.cos(theta)
        part[..., 1] += radius * math.sin(theta)
        pos = win.positions.copy()
        pos[:covered] = part
        del part
        placed = win.with_positions(pos, rate=out_rate, notes=())
        parts.append(placed.with_subject(name))
        resampled = (
            "" if abs(cap.rate - out_rate) < 1e-9 else f" resampled {cap.rate:g} -> {out_rate:g} Hz"
        )
        notes.append(
            f"{name}: from {spec.name} frame {spec.start}{resampled}, placed at "
            f"{math.degrees(theta) % 360:.1f} deg, yaw {math.degrees(yaw) % 360:.1f}"
        )

    scene = Capture.concat_markers(parts, source="compose: " + " + ".join(s.name for s in specs))
    return scene.with_positions(
        scene.positions,
        notes=(
            *notes,
            f"composed {plural(n, 'take')} on a {radius:g} mm circle, seed {seed}",
            *(
                [f"radius 0 with {n} takes: every performer stands on the same spot"]
                if radius == 0 and n > 1
                else []
            ),
        ),
    )
