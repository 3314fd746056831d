"""Seeded corruptions that turn a labeled capture into what a live system delivers.

A labeled capture (the truth) becomes a stream of frames of anonymous points: optional
down-sampling (seed 003 Fig. 6), marker gaps with known truth (for recovery scoring, seed 003
Fig. 8), occluded body parts that reappear one marker at a time, random contiguous drop-outs,
ghost points near the performers, measurement jitter, and a per-frame shuffle. Missing samples
are simply absent from a frame. Columns named ``*N`` in the capture are ghost tracks: their
points are fed with the rest and carry truth -1.

``iter_stream`` yields frames lazily (long soak runs), ``corrupt`` collects them.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from labeler_service.capture import Capture
from labeler_service.errors import SceneError
from labeler_service.wording import plural

#: Most ghost points per frame a corruption adds on average: more than any capture shows (a
#: cluttered volume has tens); 1e9 asked the memory for 200 million points a frame.
MAX_GHOSTS = 1000.0


#: the command-line flag of each corruption setting that has one (evaluate, replay, demo)
_FLAGS = {
    "downsample": "--downsample",
    "gaps": "--gaps",
    "gap_frames": "--gap-frames",
    "occlude": "--occlude",
    "occlude_frames": "--occlude-frames",
    "dropouts": "--dropouts",
    "ghosts": "--ghosts",
    "jitter_mm": "--jitter",
    "protect_frames": "--init-frames",
    "leave": "--leave",
    "leave_seconds": "--leave-seconds",
}


@dataclass(frozen=True)
class CorruptionSpec:
    """What to do to a capture before it is streamed. Every random choice uses ``seed``.

    - ``downsample``: keep every N-th frame (the rate is divided by N).
    - ``gaps``, ``gap_frames``: for each subject, ``gaps`` randomly chosen markers are removed
      for ``gap_frames`` consecutive frames; one such gap event per subject starts every
      ``gap_period`` frames (default ``4 * gap_frames``) after ``protect_frames``.
    - ``occlude``, ``occlude_frames``: ``occlude`` times per subject, every marker within
      ``occlude_radius_mm`` (120 mm) of a random visible marker of that subject is hidden for
      ``occlude_frames`` frames; then the hidden markers reappear one at a time, in random
      order, ``occlude_stagger`` frames apart (a hand coming out from behind the body). The
      events of one subject fall in separate, equal slices of the frames after
      ``protect_frames``.
    - ``dropouts``: fraction of the remaining visible samples dropped as contiguous runs of
      mean length ``dropout_frames`` (occlusion-like), after ``protect_frames``.
    - ``ghosts``: mean number of ghost points per frame (at most :data:`MAX_GHOSTS`), each
      living a few frames 20-100 mm from a random visible marker.
    - ``jitter_mm``: Gaussian noise (standard deviation, per axis) on every point.
    - ``shuffle``: permute the points of every frame.
    - ``leave``, ``leave_seconds``: ``leave`` randomly chosen subjects each vanish entirely once
      (every marker gone) for ``leave_seconds`` and come back displaced: from the return on,
      the subject's trajectory is turned about the vertical (Z) axis through its centroid by a
      random angle (uniform, +-180 degrees) and shifted horizontally by a random vector of
      length up to ``leave_shift_mm`` (1 m). The absence starts at a random frame after
      ``protect_frames``, and the return leaves at least ``leave_seconds`` (at least one
      frame) before the take ends, and before the subject's own markers end (a short take
      in a composed scene): subjects that end too soon for that are not chosen. Applied
      before every other corruption.
    - ``protect_frames``: the first frames (after down-sampling) get no gaps, drop-outs,
      departures or ghosts (the labeler's supervised training window).
    """

    downsample: int = 1
    gaps: int = 0
    gap_frames: int = 20
    gap_period: int | None = None
    occlude: int = 0
    occlude_frames: int = 15
    occlude_radius_mm: float = 120.0
    occlude_stagger: int = 2
    dropouts: float = 0.0
    dropout_frames: int = 10
    ghosts: float = 0.0
    ghost_life_frames: float = 5.0
    jitter_mm: float = 0.0
    shuffle: bool = True
    protect_frames: int = 0
    leave: int = 0
    leave_seconds: float = 1.0
    leave_shift_mm: float = 1000.0
    seed: int = 0

    def __post_init__(self) -> None:
        fin = np.isfinite
        # setting -> (holds, what it must be)
        checks = {
            "downsample": (self.downsample >= 1, ">= 1"),
            "gaps": (self.gaps >= 0, ">= 0"),
            "gap_frames": (self.gap_frames >= 1, ">= 1"),
            "gap_period": (
                self.gap_period is None or self.gap_period >= self.gap_frames,
                "at least the gap's frames",
            ),
            "occlude": (self.occlude >= 0, ">= 0"),
            "occlude_frames": (self.occlude_frames >= 1, ">= 1"),
            "occlude_radius_mm": (
                self.occlude_radius_mm > 0 and fin(self.occlude_radius_mm),
                "positive and finite (mm)",
            ),
            "occlude_stagger": (self.occlude_stagger >= 0, ">= 0"),
            "dropouts": (0.0 <= self.dropouts < 1.0, "a fraction from 0 to below 1"),
            "dropout_frames": (self.dropout_frames >= 1, ">= 1"),
            "ghosts": (0.0 <= self.ghosts <= MAX_GHOSTS, f"from 0 to {MAX_GHOSTS:g} per frame"),
            "ghost_life_frames": (self.ghost_life_frames >= 1.0, ">= 1"),
            "jitter_mm": (self.jitter_mm >= 0.0 and fin(self.jitter_mm), ">= 0 and finite (mm)"),
            "protect_frames": (self.protect_frames >= 0, ">= 0"),
            "leave": (self.leave >= 0, ">= 0"),
            "leave_seconds": (
                self.leave_seconds > 0 and fin(self.leave_seconds),
                "positive and finite (seconds)",
            ),
            "leave_shift_mm": (
                self.leave_shift_mm >= 0 and fin(self.leave_shift_mm),
                ">= 0 and finite (mm)",
            ),
        }
        bad = [k for k, (ok, _) in checks.items() if not ok]
        if bad:
            name = bad[0]
            said = _FLAGS.get(name, name)  # (a setting no command-line flag sets: its name)
            raise SceneError(
                f"invalid corruption setting: {said} must be {checks[name][1]} "
                f"(got {getattr(self, name)!r})"
            )


@dataclass
class StreamFrame:
    """One corrupted frame: anonymous points, their true marker index (-1 = ghost), time."""

    index: int
    t: float
    points: np.ndarray  # (N, 3) float32
    truth: np.ndarray  # (N,) int32


@dataclass
class StreamFrames:
    """A whole corrupted capture, with the truth needed to score a labeler on it."""

    marker_names: tuple[str, ...]
    rate: float
    times: np.ndarray  # (F,)
    points: list[np.ndarray] = field(repr=False)
    truth: list[np.ndarray] = field(repr=False)
    positions: np.ndarray = field(repr=False)  # (F, M, 3) true positions, NaN = not captured
    removed: np.ndarray = field(repr=False)  # (F, M) visible samples removed by gaps/drop-outs
    #: ``--occlude`` events: (first hidden frame, hidden marker indices in reappearance order)
    occlusions: list[tuple[int, tuple[int, ...]]] = field(default_factory=list)
    #: ``--leave`` events: (subject, first frame gone, first frame back)
    departures: list[tuple[str, int, int]] = field(default_factory=list)
    #: where a corruption did less than asked, and why (a subject with fewer markers than
    #: ``--gaps``, an occlusion with no marker in view to hide)
    notes: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.points)


@dataclass
class StreamPlan:
    """The truth behind a corrupted stream: marker positions, what was removed, the rate."""

    marker_cols: np.ndarray
    ghost_cols: np.ndarray
    positions: np.ndarray  # (F, M, 3) markers only
    ghost_positions: np.ndarray  # (F, G, 3) ghost tracks already in the capture
    removed: np.ndarray  # (F, M)
    rate: float
    marker_names: tuple[str, ...]
    occlusions: list[tuple[int, tuple[int, ...]]] = field(default_factory=list)
    departures: list[tuple[str, int, int]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _plan(capture: Capture, spec: CorruptionSpec, rng: np.random.Generator) -> StreamPlan:
    if capture.n_frames == 0:
        raise SceneError(f"{capture.source or 'capture'}: no frames")
    cap = capture.frames(step=spec.downsample) if spec.downsample > 1 else capture
    if cap.n_frames == 0:
        raise SceneError(f"{capture.source or 'capture'}: no frames left after down-sampling")
    ghost = cap.ghost_mask
    marker_cols = np.flatnonzero(~ghost)
    ghost_cols = np.flatnonzero(ghost)
    positions = cap.positions[:, marker_cols]
    n_frames, n_markers = positions.shape[:2]
    start = min(spec.protect_frames, n_frames)
    names = tuple(cap.labels[i] for i in marker_cols)
    departures = _departures(spec, rng, positions, names, cap.rate, start)
    visible = ~np.isnan(positions).any(axis=2)
    removed = np.zeros_like(visible)
    notes: list[str] = []

    if spec.gaps > 0:
        if n_frames - start < spec.gap_frames:  # (no gap would fit: none was made, silently)
            raise SceneError(
                f"--gaps {spec.gaps} x {spec.gap_frames} frames does not fit in "
                f"{n_frames - start} frames after the init window (fewer --gap-frames, or "
                "--gaps 0)"
            )
        period = spec.gap_period or 4 * spec.gap_frames
        sub = Capture(positions, names, cap.rate)
        notes += _gaps_fit(spec.gaps, sub)
        for subject in sub.subjects:
            cols = sub.subject_columns(subject)
            k = min(spec.gaps, cols.size)  # (more than a subject has: refused or noted above)
            for f0 in range(start, n_frames - spec.gap_frames + 1, period):
                chosen = rng.choice(cols, size=k, replace=False)
                removed[f0 : f0 + spec.gap_frames, chosen] = True

    occlusions = _occlusions(spec, rng, positions, visible, names, cap.rate, start, removed, notes)

    if spec.dropouts > 0.0 and n_frames > start:
        span = n_frames - start
        runs = int(round(spec.dropouts * span * n_markers / spec.dropout_frames))
        lengths = rng.geometric(1.0 / spec.dropout_frames, size=runs)
        firsts = rng.integers(start, n_frames, size=runs)
        cols = rng.integers(0, n_markers, size=runs)
        for f0, n, m in zip(firsts, lengths, cols, strict=True):
            removed[f0 : f0 + n, m] = True

    removed &= visible
    return StreamPlan(
        marker_cols=marker_cols,
        ghost_cols=ghost_cols,
        positions=positions,
        ghost_positions=cap.positions[:, ghost_cols],
        removed=removed,
        rate=cap.rate,
        marker_names=names,
        occlusions=occlusions,
        departures=departures,
        notes=notes,
    )


def _gaps_fit(gaps: int, sub: Capture) -> list[str]:
    """``--gaps K`` against the subjects' marker counts: more than every subject has is
    refused (it was taken as "all of them" without a word); more than some have is noted
    (each of their gap events removes all their markers)."""
    counts = {s: int(sub.subject_columns(s).size) for s in sub.subjects}
    _need_subjects(f"--gaps {gaps}", counts)
    if gaps <= min(counts.values()):
        return []
    listing = ", ".join(f"{s or '(no prefix)'} {n}" for s, n in counts.items())
    if gaps > max(counts.values()):
        raise SceneError(
            f"--gaps {gaps}: no subject has that many markers ({listing}): a gap event removes "
            f"--gaps markers of each subject, at most {max(counts.values())} here"
        )
    fewer = [f"{s or '(no prefix)'} ({n})" for s, n in counts.items() if n < gaps]
    return [
        f"--gaps {gaps}: {', '.join(fewer)} {'has' if len(fewer) == 1 else 'have'} fewer "
        "markers: each of their gap events removes all of them"
    ]


def _need_subjects(what: str, subjects: object) -> None:
    """Refuses a per-subject corruption of a capture with no labeled subject (only unlabeled
    tracks ``*N``): ``--gaps`` ended in ``min() arg is an empty sequence``, ``--occlude`` made
    nothing without a word."""
    if not subjects:
        raise SceneError(
            f"{what}: the capture has no labeled marker (only unlabeled tracks), and it acts on "
            "each subject's markers: leave it out"
        )


def _departures(
    spec: CorruptionSpec,
    rng: np.random.Generator,
    positions: np.ndarray,
    names: tuple[str, ...],
    rate: float,
    start: int,
) -> list[tuple[str, int, int]]:
    """Applies ``--leave`` to ``positions`` (in place) and returns the departures."""
    if spec.leave <= 0:
        return []
    n_frames = positions.shape[0]
    sub = Capture(positions[:1], names, rate)
    subjects = [s for s in sub.subjects if s]
    if spec.leave > len(subjects):
        raise SceneError(
            f"--leave {spec.leave}: the scene has only {plural(len(subjects), 'subject')}"
        )
    away = int(round(spec.leave_seconds * rate))
    if away < 1:  # (it was made one frame without a word)
        raise SceneError(
            f"--leave-seconds {spec.leave_seconds:g} is shorter than a frame "
            f"({1000.0 / rate:.3g} ms at {rate:g} Hz): a departure lasts at least one frame"
        )
    last = n_frames - 2 * away  # latest first frame gone: back >= leave_seconds before the end
    if last < start:
        raise SceneError(
            f"--leave-seconds {spec.leave_seconds:g} does not fit: a departure and as long after "
            f"the return need {2 * away} frames after the init window, there are "
            f"{n_frames - start}"
        )
    # latest first frame gone of each subject: its return and leave_seconds after it fall
    # before its take ends (a composed short take ends inside the window: a departure after
    # that, or one whose return is, would bring back no one)
    visible = np.isfinite(positions[..., 0])
    latest: dict[str, int] = {}
    for name in subjects:
        frames = np.flatnonzero(visible[:, sub.subject_columns(name)].any(axis=1))
        end = int(frames[-1]) + 1 if frames.size else 0
        if end - 2 * away >= start:
            latest[name] = min(last, end - 2 * away)
    if spec.leave > len(latest):
        raise SceneError(
            f"--leave {spec.leave}: only {len(latest)} of the "
            f"{plural(len(subjects), 'subject')} are "
            f"present long enough for a departure and a return of --leave-seconds "
            f"{spec.leave_seconds:g} after the init window (a short take ends inside the scene)"
        )
    subjects = [name for name in subjects if name in latest]
    out = []
    for k in sorted(rng.choice(len(subjects), size=spec.leave, replace=False)):
        name = subjects[int(k)]
        cols = sub.subject_columns(name)
        f0 = int(rng.integers(start, latest[name] + 1))
        back = f0 + away
        angle = rng.uniform(-np.pi, np.pi)
        r = spec.leave_shift_mm * np.sqrt(rng.random())
        phi = rng.uniform(-np.pi, np.pi)
        shift = np.array([r * np.cos(phi), r * np.sin(phi), 0.0])
        block = positions[back:, cols].astype(np.float64)
        seen = block[0][np.isfinite(block[0, :, 0])]
        if seen.size == 0:
            seen = block[np.isfinite(block[..., 0])]
        centre = seen.mean(axis=0) if seen.size else np.zeros(3)
        centre[2] = 0.0
        c, s_ = np.cos(angle), np.sin(angle)
        rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        block = (block - centre) @ rot.T + centre + shift
        positions[back:, cols] = block.astype(positions.dtype)
        positions[f0:back, cols] = np.nan
        out.append((name, f0, back))
    return out


def _occlusions(
    spec: CorruptionSpec,
    rng: np.random.Generator,
    positions: np.ndarray,
    visible: np.ndarray,
    names: tuple[str, ...],
    rate: float,
    start: int,
    removed: np.ndarray,
    notes: list[str],
) -> list[tuple[int, tuple[int, ...]]]:
    """Marks ``--occlude`` events in ``removed`` (in place) and returns them. An event's frame
    is drawn in its slice of the frames; one where the subject shows no marker is drawn again
    among the slice's frames that show one (the event was dropped without a word), and a slice
    with none (the subject has left) is noted."""
    events: list[tuple[int, tuple[int, ...]]] = []
    n_frames = positions.shape[0]
    if spec.occlude <= 0:
        return events
    sub = Capture(positions, names, rate)
    _need_subjects(f"--occlude {spec.occlude}", sub.subjects)
    for subject in sub.subjects:
        cols = sub.subject_columns(subject)
        # longest possible event: hidden frames + every marker back one at a time
        tail = spec.occlude_frames + spec.occlude_stagger * (cols.size - 1)
        span = n_frames - start - tail
        if span < spec.occlude:
            raise SceneError(
                f"--occlude {spec.occlude} x {spec.occlude_frames} frames does not fit in "
                f"{n_frames - start} frames after the init window"
            )
        edges = np.linspace(start, start + span, spec.occlude + 1).astype(np.int64)
        missed = 0
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            f0 = int(rng.integers(lo, max(hi, lo + 1)))
            seen = cols[visible[f0, cols]]
            if seen.size == 0:
                shown = lo + np.flatnonzero(visible[lo : max(hi, lo + 1), cols].any(axis=1))
                if shown.size == 0:
                    missed += 1
                    continue
                f0 = int(rng.choice(shown))
                seen = cols[visible[f0, cols]]
            centre = positions[f0, rng.choice(seen)]
            d = np.linalg.norm(positions[f0, seen] - centre, axis=1)
            hidden = seen[d <= spec.occlude_radius_mm]
            order = rng.permutation(hidden)
            back = f0 + spec.occlude_frames
            for k, m in enumerate(order):
                removed[f0 : back + k * spec.occlude_stagger, m] = True
            events.append((f0, tuple(int(m) for m in order)))
        if missed:
            notes.append(
                f"--occlude {spec.occlude}: {subject or '(no prefix)'} shows no marker in "
                f"{plural(missed, 'slice')} of the frames an event is drawn in (gone or "
                f"occluded throughout): {spec.occlude - missed} of {spec.occlude} events"
            )
    return events


def _ghost_births(
    spec: CorruptionSpec, rng: np.random.Generator, anchors: np.ndarray, n_alive: int
) -> np.ndarray:
    """New ghost points for this frame (positions), keeping the mean count near ``ghosts``."""
    if anchors.shape[0] == 0:
        return np.empty((0, 3), dtype=np.float32)
    rate = spec.ghosts / spec.ghost_life_frames
    n = int(rng.poisson(rate))
    if n_alive == 0 and spec.ghosts > 0 and rng.random() < 0.1:
        n = max(n, 1)
    if n == 0:
        return np.empty((0, 3), dtype=np.float32)
    base = anchors[rng.integers(0, anchors.shape[0], size=n)]
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(20.0, 100.0, size=(n, 1))
    return (base + direction * radius).astype(np.float32)


def iter_stream(
    capture: Capture, spec: CorruptionSpec | None = None
) -> tuple[StreamPlan, Iterator[StreamFrame]]:
    """The corruption plan (truth) and a lazy iterator of corrupted frames."""
    spec = spec or CorruptionSpec()
    rng = np.random.default_rng(spec.seed)
    plan = _plan(capture, spec, rng)

    def frames() -> Iterator[StreamFrame]:
        # Ghosts alive: position (G,3), drift per frame (G,3), frames left (G,)
        g_pos = np.empty((0, 3), dtype=np.float32)
        g_vel = np.empty((0, 3), dtype=np.float32)
        g_left = np.empty((0,), dtype=np.int64)
        for f in range(plan.positions.shape[0]):
            keep = ~np.isnan(plan.positions[f]).any(axis=1) & ~plan.removed[f]
            idx = np.flatnonzero(keep).astype(np.int32)
            pts = [plan.positions[f, idx]]
            truth = [idx]
            gp = plan.ghost_positions[f]
            gp = gp[~np.isnan(gp).any(axis=1)]
            if gp.shape[0]:
                pts.append(gp)
                truth.append(np.full(gp.shape[0], -1, dtype=np.int32))
            if spec.ghosts > 0 and f >= spec.protect_frames:
                if g_left.size:
                    g_pos = g_pos + g_vel
                    alive = g_left > 0
                    g_pos, g_vel, g_left = g_pos[alive], g_vel[alive], g_left[alive] - 1
                born = _ghost_births(spec, rng, plan.positions[f, idx], g_left.size)
                if born.shape[0]:
                    g_pos = np.concatenate([g_pos, born])
                    g_vel = np.concatenate(
                        [g_vel, rng.normal(0.0, 2.0, size=born.shape).astype(np.float32)]
                    )
                    life = rng.geometric(1.0 / spec.ghost_life_frames, size=born.shape[0])
                    g_left = np.concatenate([g_left, life - 1])
                if g_pos.shape[0]:
                    pts.append(g_pos)
                    truth.append(np.full(g_pos.shape[0], -1, dtype=np.int32))
            points = np.concatenate(pts).astype(np.float32, copy=False)
            labels = np.concatenate(truth).astype(np.int32, copy=False)
            if spec.jitter_mm > 0:
                points = points + rng.normal(0.0, spec.jitter_mm, size=points.shape).astype(
                    np.float32
                )
            if spec.shuffle and points.shape[0] > 1:
                order = rng.permutation(points.shape[0])
                points, labels = points[order], labels[order]
            yield StreamFrame(
                index=f,
                t=f / plan.rate,
                points=np.ascontiguousarray(points, dtype=np.float32),
                truth=labels,
            )

    return plan, frames()


def corrupt(capture: Capture, spec: CorruptionSpec | None = None) -> StreamFrames:
    """All corrupted frames of ``capture`` at once, with their truth."""
    plan, frames = iter_stream(capture, spec)
    points, truth = [], []
    for fr in frames:
        points.append(fr.points)
        truth.append(fr.truth)
    n = len(points)
    return StreamFrames(
        marker_names=plan.marker_names,
        rate=plan.rate,
        times=np.arange(n, dtype=np.float64) / plan.rate,
        points=points,
        truth=truth,
        positions=plan.positions,
        removed=plan.removed,
        occlusions=plan.occlusions,
        departures=plan.departures,
        notes=plan.notes,
    )
