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

from labeler_service.capture import Capture, split_label
from labeler_service.errors import MocapError, SceneError
from labeler_service.labeling.frame import FrameLabeler, LabeledFrame, MarkerState
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


#: Codes of the per-marker error raster (``MethodScore.raster``, ``FILE_errors.png``).
NOT_VISIBLE, CORRECT, SAME_SUBJECT, CROSS_SUBJECT, UNLABELED = 0, 1, 2, 3, 4
ERROR_KINDS = ("same_subject", "cross_subject", "unlabeled")
WORST_MARKERS = 10


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
    #: Error anatomy (see :class:`Scorer`): scored samples, error counts by kind, samples of
    #: markers never seen in the init window and the accuracy without them, the longest swap.
    visible: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    unseen_at_init: int = 0
    accuracy_seen: float = float("nan")
    max_swap_frames: int = 0
    max_swap: dict[str, Any] | None = None
    worst_markers: list[dict[str, Any]] = field(default_factory=list)
    marker_names: tuple[str, ...] = field(default=(), repr=False)
    #: ``(F, M)`` int8 codes per frame and marker (``NOT_VISIBLE`` .. ``UNLABELED``).
    raster: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int8), repr=False)

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
            "visible": self.visible,
            "errors": dict(self.errors),
            "unseen_at_init": self.unseen_at_init,
            "accuracy_seen": r(self.accuracy_seen),
            "max_swap_frames": self.max_swap_frames,
            "max_swap": self.max_swap,
            "worst_markers": self.worst_markers,
        }


class Scorer:
    """Accumulates the scores of one labeler, frame by frame (one implementation for
    ``evaluate``, ``demo`` and the benchmarks).

    Call :meth:`add` for every frame of the stream in order, init frames included (they are
    not scored, but say which markers the labeler was shown), then :meth:`result`. Per scored
    frame and true point: the point's label is *correct*, another marker of the *same subject*,
    a marker of *another subject*, or none (*unlabeled*); a ghost point given a label counts in
    ``ghost_taken``. ``out=None`` means the labeler's answer for that frame was lost: every true
    point counts as unlabeled.

    ``unseen_at_init`` counts the scored samples of markers that no init frame showed (they
    stay in ``accuracy``; ``accuracy_seen`` leaves them out). A *swap run* of a marker is a
    series of frames in which its point carries a wrong label; frames where the marker is not
    visible neither extend nor end a run, a correct or unlabeled frame ends it;
    ``max_swap_frames`` is the longest run over markers.

    Storage is allocated (and touched) up front for ``n_frames`` frames, so a long run adds no
    objects and no memory per frame (``benchmarks/bench_labeler.py`` measures leaks with it).
    """

    def __init__(
        self, marker_names: Sequence[str], init_frames: int, n_frames: int, method: str = ""
    ) -> None:
        self.names = tuple(marker_names)
        self.method = method
        self.init_frames = int(init_frames)
        subj = [split_label(n)[0] or "" for n in self.names]
        index = {s: i for i, s in enumerate(dict.fromkeys(subj))}
        self._subject = np.array([index[s] for s in subj], dtype=np.int64)
        m = len(self.names)
        self._seen = np.zeros(m, dtype=bool)
        self.n_frames = int(n_frames)
        self._raster = np.full((self.n_frames, m), NOT_VISIBLE, dtype=np.int8)
        self._per_frame = np.full(self.n_frames, np.nan)
        self._times_ms = np.full(self.n_frames, np.nan)
        self.ghosts = self.ghosts_taken = 0
        self._rec_err: list[float] = []
        self._rec_marker: list[int] = []
        self.removed = 0

    def add(
        self,
        f: int,
        truth: np.ndarray,
        out: LabeledFrame | None,
        *,
        removed: np.ndarray | None = None,
        positions: np.ndarray | None = None,
        dt_ns: int | None = None,
    ) -> None:
        """Scores frame ``f``: ``truth`` is the true marker of every input point (-1 = ghost),
        ``out`` the labeler's answer; ``removed`` (``(M,)`` bool) and ``positions``
        (``(M, 3)`` truth) score the recovery of hidden samples; ``dt_ns`` the labeling time."""
        truth = np.asarray(truth)
        real = truth >= 0
        if f < self.init_frames:
            self._seen[truth[real]] = True
            return
        if dt_ns is not None and f >= self.init_frames + WARMUP_FRAMES:
            self._times_ms[f] = dt_ns / 1e6
        row = self._raster[f]
        tm = truth[real]
        if out is None:
            row[tm] = UNLABELED
        else:
            lab = np.asarray(out.point_labels)
            got = lab[real]
            code = np.full(tm.size, UNLABELED, dtype=np.int8)
            wrong = (got >= 0) & (got != tm)
            code[got == tm] = CORRECT
            same = self._subject[np.where(wrong, got, 0)] == self._subject[tm]
            code[wrong & same] = SAME_SUBJECT
            code[wrong & ~same] = CROSS_SUBJECT
            row[tm] = code
            self.ghosts_taken += int(np.count_nonzero(lab[~real] >= 0))
            if removed is not None:
                gone = np.flatnonzero(removed)
                if gone.size:
                    self.removed += int(gone.size)
                    rec = gone[out.state[gone] == MarkerState.RECOVERED]
                    if rec.size and positions is not None:
                        err = np.linalg.norm(
                            out.positions[rec].astype(np.float64) - positions[rec], axis=1
                        )
                        self._rec_err.extend(err.tolist())
                        self._rec_marker.extend(rec.tolist())
        if out is None and removed is not None:
            self.removed += int(np.count_nonzero(removed))
        self.ghosts += int(truth.size - tm.size)
        nv = tm.size
        ok = int(np.count_nonzero(row == CORRECT))
        self._per_frame[f] = ok / nv if nv else np.nan

    def result(
        self,
        body_extent: np.ndarray | None = None,
        recovery: bool = True,
    ) -> MethodScore:
        """The scores so far. ``body_extent`` (``(M,)`` mm) gives ``recovery_mean_ratio``;
        ``recovery=False`` reports no recovery rate (a method that recovers nothing)."""
        raster = self._raster.copy()
        per_frame = self._per_frame.copy()
        vis = raster != NOT_VISIBLE
        visible = int(vis.sum())
        correct = int((raster == CORRECT).sum())
        errors = {
            "same_subject": int((raster == SAME_SUBJECT).sum()),
            "cross_subject": int((raster == CROSS_SUBJECT).sum()),
            "unlabeled": int((raster == UNLABELED).sum()),
            "ghost_taken": int(self.ghosts_taken),
        }
        unseen_cols = ~self._seen
        unseen = int(vis[:, unseen_cols].sum())
        seen_vis = visible - unseen
        seen_ok = int((raster[:, ~unseen_cols] == CORRECT).sum())
        swap_len, swap = _longest_swap(raster, self.names)
        bad = (vis & (raster != CORRECT)).sum(axis=0)
        order = [int(j) for j in np.argsort(-bad, kind="stable") if bad[j] > 0][:WORST_MARKERS]
        worst = [
            {
                "marker": self.names[j],
                "errors": int(bad[j]),
                "visible": int(vis[:, j].sum()),
                "same_subject": int((raster[:, j] == SAME_SUBJECT).sum()),
                "cross_subject": int((raster[:, j] == CROSS_SUBJECT).sum()),
                "unlabeled": int((raster[:, j] == UNLABELED).sum()),
                "seen_at_init": bool(self._seen[j]),
            }
            for j in order
        ]
        times_ms = self._times_ms[np.isfinite(self._times_ms)]
        if times_ms.size == 0:
            times_ms = np.asarray([np.nan])
        err = np.asarray(self._rec_err)
        ratios = np.empty(0)
        if body_extent is not None and err.size:
            ext = np.asarray(body_extent, dtype=np.float64)
            ratios = err / ext[np.asarray(self._rec_marker, dtype=np.intp)]
            ratios = ratios[np.isfinite(ratios)]
        return MethodScore(
            method=self.method,
            accuracy=correct / visible if visible else float("nan"),
            ghost_labeled_rate=self.ghosts_taken / self.ghosts if self.ghosts else None,
            recovery_mean_mm=float(err.mean()) if err.size else None,
            recovery_p95_mm=float(np.percentile(err, 95)) if err.size else None,
            recovery_mean_ratio=float(np.mean(ratios)) if ratios.size else None,
            recovery_rate=(err.size / self.removed) if recovery and self.removed else None,
            ms_per_frame_p50=float(np.median(times_ms)),
            ms_per_frame_p99=float(np.percentile(times_ms, 99)),
            per_frame_accuracy=per_frame,
            removed=self.removed,
            recovered=int(err.size),
            visible=visible,
            errors=errors,
            unseen_at_init=unseen,
            accuracy_seen=seen_ok / seen_vis if seen_vis else float("nan"),
            max_swap_frames=swap_len,
            max_swap=swap,
            worst_markers=worst,
            marker_names=self.names,
            raster=raster,
        )


def _longest_swap(raster: np.ndarray, names: Sequence[str]) -> tuple[int, dict[str, Any] | None]:
    """Longest run of wrong-label frames of one marker (absent frames skipped, see Scorer)."""
    best, where = 0, None
    wrong_any = np.flatnonzero(((raster == SAME_SUBJECT) | (raster == CROSS_SUBJECT)).any(axis=0))
    for j in wrong_any:
        col = raster[:, j]
        frames = np.flatnonzero(col != NOT_VISIBLE)
        wrong = (col[frames] == SAME_SUBJECT) | (col[frames] == CROSS_SUBJECT)
        # runs of True in `wrong` (consecutive among the frames where the marker is visible)
        edges = np.diff(np.concatenate([[0], wrong.astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        lengths = stops - starts
        k = int(np.argmax(lengths))
        if lengths[k] > best:
            best = int(lengths[k])
            where = {
                "marker": names[int(j)],
                "first_frame": int(frames[starts[k]]),
                "last_frame": int(frames[stops[k] - 1]),
            }
    return best, where


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
    scorer = Scorer(stream.marker_names, init_frames, n, method)
    for f in range(n):
        pts, truth = stream.points[f], stream.truth[f]
        labels = truth if f < init_frames else None
        t0 = time.perf_counter_ns()
        out = labeler.process(pts, float(stream.times[f]), labels)
        dt = time.perf_counter_ns() - t0
        if progress is not None:
            progress(f)
        scorer.add(
            f, truth, out, removed=stream.removed[f], positions=stream.positions[f], dt_ns=dt
        )
    # Body extents are known once the labeler has trained: ask after the run.
    body_extent = np.asarray(labeler.body_extent(), dtype=np.float64)
    return scorer.result(body_extent, recovery=method != "closest-point")


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
    occlude: int = 0,
    occlude_frames: int = 15,
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
        occlude=occlude,
        occlude_frames=occlude_frames,
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
            "occlude": occlude,
            "occlude_frames": occlude_frames,
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
