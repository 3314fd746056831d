"""``BootingLabeler``: the online labeler started from a model with no labeled frame.

``BootingLabeler(model, rate, config, boot=BootConfig())`` follows the
:class:`~labeler_service.labeling.frame.FrameLabeler` protocol. Every frame:

1. the anonymous points are tracked (:class:`~labeler_service.labeling.boot.PointTracker`);
2. the subjects booted so far are labeled by an inner
   :class:`~labeler_service.labeling.labeler.Labeler` built with its public API only
   (``Labeler.from_model`` on a model of the *active* subjects, then the recent frames with
   their labels as its labeled first frames);
3. a subject of the active set with fewer than ``vanish_fraction`` of its markers observed has
   its labels withheld (when a performer leaves, the inner labeler gives its last labels to
   points near where it was); after ``drop_after_s`` it is dropped: the inner labeler is
   rebuilt without it, so none of its labels can go to other points or ghosts while it is
   away; when it comes back it is booted again (re-identification, anywhere);
4. every ``boot_every_s`` (doubling after each fruitless attempt up to ``boot_backoff_s``: a
   model's absent subjects would otherwise cost a boot every 0.05 s), while some model subject
   is not active, the boot
   (:class:`~labeler_service.labeling.boot.Booter`) runs on the window's last frame, restricted
   to the points the inner labeler left unlabeled and to the inactive subjects. Subjects it
   finds become active: their labels are spread along the tracks over the window, and the inner
   labeler is rebuilt with the window (old subjects' labels as it gave them, new subjects' from
   the boot) as its labeled first frames.

While nothing is booted every point is emitted unlabeled. Subjects listed in the model but not
in the volume are never booted, so their labels are never given.

Limits (public ``Labeler`` API): a subject can only be added or removed by rebuilding the inner
labeler from the recent frames; the rebuild re-trains nothing, but the inner labeler's adapted
structure window (Eq. 1-2) and recovery snapshots restart, and the rebuild costs one
``from_model`` (a few ms per subject) in the frame where it happens. A marker hidden during the
whole boot window has no Kalman state in the inner labeler, which today cannot acquire it later.
An ``add_subjects(labels)`` / ``drop_subject(name)`` and a template-seeded acquisition of
never-seen markers in ``Labeler`` would remove both limits; the wrapper keeps both steps in
``_rebuild`` so that a later change is local.

``labels`` passed to :meth:`BootingLabeler.process` are ignored: this labeler never needs them.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from labeler_service.errors import LabelerError
from labeler_service.labeling.boot import (
    BootConfig,
    Booter,
    PointTracker,
    labels_along_tracks,
    track_history,
    warmup_kernels,
)
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import LabeledFrame, MarkerState
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.templates import LabelerModel


@dataclass
class _Frame:
    t: float
    points: np.ndarray  # (N, 3) float32
    ids: np.ndarray  # (N,) track ids
    labels: np.ndarray  # (N,) global marker index or -1


class BootingLabeler:
    """Labels a stream from a subject model alone (see the module docstring)."""

    def __init__(
        self,
        model: LabelerModel,
        rate: float,
        config: LabelerConfig | None = None,
        boot: BootConfig | None = None,
    ) -> None:
        if not (np.isfinite(rate) and rate > 0):
            raise LabelerError(f"invalid frame rate {rate}")
        self.model = model
        self.rate = float(rate)
        self.config = config or LabelerConfig()
        self.boot_config = boot or BootConfig()
        c = self.boot_config
        self._names = model.marker_names
        self._booter = Booter(model, c)
        self._tracker = PointTracker(self.rate, c)
        w = int(np.clip(round(c.window_s * self.rate), c.min_window_frames, c.max_window_frames))
        self._window: deque[_Frame] = deque(maxlen=w)
        sizes = [len(s.markers) for s in model.subjects]
        self._offset = np.cumsum([0] + sizes)
        self._subject_of = np.repeat(np.arange(len(sizes)), sizes)
        self._active: set[int] = set()
        self._gone = np.zeros(len(sizes), dtype=np.int64)
        self._drop_frames = max(1, round(c.drop_after_s * self.rate))
        self._boot_every = max(1, round(c.boot_every_s * self.rate))
        self._boot_every_max = max(self._boot_every, round(c.boot_backoff_s * self.rate))
        self._boot_wait = self._boot_every  # doubles after a fruitless attempt (absent subjects)
        self._since_attempt = self._boot_every
        self._extend_every = max(1, round(c.extend_every_s * self.rate))
        self._since_extend = 0
        self._inner: Labeler | None = None
        self._inner_map = np.zeros(0, dtype=np.int64)
        self.events: list[tuple[float, str, str]] = []  # (t, "boot" | "drop", subject)
        self.boot_ms: list[float] = []  # wall time of every boot attempt

    # ------------------------------------------------------------------ protocol
    @property
    def marker_names(self) -> tuple[str, ...]:
        return self._names

    @property
    def active_subjects(self) -> tuple[str, ...]:
        """Subjects booted and currently labeled (model order)."""
        return tuple(self.model.subjects[i].name for i in sorted(self._active))

    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame:
        """Labels one frame of anonymous points ``(N, 3)`` mm; ``labels`` are ignored."""
        t0 = time.perf_counter_ns()
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise LabelerError(f"points must be (N, 3), got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise LabelerError("points must be finite (drop missing points instead of NaN)")
        pts = np.ascontiguousarray(pts)
        t = float(t)
        m = len(self._names)
        ids = self._tracker.update(pts, t)
        glab = np.full(pts.shape[0], -1, dtype=np.int64)
        pos = np.full((m, 3), np.nan, dtype=np.float32)
        state = np.zeros(m, dtype=np.uint8)
        if self._inner is not None:
            out = self._inner.process(pts, t)
            lab = out.point_labels.astype(np.int64)
            glab = np.where(lab >= 0, self._inner_map[np.maximum(lab, 0)], -1)
            pos[self._inner_map] = out.positions
            state[self._inner_map] = out.state
            self._drop_vanished(glab, state, pos, t)
        self._window.append(_Frame(t, pts, ids, glab))
        self._since_attempt += 1
        self._since_extend += 1
        if (
            self._active
            and len(self._window) == self._window.maxlen
            and self._since_extend >= self._extend_every
            and np.any(glab < 0)
        ):
            self._since_extend = 0
            if self._extend():
                glab = self._window[-1].labels
                obs = glab >= 0
                pos[glab[obs]] = pts[obs]
                state[glab[obs]] = MarkerState.OBSERVED
        if (
            len(self._window) == self._window.maxlen
            and len(self._active) < len(self.model.subjects)
            and self._since_attempt >= self._boot_wait
        ):
            self._since_attempt = 0
            booted = self._attempt(t)
            self._boot_wait = (
                self._boot_every if booted.size else min(2 * self._boot_wait, self._boot_every_max)
            )
            if booted.size:
                glab = self._window[-1].labels
                obs = glab >= 0
                pos[glab[obs]] = pts[obs]
                state[glab[obs]] = MarkerState.OBSERVED
        return LabeledFrame(
            t=t,
            point_labels=glab.astype(np.int32),
            positions=pos,
            state=state,
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    # ------------------------------------------------------------------ steps
    def _drop_vanished(
        self, glab: np.ndarray, state: np.ndarray, pos: np.ndarray, t: float
    ) -> None:
        """Withholds the labels of subjects with fewer than ``vanish_fraction`` of their markers
        observed (a performer leaving: the inner labeler would give its last labels to points
        near where it was) and drops those gone for ``drop_after_s``."""
        dropped = []
        c = self.boot_config
        for s in sorted(self._active):
            sl = slice(self._offset[s], self._offset[s + 1])
            n_obs = int(np.count_nonzero(state[sl] == MarkerState.OBSERVED))
            if n_obs >= max(1, c.vanish_fraction * (sl.stop - sl.start)):
                self._gone[s] = 0
                continue
            self._gone[s] += 1
            mine = (glab >= sl.start) & (glab < sl.stop)
            glab[mine] = -1
            pos[sl] = np.nan
            state[sl] = MarkerState.MISSING
            if self._gone[s] >= self._drop_frames:
                dropped.append(s)
        if not dropped:
            return
        for s in dropped:
            self._active.discard(s)
            self._gone[s] = 0
            self.events.append((t, "drop", self.model.subjects[s].name))
        # the window's labels of dropped subjects are forgotten (a rebuild must not see them)
        gone = np.isin(self._subject_of, dropped)
        for fr in self._window:
            bad = fr.labels >= 0
            bad[bad] = gone[fr.labels[bad]]
            fr.labels[bad] = -1
        self._rebuild()

    def _extend(self) -> bool:
        """Free points joined to active subjects (markers hidden at boot that appear)."""
        last = self._window[-1]
        frames = [(f.points, f.ids) for f in self._window]
        hist = track_history(frames, last.ids)
        new = self._booter.extend(last.points, hist, last.labels, sorted(self._active))
        added = (last.labels < 0) & (new >= 0)
        if not added.any():
            return False
        extra = np.where(added, new, -1)
        self._spread(frames, last.ids, extra)
        self._rebuild()
        return True

    def _spread(self, frames: list, ids: np.ndarray, labels: np.ndarray) -> None:
        """Gives the labels of the last frame's tracks to the window's free points."""
        spread = labels_along_tracks(frames, ids, labels)
        for fr, lab in zip(self._window, spread, strict=True):
            new = (fr.labels < 0) & (lab >= 0)
            # a label can be given only once per frame (a track split may repeat it)
            taken = set(fr.labels[fr.labels >= 0].tolist())
            for j in np.flatnonzero(new):
                if int(lab[j]) not in taken:
                    fr.labels[j] = lab[j]
                    taken.add(int(lab[j]))

    def _attempt(self, t: float) -> np.ndarray:
        """One boot on the window; returns the model indices of the subjects booted."""
        tb = time.perf_counter()
        last = self._window[-1]
        frames = [(f.points, f.ids) for f in self._window]
        hist = track_history(frames, last.ids)
        inactive = [s for s in range(len(self.model.subjects)) if s not in self._active]
        res = self._booter.run(last.points, hist, free=last.labels < 0, subjects=inactive)
        self.boot_ms.append((time.perf_counter() - tb) * 1e3)
        if not res.subjects:
            return np.zeros(0, dtype=np.int64)
        self._spread(frames, last.ids, res.labels)
        names = {s.name: i for i, s in enumerate(self.model.subjects)}
        booted = np.array([names[n] for n in res.subjects], dtype=np.int64)
        self._active.update(int(s) for s in booted)
        for n in res.subjects:
            self.events.append((t, "boot", n))
        self._rebuild()
        return booted

    def _rebuild(self) -> None:
        """A new inner labeler for the active subjects, started from the window's labels (its
        labeled first frames, the last one being this frame); the next frame is its first
        unlabeled one."""
        if not self._active:
            self._inner = None
            self._inner_map = np.zeros(0, dtype=np.int64)
            return
        order = sorted(self._active)
        sub = LabelerModel(
            rate=self.model.rate,
            subjects=[self.model.subjects[s] for s in order],
            source=self.model.source,
        )
        inner = Labeler.from_model(sub, self.rate, self.config)
        gmap = np.concatenate([np.arange(self._offset[s], self._offset[s + 1]) for s in order])
        g2i = np.full(len(self._names), -1, dtype=np.int64)
        g2i[gmap] = np.arange(gmap.size)
        for fr in self._window:
            lab = np.where(fr.labels >= 0, g2i[np.maximum(fr.labels, 0)], -1)
            inner.process(fr.points, fr.t, lab)
        self._inner = inner
        self._inner_map = gmap

    # ------------------------------------------------------------------ warm-up
    def warmup(self) -> None:
        """Compiles the boot's and the inner labeler's kernels (see :meth:`Labeler.warmup`)
        without touching this labeler's state."""
        warmup_kernels()
        Labeler(["w:a", "w:b", "w:c"], self.rate, self.config).warmup()
