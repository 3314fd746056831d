"""Scoring labelers on a labeled capture (the ``evaluate`` contract of DESIGN.md).

The truth capture is corrupted (``scenes.corrupt``: down-sampling, gaps, ghosts, shuffle), the
first ``init_frames`` frames are given with their true labels (seed 003's supervised training
window), then every labeler sees the same anonymous frames. Scores count frames after the init
window only:

- ``accuracy``: visible true points given their true label / visible true points;
- ``ghost_labeled_rate``: ghost points given any marker label / ghost points;
- recovery: every sample removed by ``--gaps`` (truth known) that the labeler reports as
  RECOVERED is compared with the truth (mm); ``recovery_mean_ratio`` divides each error by the
  longest marker-pair distance of the marker's rigid body (seed 003 Fig. 8), as reported by the
  labeler's ``body_extent()``; ``recovery_rate`` is the fraction of removed samples recovered;
- ``ms_per_frame_p50/p99``: wall time of ``process`` per frame in this process, after warm-up.

A method that does not exist is never scored: ``available_methods`` says why.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labeler_service.capture import Capture
from labeler_service.errors import MocapError, SceneError
from labeler_service.labeling.frame import FrameLabeler, MarkerState
from labeler_service.labeling.registry import make_labeler
from labeler_service.scenes.corrupt import CorruptionSpec, StreamFrames, corrupt

WARMUP_FRAMES = 10  # frames after the init window whose time is not counted

#: ``evaluate``'s method name -> the registry's labeler kind (``make_labeler``)
METHODS: dict[str, str] = {"online": "online", "closest-point": "baseline"}


def available_methods() -> dict[str, str | None]:
    """Method name -> ``None`` when usable, else the reason it is not."""
    out: dict[str, str | None] = {}
    for name in METHODS:
        if name == "online":
            try:
                import labeler_service.labeling.labeler as mod

                out[name] = None if hasattr(mod, "Labeler") else "no Labeler class"
            except ImportError as exc:
                out[name] = f"the online labeler is not available ({exc})"
        else:
            out[name] = None
    return out


@dataclass
class MethodScore:
    """Scores of one method on one corrupted stream."""

    method: str
    accuracy: float
    ghost_labeled_rate: float | None
    recovery_mean_mm: float | None
    recovery_p95_mm: float | None
    recovery_mean_ratio: float | None
    recovery_rate: float | None
    ms_per_frame_p50: float
    ms_per_frame_p99: float
    per_frame_accuracy: np.ndarray = field(repr=False)
    #: Samples removed by ``--gaps`` after the init window, and how many of them came back
    #: RECOVERED (the counts behind ``recovery_rate``; not part of ``summary()``).
    removed: int = 0
    recovered: int = 0

    def summary(self) -> dict[str, Any]:
        def r(x: float | None, nd: int = 6) -> float | None:
            return None if x is None or not np.isfinite(x) else round(float(x), nd)

        return {
            "accuracy": r(self.accuracy),
            "ghost_labeled_rate": r(self.ghost_labeled_rate),
            "recovery_mean_mm": r(self.recovery_mean_mm, 3),
            "recovery_p95_mm": r(self.recovery_p95_mm, 3),
            "recovery_mean_ratio": r(self.recovery_mean_ratio, 5),
            "recovery_rate": r(self.recovery_rate, 5),
            "ms_per_frame_p50": r(self.ms_per_frame_p50, 4),
            "ms_per_frame_p99": r(self.ms_per_frame_p99, 4),
        }


def score_labeler(
    labeler: FrameLabeler,
    stream: StreamFrames,
    init_frames: int,
    method: str = "",
    progress: Callable[[int], None] | None = None,
) -> MethodScore:
    """Feeds ``stream`` to ``labeler`` (labels on the first ``init_frames``) and scores it."""
    n = stream.n_frames
    if n <= init_frames:
        raise SceneError(f"{n} frames is not more than the {init_frames}-frame init window")
    labeler.warmup()

    correct = visible = ghosts = ghosts_labeled = 0
    per_frame = np.full(n, np.nan)
    times_ns: list[int] = []
    errors: list[float] = []
    error_markers: list[int] = []
    removed_total = 0
    for f in range(n):
        pts, truth = stream.points[f], stream.truth[f]
        labels = truth if f < init_frames else None
        t0 = time.perf_counter_ns()
        out = labeler.process(pts, float(stream.times[f]), labels)
        dt = time.perf_counter_ns() - t0
        if progress is not None:
            progress(f)
        if f < init_frames:
            continue
        if f >= init_frames + WARMUP_FRAMES:
            times_ns.append(dt)
        real = truth >= 0
        ok = int(np.count_nonzero(out.point_labels[real] == truth[real]))
        nv = int(np.count_nonzero(real))
        correct += ok
        visible += nv
        per_frame[f] = ok / nv if nv else np.nan
        ghosts += int(truth.size - nv)
        ghosts_labeled += int(np.count_nonzero(out.point_labels[~real] >= 0))
        gone = np.flatnonzero(stream.removed[f])
        if gone.size:
            removed_total += gone.size
            rec = gone[out.state[gone] == MarkerState.RECOVERED]
            if rec.size:
                err = np.linalg.norm(
                    out.positions[rec].astype(np.float64) - stream.positions[f, rec], axis=1
                )
                errors.extend(err.tolist())
                error_markers.extend(rec.tolist())
    times_ms = np.asarray(times_ns, dtype=np.float64) / 1e6
    if times_ms.size == 0:
        times_ms = np.asarray([np.nan])
    err_arr = np.asarray(errors)
    # Body extents are known once the labeler has trained: ask after the run.
    ratios = np.empty(0)
    if err_arr.size:
        body_extent = np.asarray(labeler.body_extent(), dtype=np.float64)
        ratios = err_arr / body_extent[np.asarray(error_markers, dtype=np.intp)]
        ratios = ratios[np.isfinite(ratios)]
    has_recovery = removed_total > 0 and method != "closest-point"
    return MethodScore(
        method=method,
        accuracy=correct / visible if visible else float("nan"),
        ghost_labeled_rate=ghosts_labeled / ghosts if ghosts else None,
        recovery_mean_mm=float(err_arr.mean()) if err_arr.size else None,
        recovery_p95_mm=float(np.percentile(err_arr, 95)) if err_arr.size else None,
        recovery_mean_ratio=float(np.mean(ratios)) if ratios.size else None,
        recovery_rate=(err_arr.size / removed_total) if has_recovery else None,
        ms_per_frame_p50=float(np.median(times_ms)),
        ms_per_frame_p99=float(np.percentile(times_ms, 99)),
        per_frame_accuracy=per_frame,
        removed=removed_total,
        recovered=int(err_arr.size),
    )


def resolve_methods(requested: Sequence[str] | None) -> tuple[list[str], list[str]]:
    """The methods to score and notes about skipped ones; unknown/unavailable asks -> error."""
    avail = available_methods()
    notes = []
    if not requested:
        methods = [m for m, why in avail.items() if why is None]
        notes += [f"{m} not scored: {why}" for m, why in avail.items() if why is not None]
        return methods, notes
    methods = []
    for m in requested:
        if m not in avail:
            raise MocapError(f"unknown method {m!r} (choose from {', '.join(avail)})")
        if avail[m] is not None:
            raise MocapError(f"method {m!r} cannot be scored: {avail[m]}")
        if m not in methods:
            methods.append(m)
    return methods, notes


def evaluate(
    capture: Capture,
    methods: Sequence[str] | None = None,
    downsample: int = 1,
    init_frames: int = 50,
    gaps: int = 0,
    gap_frames: int = 20,
    ghosts: float = 0.0,
    seed: int = 0,
    show_progress: bool = False,
) -> tuple[dict[str, Any], dict[str, MethodScore]]:
    """Scores the chosen methods on one corrupted version of ``capture``.

    Returns the JSON report (DESIGN.md keys for the first method, ``baseline_accuracy`` for the
    closest-point baseline, and every method under ``methods``) and the full scores.
    """
    names, notes = resolve_methods(methods)
    if init_frames < 1:
        raise SceneError(f"init-frames must be >= 1, got {init_frames}")
    spec = CorruptionSpec(
        downsample=downsample,
        gaps=gaps,
        gap_frames=gap_frames,
        ghosts=ghosts,
        protect_frames=init_frames,
        seed=seed,
    )
    stream = corrupt(capture, spec)
    if not stream.marker_names:
        raise SceneError(f"{capture.source or 'capture'}: no labeled markers to score")
    scores: dict[str, MethodScore] = {}
    for name in names:
        labeler = make_labeler(METHODS[name], marker_names=stream.marker_names, rate=stream.rate)
        scores[name] = _with_progress(
            lambda cb, lab=labeler, nm=name: score_labeler(lab, stream, init_frames, nm, cb),  # type: ignore[misc]
            total=stream.n_frames,
            label=name,
            enabled=show_progress,
        )
    first = scores[names[0]]
    report: dict[str, Any] = {"method": names[0], **first.summary()}
    report["baseline_accuracy"] = (
        scores["closest-point"].summary()["accuracy"] if "closest-point" in scores else None
    )
    sub = Capture(stream.positions[:1], stream.marker_names, stream.rate)
    report.update(
        frames=stream.n_frames - init_frames,
        subjects=len(sub.subjects),
        markers=len(stream.marker_names),
        rate_hz=stream.rate,
        settings={
            "downsample": downsample,
            "init_frames": init_frames,
            "gaps": gaps,
            "gap_frames": gap_frames,
            "ghosts": ghosts,
            "seed": seed,
        },
        methods={k: v.summary() for k, v in scores.items()},
        notes=notes,
    )
    return report, scores


def _with_progress(
    fn: Callable[[Callable[[int], None] | None], MethodScore],
    total: int,
    label: str,
    enabled: bool,
) -> MethodScore:
    if not enabled:
        return fn(None)
    from rich.console import Console
    from rich.progress import Progress

    with Progress(console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(f"labeling ({label})", total=total)
        return fn(lambda f: bar.update(task, completed=f + 1) if f % 25 == 0 else None)
