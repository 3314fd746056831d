"""``BootingLabeler``: the online labeler started from a model with no labeled frame.

``BootingLabeler(model, rate, config, boot=BootConfig())`` follows the
:class:`~labeler_service.labeling.frame.FrameLabeler` protocol. Every frame:

1. the anonymous points are tracked (:class:`~labeler_service.labeling.boot.PointTracker`);
2. the subjects booted so far are labeled by an inner
   :class:`~labeler_service.labeling.labeler.Labeler` built once with every model subject
   inactive (``Labeler.from_model(model, ..., subjects=())``): a booted subject is added to it
   (``Labeler.add_subjects`` from the recent frames with its labels), a dropped one removed
   (``Labeler.drop_subject``); the other subjects' state is never touched;
3. a subject of the active set with fewer than ``vanish_fraction`` of its markers observed, or
   fewer than ``vanish_relative`` of its recent count (moving average over
   ``vanish_memory_s``), has its labels withheld (when a performer leaves, the inner labeler
   gives its last labels to points near where it was); after ``drop_after_s`` it is dropped:
   the inner labeler stops labeling it (``Labeler.drop_subject``), so none of its labels can go
   to other points or ghosts while it is away; when it comes back it is booted again
   (re-identification, anywhere);
   a subject whose anonymous point tracks a jump of the whole scene ended (a take that
   loops, frames lost with ``t`` continuous: :func:`jumped_subjects`) is dropped at once and
   booted again;
   a booted subject is also re-verified over time (:mod:`~labeler_service.labeling.boot_verify`,
   ``BootConfig.verify``): labels whose template pairs stop holding are withdrawn (from the
   frame, the window and the inner labeler: ``Labeler.withdraw_markers``) and their tracks
   kept from that subject for ``verify_block_s``; a subject that mostly fails is dropped and
   booted again;
4. every ``boot_every_s`` (doubling after each fruitless attempt up to ``boot_backoff_s``: a
   model's absent subjects would otherwise cost a boot every 0.05 s), while some model subject
   is not active, the boot
   (:class:`~labeler_service.labeling.boot.Booter`) runs on the window's last frame, restricted
   to the points the inner labeler left unlabeled and to the inactive subjects. Subjects it
   finds become active: their labels are spread along the tracks over the window, and the inner
   labeler adds them from the window (their Kalman states, structure windows and recovery
   snapshots start from it; ~1 ms for one of 10 performers at 360 Hz, where the former rebuild
   of the whole inner labeler cost ~14 ms and restarted every tracked subject).

While nothing is booted every point is emitted unlabeled. Subjects listed in the model but not
in the volume are never booted, so their labels are never given.

A marker hidden during the whole boot window has no Kalman state in the inner labeler; once an
extension or acquisition labels it, the inner labeler starts its track from the window
(``Labeler.seed_markers``; only the markers it lacks). The inner labeler is rebuilt only
after labeled frames, from them (below).

This labeler never needs labels; a frame that carries them (``process(points, t, labels)``)
is taken as labeled: its subjects become active without a boot and the inner labeler starts
from those labels (as ``Labeler.from_model`` with labeled first frames), so a stream configured
with a model can use this one labeler whether its client sends labels or not.

**Boot off the frame path.** Step 4 is the only heavy one (0.1-0.3 s per attempt for 3-5
performers, up to ~1 s for 10 on a busy machine). ``BootingLabeler(..., inline_boot=False)``
never runs it inside :meth:`~BootingLabeler.process`; its owner runs it instead, in three calls:

1. after a frame, in the frame thread: ``if lab.needs_boot(): snap = lab.boot_snapshot()``
   (copies the window's last frame and track history; restarts the wait to the next attempt);
2. anywhere, e.g. a worker thread with a time budget: ``res = lab.boot_step(snap)`` (reads only
   the snapshot and the immutable templates);
3. back in the frame thread, between two frames: ``lab.install_boot(snap, res)`` (labels follow
   the snapshot's tracks to the current frame; the inner labeler adds the booted subjects).

Frames keep flowing unlabeled for the booting subjects meanwhile. Only one attempt should be in
flight: skip step 1 while one runs. An attempt abandoned over its budget is reported with
``lab.install_boot(snap, None)`` (the wait to the next attempt doubles, as after a fruitless
one). The service's background mechanism for heavy work (the
same one that trains in-stream) is meant to drive exactly these calls; with ``inline_boot=True``
(the default) :meth:`~BootingLabeler.process` does all three in the frame that is due.

Step 3's extension (free points joined to active subjects, every ``extend_every_s``; ~20 ms
for 3 performers, more for 10, even when it finds nothing, e.g. with ghosts present) is the
other heavy step on the frame path. With ``inline_extend=False`` it moves into the same three
calls: :meth:`~BootingLabeler.needs_boot` is also true when an extension is due, the snapshot
then carries the active subjects' labels, :meth:`~BootingLabeler.boot_step` runs the extension
(its result stored in the snapshot's ``extended``) besides or instead of the boot, and
:meth:`~BootingLabeler.install_boot` installs both. The service uses both flags off.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from labeler_service.errors import LabelerError
from labeler_service.labeling.boot import (
    BootConfig,
    Booter,
    BootResult,
    HypothesesShare,
    PointTracker,
    track_history,
    warmup_kernels,
)
from labeler_service.labeling.boot_tracks import track_gates
from labeler_service.labeling.boot_verify import BootVerifier, extend_blocked
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import LabeledFrame, MarkerState, frame_labels, frame_points
from labeler_service.labeling.kernels.stacked import _spread_labels
from labeler_service.labeling.kernels.track import _no_point_within
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.templates import LabelerModel

log = logging.getLogger(__name__)

#: Models whose boot preparation (:class:`Booter`, the :class:`BootVerifier`'s structures) is
#: kept for the next labeler of the same model: a stream's recovery builds a
#: :class:`BootingLabeler` of its model on the frame path, and preparing a 1,000-marker model
#: took 2.8 s there (every stream of the service waited); the training job prepares it first,
#: off the loop (:func:`prepare_boot`).
PREPARED_KEPT = 8
_prepared: dict[tuple[int, str], tuple[LabelerModel, Booter, dict[float, BootVerifier]]] = {}
_prepared_lock = threading.Lock()


def prepare_boot(
    model: LabelerModel, config: BootConfig, rate: float, keep: bool = True
) -> tuple[Booter, BootVerifier | None]:
    """The :class:`Booter` of ``model`` and a fresh :class:`BootVerifier` (None when
    ``config.verify`` is off), from the preparation of an earlier call with the same model object
    and settings when one is kept (the booter is read-only once built, so labelers share it; the
    verifier, which keeps evidence over time, is a copy of a prepared one). ``keep=False``: a
    model used once (a relearn's), neither looked up nor kept (it would push out the models
    that recoveries come back to)."""
    key = (id(model), config.model_dump_json())
    hit = None
    if keep:
        with _prepared_lock:
            hit = _prepared.get(key)
            if hit is not None and hit[0] is model:
                _prepared[key] = _prepared.pop(key)  # most recently used last
    if hit is None or hit[0] is not model:
        hit = (model, Booter(model, config), {})
        if keep:
            with _prepared_lock:
                _prepared[key] = hit
                while len(_prepared) > PREPARED_KEPT:
                    del _prepared[next(iter(_prepared))]
    booter, verifiers = hit[1], hit[2]
    if not config.verify:
        return booter, None
    proto = verifiers.get(rate)
    if proto is None:
        proto = BootVerifier(booter, rate, config)
        with _prepared_lock:
            verifiers.setdefault(rate, proto)
    return booter, copy.deepcopy(proto)


#: Seconds of the stream's own frames a relearn reads (``BootConfig.relearn_every_s``).
RELEARN_HISTORY_S = 10.0
#: Frames on either side of a frame with an unlabeled point that a relearn leaves out too.
RELEARN_MARGIN = 5
#: Most frames a relearn trains on, evenly spread over its clean frames (the training's cost
#: grows with them: 0.67 s on 987 frames of three performers, in the service's process).
RELEARN_MAX_FRAMES = 250
#: Off the frame path (the service) a relearn's Python shares the process with the frame path:
#: the next one waits at least this many times the last one's duration (at most a tenth of
#: the stream's time spent relearning: three performers at 120 Hz took 0.3 s a relearn).
RELEARN_LOAD = 10.0


#: Longest wait between fruitless extensions off the frame path, in ``extend_every_s`` periods.
EXTEND_BACKOFF = 4
#: A free track is offered to :meth:`Booter.acquire` in this many frames after it appears.
ACQUIRE_TRIES = 3
#: The rebuild after labeled frames starts the inner labeler from at most this many seconds
#: of them (the last ones): the window alone (0.1 s, 5 frames at 50 Hz) gave its Kalman states
#: too short a start, and a fast forearm was read exchanged for seconds. The rebuild runs in
#: the frame that ends the labeled run: 10 performers at 360 Hz, 12 ms from the window alone,
#: 22-23 ms from these 0.5 s (``benchmarks/boot_frame_cost.py --labeled-s 1.0``).
LABELED_KEPT_S = 0.5
#: Frames kept for the catch-up of one attempt (:meth:`BootingLabeler.catch_up`), in seconds of
#: stream: an attempt slower than this is installed along the tracks instead (a bound on memory:
#: 10 performers at 360 Hz keep ~14 kB a frame).
CATCH_UP_MAX_S = 12.0
#: The catch-up labels at least this rate while far behind (every ``rate // CATCH_UP_HZ``-th
#: frame): 10 performers cost ~1-2 ms a frame, near a 360 Hz period, so at the full rate
#: a 1.7 s attempt would take seconds more to catch up.
CATCH_UP_HZ = 60.0
#: A result fewer seconds of stream late than this is installed along the tracks (they hold
#: that long: 4 walkers, 0.5 s late, 0.945 correct after boot along them, 0.954 caught up; 2.5
#: s late 0.79 against 0.955), which saves the catch-up's fixed cost (two labeler starts, two
#: extensions, the round trips: 0.2-1 s, which delayed the demo's boot from 0.2 to 0.6 s).
CATCH_UP_AFTER_S = 0.5
#: Catch-up rounds that end with a full-rate window before it strides to the newest frame
#: (see ``_catch_up_plan``).
CATCH_UP_TAIL_ROUNDS = 4
#: Newest frames the catch-up's last part, in the service's own process, labels at the full
#: rate; older ones every ``rate // CATCH_UP_HZ``-th (:meth:`BootingLabeler._catch_last`).
CATCH_LAST_FULL = 2


#: Entries :attr:`BootingLabeler.events` and :attr:`BootingLabeler.boot_ms` keep (a stream
#: runs for days: a model's absent subjects cost an attempt every 0.2 s, a crowd a withdrawal
#: or two a second).
HISTORY_KEPT = 10_000


class History(list):
    """A list that keeps only its last ``keep`` entries (trimmed once it holds twice as many)
    and counts every entry ever added in :attr:`total`: a reader that remembers ``total``
    finds what came since in the last ``total - remembered`` entries."""

    def __init__(self, keep: int = HISTORY_KEPT) -> None:
        super().__init__()
        self.keep = int(keep)
        self.total = 0

    def append(self, item) -> None:  # type: ignore[override]
        super().append(item)
        self.total += 1
        self._trim()

    def extend(self, items) -> None:  # type: ignore[override]
        items = list(items)
        super().extend(items)
        self.total += len(items)
        self._trim()

    def __iadd__(self, items):  # type: ignore[override, misc]
        self.extend(items)
        return self

    def _trim(self) -> None:
        if len(self) > 2 * self.keep:
            del self[: len(self) - self.keep]

    def __reduce__(self):
        # (a boot worker process gets a copy: pickle's default would append the items before
        # it sets ``total``)
        return (_history, (self.keep, self.total, list(self)))


def _history(keep: int, total: int, items: list) -> History:
    h = History(keep)
    list.extend(h, items)
    h.total = total
    return h


@dataclass
class _Frame:
    t: float
    points: np.ndarray  # (N, 3) float32
    ids: np.ndarray  # (N,) track ids
    labels: np.ndarray  # (N,) global marker index or -1


@dataclass
class BootSnapshot:
    """The input of one boot attempt (:meth:`BootingLabeler.boot_snapshot`): the window's last
    frame, its tracks over the window, which of its points are free, the subjects looked for."""

    t: float
    points: np.ndarray  # (N, 3)
    ids: np.ndarray  # (N,) track ids
    history: np.ndarray  # (N, W, 3) NaN where untracked
    free: np.ndarray  # (N,) bool
    subjects: list[int]
    #: ``inline_extend=False``: the active subjects' labels of the last frame (global marker
    #: index or -1) when an extension is due, else None; :meth:`BootingLabeler.boot_step` puts
    #: the extended labels in ``extended``
    labels: np.ndarray | None = None
    active: list[int] = field(default_factory=list)
    extended: np.ndarray | None = None
    #: the frames labeled since the snapshot, appended by :meth:`BootingLabeler.process`
    #: while the attempt is in flight (None: not recorded)
    since: list[_Frame] | None = None
    #: a copy of the labeler at the snapshot (:meth:`BootingLabeler.catch_up` runs it)
    shadow: BootingLabeler | None = None
    #: :meth:`BootingLabeler.catch_up`'s result, installed by :meth:`BootingLabeler.install_boot`
    caught: _CatchUp | None = None
    #: per active subject the points (bool over ``points``) its extension may not take: tracks
    #: of labels the re-verification withdrew from it (``boot_verify.py``)
    blocked: dict[int, np.ndarray] | None = None
    #: (N,) seconds each point's track has lived (the extension's joint fill reads it)
    age: np.ndarray | None = None
    #: the active subjects whose readings the extension re-checks (:meth:`Booter.extend`)
    checked: list[int] = field(default_factory=list)
    #: a relearn due off the frame path (``inline_extend=False``): its clean frames
    #: ``(t, points, labels)``; :meth:`BootingLabeler.boot_step` trains on them and puts the
    #: model, booter and verifier in ``relearned``, which :meth:`~BootingLabeler.install_boot`
    #: installs
    relearn: list | None = None
    relearned: tuple | None = None

    def remote(self) -> BootSnapshot:
        """The part a boot step reads (no frames, no catch-up): what goes to a worker process."""
        return dataclasses.replace(
            self, since=None, shadow=None, caught=None, relearn=None, relearned=None
        )


@dataclass
class _CatchUp:
    """What :meth:`BootingLabeler.catch_up` did: the subjects its shadow booted and how many
    recorded frames it has labeled since."""

    booted: list[int]
    done: int


class BootingLabeler:
    """Labels a stream from a subject model alone (see the module docstring)."""

    def __init__(
        self,
        model: LabelerModel,
        rate: float,
        config: LabelerConfig | None = None,
        boot: BootConfig | None = None,
        inline_boot: bool = True,
        inline_extend: bool = True,
        labeled_kept_s: float = LABELED_KEPT_S,
        window_frames: int | None = None,
    ) -> None:
        if not (np.isfinite(rate) and rate > 0):
            raise LabelerError(f"invalid frame rate {rate}")
        if not (np.isfinite(labeled_kept_s) and labeled_kept_s > 0):
            raise LabelerError(f"labeled_kept_s must be > 0 seconds, got {labeled_kept_s}")
        self.model = model
        self.rate = float(rate)
        # (the inner labeler's markers never observed are this wrapper's to place: its
        # acquisition and extension label them and seed their tracks)
        self.config = (config or LabelerConfig()).model_copy(update={"acquire_unseen": False})
        self.boot_config = boot or BootConfig()
        #: False: :meth:`process` never boots; the owner runs the attempts (see the module doc)
        self.inline_boot = bool(inline_boot)
        #: False: :meth:`process` never extends; the extension rides on the boot calls
        self.inline_extend = bool(inline_extend)
        #: the labeled start through a window model (``registry.make_window_labeler``): the
        #: labeled frames its model was trained on; None for a boot from a model file
        self.window_frames = window_frames
        #: the booter's templates learned again from the stream (:meth:`_relearn`): its frames
        #: ``(t, points, labels)``, whether each was clean, and the relearns done
        every = self.boot_config.relearn_every_s
        self._relearn_every = max(1, round(every * self.rate)) if every > 0 else 0
        hist = max(window_frames or 0, round(RELEARN_HISTORY_S * self.rate))
        self._relearn_frames: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=hist)
        self._relearn_clean: deque[bool] = deque(maxlen=hist)
        self._since_relearn = 0
        self._relearn_pending = False  # due, for the next boot job (off the frame path)
        self._relearn_cost_s = 0.0  # the last relearn's wall time (off the frame path)
        self.relearned = 0
        #: the model of the booter's templates: ``model``, or the last relearn's
        self.boot_model = model
        c = self.boot_config
        self._names = model.marker_names
        self._booter, verifier = prepare_boot(model, c, self.rate)
        #: names this labeler's model and boot settings in a worker process's booter cache
        self.key = uuid.uuid4().hex
        self._tracker = PointTracker(self.rate, c)
        w = int(np.clip(round(c.window_s * self.rate), c.min_window_frames, c.max_window_frames))
        self._window: deque[_Frame] = deque(maxlen=w)
        sizes = [len(s.markers) for s in model.subjects]
        self._offset = np.cumsum([0] + sizes)
        self._subject_of = np.repeat(np.arange(len(sizes)), sizes)
        self._active: set[int] = set()
        self._gone = np.zeros(len(sizes), dtype=np.int64)
        self._dropout = DropoutHold()
        self._t_points: float | None = None  # the last frame with a point (blackout_reboot_s)
        self._recent = np.zeros(len(sizes))  # moving average of observed markers (0: unset)
        self._recent_alpha = min(1.0, 1.0 / max(1.0, c.vanish_memory_s * self.rate))
        self._drop_frames = max(1, round(c.drop_after_s * self.rate))
        self._boot_every = max(1, round(c.boot_every_s * self.rate))
        self._boot_every_max = max(self._boot_every, round(c.boot_backoff_s * self.rate))
        self._boot_wait = self._boot_every  # doubles after a fruitless attempt (absent subjects)
        self._since_attempt = self._boot_every
        self._extend_every = max(1, round(c.extend_every_s * self.rate))
        self._since_extend = 0
        #: off the frame path (``inline_extend=False``): the wait to the next extension doubles
        #: after one that found nothing, up to ``EXTEND_BACKOFF`` periods (a background job
        #: every ``extend_every_s`` costs the live stream GIL time even when it finds nothing)
        self._extend_wait = self._extend_every
        #: the inner labeler holds every model subject, inactive until booted: a boot adds its
        #: subjects (:meth:`Labeler.add_subjects`), a drop removes one, the others keep their state
        self._inner = Labeler.from_model(model, self.rate, self.config, subjects=())
        self._inner_state = np.zeros(len(self._names), dtype=np.uint8)  # its last frame's
        #: markers the inner labeler was started with (labeled in its window at the rebuild)
        self._inner_known = np.zeros(len(self._names), dtype=bool)
        #: markers labeled from the template (:meth:`Booter.acquire`) the inner labeler lacks
        self._acquired_new = False
        self._since_acquire = 0
        self.acquired = 0  # points labeled by acquisition (diagnostics)
        self._acq_ids = np.zeros(0, dtype=np.int64)  # free tracks looked at (sorted)
        self._acq_tries = np.zeros(0, dtype=np.int64)  # and how often
        self._labeled_run = False  # labeled frames seen since the last rebuild
        #: subjects the stream's labels placed (until dropped): never verified, re-checked by
        #: the extension once the labels stop (:meth:`_checked`)
        self._from_labels: frozenset[int] = frozenset()
        #: the labeled frames of the current labeled run (the last ``labeled_kept_s``,
        #: default ``LABELED_KEPT_S``): the rebuild starts the inner labeler from all of them,
        #: not only from the window
        self._labeled_frames: deque[_Frame] = deque(
            maxlen=max(w, int(round(labeled_kept_s * self.rate)))
        )
        self._extent: np.ndarray | None = None
        #: (t, "boot"|"labeled"|"drop"|"withdraw"|"reject"|"jump"|"blackout", subject), the last
        #: HISTORY_KEPT
        self.events: History = History()
        #: frames labeled since the snapshot of the boot attempt in flight (its catch-up reads
        #: them; None while no attempt records)
        self._since: list[_Frame] | None = None
        self._since_max = max(1, int(CATCH_UP_MAX_S * self.rate))
        self.boot_ms: History = History()  # wall time of every boot attempt (the last ones)
        #: re-verification of booted subjects over time (boot_verify.py); None when off
        self._verifier = verifier
        #: per subject the tracks of its withdrawn labels and until when it may not take them
        self._blocked: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    # ------------------------------------------------------------------ protocol
    @property
    def boot_spec(self) -> tuple[LabelerModel, BootConfig]:
        """What a worker process builds this labeler's booter from (its cache key: :attr:`key`)."""
        return self.boot_model, self.boot_config

    @property
    def marker_names(self) -> tuple[str, ...]:
        return self._names

    def body_extent(self) -> np.ndarray:
        """``(M,)`` mm: per model marker the longest pair distance ``D`` of the smallest rigid
        body of its template containing it (as :meth:`Labeler.body_extent`); NaN without one."""
        if self._extent is None:
            out = np.full(len(self._names), np.nan)
            for s, tpl in enumerate(self.model.subjects):
                d = np.array(tpl.D, dtype=np.float64)  # None -> nan
                for body in tpl.bodies:
                    b = np.asarray(body, dtype=np.int64)
                    if b.size < 2:
                        continue
                    ext = float(np.nanmax(d[np.ix_(b, b)]))
                    g = self._offset[s] + b
                    out[g] = np.where(np.isfinite(out[g]), np.fmin(out[g], ext), ext)
            self._extent = out
        return self._extent

    @property
    def active_subjects(self) -> tuple[str, ...]:
        """Subjects booted and currently labeled (model order)."""
        return tuple(self.model.subjects[i].name for i in sorted(self._active))

    @property
    def n_active(self) -> int:
        """How many subjects are booted and labeled now (no tuple built: per-frame gauges)."""
        return len(self._active)

    @property
    def n_active_markers(self) -> int:
        """The markers of the subjects booted and labeled now (a stream's health counts these:
        a model may list performers who are not in the volume)."""
        return sum(len(self.model.subjects[i].markers) for i in self._active)

    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame:
        """Labels one frame of anonymous points ``(N, 3)`` mm. ``labels`` (optional, model marker
        index per point, -1 = unknown) are taken as that frame's answer: a subject with three
        or more labeled points becomes active without a boot, and the first unlabeled frame
        after labeled ones rebuilds the inner labeler from those frames (the last
        ``LABELED_KEPT_S`` of them: the labeled start of ``Labeler.from_model``, so one labeler
        serves both starts)."""
        t0 = time.perf_counter_ns()
        pts = frame_points(points)
        t = float(t)
        m = len(self._names)
        ids = self._tracker.update(pts, t)
        if labels is not None:
            return self._labeled(pts, t, ids, labels, t0)
        if self._labeled_run:
            self._labeled_run = False
            self._rebuild()
        glab = np.full(pts.shape[0], -1, dtype=np.int64)
        pos = np.full((m, 3), np.nan, dtype=np.float32)
        state = np.zeros(m, dtype=np.uint8)
        if pts.shape[0]:
            self._after_blackout(t)
        if self._active:  # (the inner labeler costs nothing while no subject is booted)
            out = self._inner.process(pts, t)
            self._inner_state = out.state
            glab = out.point_labels.astype(np.int64)  # the inner labeler has the model's markers
            pos[:] = out.positions
            state[:] = out.state
            if not self._blackout(pts, t):
                self._drop_vanished(glab, state, pos, t)
            if self.boot_config.jump_fraction > 0 and self._window:
                self._drop_jumped(pts, ids, glab, pos, state, t)
            if self._verifier is not None:
                self._verify(ids, glab, pos, state, t)
            self._acquire(pts, ids, glab, pos, state, t)
        frame = _Frame(t, pts, ids, glab)
        self._window.append(frame)
        if self._since is not None:
            if len(self._since) < self._since_max:
                self._since.append(frame)
            else:  # too slow an attempt to catch up with: installed along the tracks
                self._since = None
        self._since_attempt += 1
        self._since_extend += 1
        self._since_acquire += 1
        if (
            self.inline_extend
            and self._acquired_new
            and self._since_acquire >= self._extend_every
            and len(self._window) == self._window.maxlen
        ):
            # markers the inner labeler never had, labeled from the template: it takes them
            # over from the window (at most every extend_every_s)
            self._install([])
        if (
            self.inline_extend
            and self._active
            and len(self._window) == self._window.maxlen
            and self._since_extend >= self._extend_every
            and (
                np.any(glab < 0)
                # (with every point labeled, the re-check of the booted readings only, at the
                # cadence the service's backed-off jobs keep: EXTEND_BACKOFF periods)
                or (
                    self._since_extend >= EXTEND_BACKOFF * self._extend_every
                    and bool(self._checked())
                )
            )
        ):
            self._since_extend = 0
            if self._extend():
                glab = self._window[-1].labels
                _mark_observed(glab, pts, pos, state)
        if self.inline_boot and self.needs_boot():
            booted = self._attempt(t)
            if booted.size:
                glab = self._window[-1].labels
                _mark_observed(glab, pts, pos, state)
        if self._relearn_record(t, pts, glab, clean=self._clean(glab)):
            if self.inline_extend:
                self._relearn()
            else:  # (the next boot job trains it: boot_snapshot, boot_step, install_boot)
                self._relearn_pending = True
        return LabeledFrame(
            t=t,
            point_labels=glab.astype(np.int32),
            positions=pos,
            state=state,
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    def _labeled(
        self, pts: np.ndarray, t: float, ids: np.ndarray, labels: np.ndarray, t0: int
    ) -> LabeledFrame:
        """A frame that carries its labels (see :meth:`process`)."""
        m = len(self._names)
        if pts.shape[0]:
            self._t_points = t
        lab = frame_labels(labels, pts.shape[0], m)
        self._window.append(_Frame(t, pts, ids, lab.copy()))
        if not self._labeled_run:
            self._labeled_frames.clear()  # a new labeled run
        self._labeled_frames.append(self._window[-1])
        self._since = None  # labeled frames: a result in flight is installed along the tracks
        self._since_attempt += 1
        self._since_extend += 1
        counts = np.bincount(self._subject_of[lab[lab >= 0]], minlength=len(self.model.subjects))
        for s in np.flatnonzero(counts >= 3).tolist():
            # (labels from the stream are not re-verified; the verifier and the set change only
            # when a subject's labels start: this runs on every labeled frame)
            if self._verifier is not None and self._verifier.verifies(s):
                self._verifier.stop(s)
            if s not in self._from_labels:
                self._from_labels = self._from_labels | {s}
            if s not in self._active:
                self._active.add(s)
                self._recent[s] = 0.0
                self._gone[s] = 0
                self.events.append((t, "labeled", self.model.subjects[s].name))
        self._labeled_run = True
        pos = np.full((m, 3), np.nan, dtype=np.float32)
        state = np.zeros(m, dtype=np.uint8)
        _mark_observed(lab, pts, pos, state)
        self._relearn_record(t, pts, lab, clean=True)
        return LabeledFrame(
            t=t,
            point_labels=lab.astype(np.int32),
            positions=pos,
            state=state,
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    # ------------------------------------------------------------------ relearn
    def _relearn_record(self, t: float, pts: np.ndarray, labels: np.ndarray, clean: bool) -> bool:
        """Keeps a frame and its labels for :meth:`_relearn` (only when relearning is on); True
        when a relearn is due: ``relearn_every_s`` of unlabeled frames since the last one, the
        last ``window_frames`` frames clean."""
        if not self._relearn_every:
            return False
        self._relearn_frames.append((t, pts, np.asarray(labels, dtype=np.int64).copy()))
        self._relearn_clean.append(bool(clean))
        if self._labeled_run:
            return False
        self._since_relearn += 1
        feed = self.window_frames or 1
        every = self._relearn_every
        if not self.inline_extend:
            every = max(every, round(RELEARN_LOAD * self._relearn_cost_s * self.rate))
        if self._since_relearn < every:
            return False
        clean_tail = list(self._relearn_clean)[-feed:]
        if not all(clean_tail):
            return False
        self._since_relearn = 0
        return True

    def _clean(self, glab: np.ndarray) -> bool:
        """Is this frame's reading clean enough to learn from (:meth:`_relearn`)? Every point
        labeled, or every marker of the active subjects labeled (some subject active): then a
        free point is none of their markers (a ghost, a point no template has) and the
        training, which reads only labeled points, gets no sample from it. Counting every free
        point, a stream with ghosts had almost no clean frame and never relearned (t24
        ``--ghosts 3``: 1 % of its frames clean, 0 relearns against 2 without ghosts; the
        window's template then refused the toe's point for 1 s, its pair to the other foot
        beyond the quiet window's reach). A free point while a marker is unlabeled still makes
        the frame unclean, however young (a marker back from a gap, where swaps start): so a
        marker hidden, or in no trained body and never labeled, beside a ghost still keeps a
        frame out; the rule is narrower than "no ghost"."""
        free = glab < 0
        if not free.any():
            return True
        if not self._active:
            return False
        known = np.zeros(len(self._names), dtype=bool)
        known[glab[~free]] = True
        return bool(np.all(known[self._subjects_in(self._active)[self._subject_of]]))

    def _relearn(self) -> bool:
        """The booter's templates - the model the boot and the extension place markers with -
        trained again (:func:`~labeler_service.labeling.structure.window_model`) on the
        stream's own clean frames of the last :data:`RELEARN_HISTORY_S` seconds (:meth:`_clean`),
        and no frame within :data:`RELEARN_MARGIN` of one that was not. The labeler
        (its tracks, bodies, windows) is kept. Why: a labeled start knows the 0.4 s of its
        window; the tennis take's arm, still there, was lost for 4.6 s at the third serve
        (docs/algorithm.md). False when too few clean frames (``relearn_min_frames``) or the
        training refuses them."""
        frames = self._relearn_take()
        built = None if frames is None else self._relearn_build(frames)
        if built is None:
            return False
        self._relearn_use(built)
        return True

    def _relearn_take(self) -> list | None:
        """The clean frames a relearn trains on (frame thread), None when too few."""
        self._relearn_pending = False
        ok = np.array(self._relearn_clean, dtype=bool)
        good = ok.copy()
        for k in range(1, RELEARN_MARGIN + 1):
            good[k:] &= ok[:-k]
            good[:-k] &= ok[k:]
        frames = [f for f, g in zip(self._relearn_frames, good, strict=True) if g]
        if len(frames) < max(self.window_frames or 1, self.boot_config.relearn_min_frames):
            return None
        if len(frames) > RELEARN_MAX_FRAMES:  # evenly spread: the training's cost is per frame
            pick = np.linspace(0, len(frames) - 1, RELEARN_MAX_FRAMES).round().astype(int)
            frames = [frames[i] for i in pick]
        return frames

    def _relearn_build(self, frames: list) -> tuple | None:
        """The relearned ``(model, booter, verifier)`` of ``frames`` (reads nothing else of this
        labeler but its names, rate and settings: a boot job's thread may run it), None when
        the training refuses them."""
        from labeler_service.capture import Capture
        from labeler_service.errors import MocapError
        from labeler_service.labeling.frame import window_observations
        from labeler_service.labeling.structure import window_model

        t0 = time.perf_counter()
        pos = window_observations(frames, np.ones(len(self._names), dtype=bool))
        try:
            model = window_model(Capture(pos.astype(np.float32), self._names, self.rate))
        except MocapError:
            return None
        if model.marker_names != self._names:
            return None  # (cannot happen: the window model keeps the stream's names)
        built = (model, *prepare_boot(model, self.boot_config, self.rate, False))
        self._relearn_cost_s = time.perf_counter() - t0
        return built

    def _relearn_use(self, built: tuple) -> None:
        """Installs a relearned booter (frame thread); a worker process's booter cache knows
        it by a new :attr:`key`."""
        self.boot_model, self._booter, self._verifier = built
        self.key = uuid.uuid4().hex
        self.relearned += 1

    # ------------------------------------------------------------------ steps
    def _blackout(self, pts: np.ndarray, t: float) -> bool:
        """This frame has no point at all, within ``blackout_hold_s`` of the run's first
        (:class:`DropoutHold`): no subject counts as vanished in it. After a 0.1 s dropout the
        tennis serve's performer was dropped and booted again 0.52 s after it began, with
        nothing labeled in between; held, his markers are taken up where they return. A
        performer who did leave meanwhile is dropped from the first frame with points."""
        return self._dropout.held(pts.shape[0], t, self.boot_config.blackout_hold_s)

    def _after_blackout(self, t: float) -> None:
        """A frame with points at ``t``: when the last one was more than
        ``blackout_reboot_s`` earlier (every frame between empty, or none sent), every active
        subject is dropped ("blackout") and booted again at once. The tracks cannot follow the
        performers over that gap: after 0.3 s of empty frames two CMU performers 300 mm apart
        came back with a pelvis read mirrored and left and right feet exchanged, and kept
        those labels to the end of the take (683 frames), the labeled fraction high. Shorter
        dropouts are held (:meth:`_blackout`): the tennis server's markers are taken up where
        they return after 0.1 s."""
        last, self._t_points = self._t_points, t
        c = self.boot_config
        if last is None or not self._active or c.blackout_reboot_s <= 0:
            return
        if t - last > c.blackout_reboot_s:
            self._drop(sorted(self._active), t, kind="blackout")
            self._since_attempt = self._boot_wait = self._boot_every  # (an attempt now)

    def _drop_vanished(
        self, glab: np.ndarray, state: np.ndarray, pos: np.ndarray, t: float
    ) -> None:
        """Withholds the labels of subjects with fewer than ``vanish_fraction`` of their markers
        observed, or fewer than ``vanish_relative`` of their recent count (a performer leaving:
        the inner labeler would give its last labels to points near where it was, and labels
        the boot put on other performers' points would stay there) and drops those gone for
        ``drop_after_s``."""
        dropped = []
        c = self.boot_config
        # every subject's observed count at once (a loop of per-subject slices cost ~0.1 ms a
        # frame at 10 performers); only the vanishing ones are looked at one by one
        act = np.array(sorted(self._active), dtype=np.int64)
        if c.vanish_fraction <= 0 and c.vanish_relative <= 0:
            # (the window labeler: a subject vanishes only with no marker observed, and the
            # moving average is never read; a third of this step's cost)
            seen = np.zeros(len(self._offset) - 1, dtype=bool)
            seen[self._subject_of[state == MarkerState.OBSERVED]] = True
            ok = seen[act]
            self._gone[act[ok]] = 0
        else:
            obs = (state == MarkerState.OBSERVED).view(np.uint8)
            n_obs = np.add.reduceat(obs, self._offset[:-1], dtype=np.int64)[act]
            size = (self._offset[1:] - self._offset[:-1])[act]
            ref = self._recent[act]
            ok = (n_obs >= np.maximum(1.0, c.vanish_fraction * size)) & (
                (ref <= 0) | (n_obs >= c.vanish_relative * ref)
            )
            self._gone[act[ok]] = 0
            self._recent[act[ok]] = np.where(
                ref[ok] <= 0, n_obs[ok], ref[ok] + self._recent_alpha * (n_obs[ok] - ref[ok])
            )
        for s in act[~ok].tolist():
            self._gone[s] += 1
            self._withhold(s, glab, pos, state)
            if self._gone[s] >= self._drop_frames:
                dropped.append(s)
        if dropped:
            self._drop(dropped, t)

    def _drop_jumped(
        self,
        pts: np.ndarray,
        ids: np.ndarray,
        glab: np.ndarray,
        pos: np.ndarray,
        state: np.ndarray,
        t: float,
    ) -> None:
        """Drops the subjects a jump of the scene took from their tracks
        (:func:`jumped_subjects`): they give no label in this frame and are booted again at
        the next chance; the others keep theirs."""
        last = self._window[-1]
        jumped = jumped_subjects(
            last.ids, last.labels, ids, self._tracker.born, self._subject_of, self.boot_config
        )
        hit = [s for s in jumped.tolist() if s in self._active]
        if hit:
            hit = self._unreached_subjects(hit, pts, t)
        for s in hit:
            self._withhold(s, glab, pos, state)
        if hit:
            self._drop(hit, t, kind="jump")
            self._boot_wait = self._boot_every

    def _unreached_subjects(self, hit: list[int], pts: np.ndarray, t: float) -> list[int]:
        """Of the subjects ``hit`` (their tracks ended: :func:`jumped_subjects`), those whose
        markers mostly have no point of this frame within reach of where they were
        (:func:`marker_reach`; ``jump_fraction`` of the markers labeled in the last frame):
        the tracker ends a track whose point is past its gate around the constant-velocity
        prediction, which every point of a take played back and forth is at each turn."""
        m = len(self._names)
        p1, p2 = np.full((m, 3), np.nan), np.full((m, 3), np.nan)
        last_two = [self._window[-k] for k in range(1, min(2, len(self._window)) + 1)]
        for fr, into in zip(last_two, (p1, p2), strict=False):
            ok = fr.labels >= 0
            into[fr.labels[ok]] = fr.points[ok]
        seen = np.flatnonzero(np.isfinite(p1[:, 0]) & np.isin(self._subject_of, hit))
        dt = t - self._window[-1].t
        dt = dt if dt > 0 else 1.0 / self.rate
        lost = seen[_unreached(pts, p1[seen], p2[seen], dt, self.boot_config)]
        far = set(_subjects_losing(self._subject_of, seen, lost, self.boot_config.jump_fraction))
        return [s for s in hit if s in far]

    def _drop(self, dropped: list[int], t: float, kind: str = "drop") -> None:
        """Drops the active subjects ``dropped``: the inner labeler stops labeling them and the
        window forgets their labels; they are booted again when seen."""
        for s in dropped:
            self._active.discard(s)
            self._gone[s] = 0
            self._recent[s] = 0.0
            self.events.append((t, kind, self.model.subjects[s].name))
            self._inner_known[self._offset[s] : self._offset[s + 1]] = False
            if self._verifier is not None:
                self._verifier.stop(s)
            self._from_labels = self._from_labels - {s}
            self._blocked.pop(s, None)
            if not self._labeled_run:  # (else the rebuild due at the next frame drops it)
                self._inner.drop_subject(self.model.subjects[s].name)
        # the window's labels of dropped subjects are forgotten (a rebuild must not see them)
        gone = np.isin(self._subject_of, dropped)
        for fr in self._window:
            bad = fr.labels >= 0
            bad[bad] = gone[fr.labels[bad]]
            fr.labels[bad] = -1

    def _verify(
        self, ids: np.ndarray, glab: np.ndarray, pos: np.ndarray, state: np.ndarray, t: float
    ) -> None:
        """Re-verification (boot_verify.py): the verifier takes this frame's observed labels;
        markers whose evidence says they are not this subject's lose their labels (this frame,
        the window, the inner labeler) and their tracks are kept from that subject for
        ``verify_block_s``; a subject that mostly fails is dropped and booted again."""
        assert self._verifier is not None
        if self._verifier.idle():  # (the labeled start: its subjects are not re-verified)
            return
        tracks = np.full(len(self._names), -1, dtype=np.int64)
        have = glab >= 0
        tracks[glab[have]] = ids[have]
        verdict = self._verifier.update(pos, state == MarkerState.OBSERVED, tracks)
        if verdict is None:
            return
        for s, pairs in verdict.exchange.items():
            if s in self._active:
                self._exchange(pairs, glab, pos, state)
                self.events.append((t, "exchange", self.model.subjects[s].name))
        c = self.boot_config
        for s, mk in verdict.withdraw.items():
            if s not in self._active:
                continue
            hit = np.isin(glab, mk)
            self._block(s, ids[hit], t + c.verify_block_s)
            glab[hit] = -1
            pos[mk] = np.nan
            state[mk] = MarkerState.MISSING
            self._unlabel(mk)
            self.events.append((t, "withdraw", self.model.subjects[s].name))
        drop = [s for s in verdict.drop if s in self._active]
        if not drop:
            return
        for s in drop:
            self._withhold(s, glab, pos, state)
        self._drop(drop, t, "reject")

    def _exchange(
        self, pairs: np.ndarray, glab: np.ndarray, pos: np.ndarray, state: np.ndarray
    ) -> None:
        """Each marker of ``pairs (K, 2)`` takes the other's points (re-verification: a left
        and a right marker read on each other's, :meth:`BootVerifier._exchanges`): in this
        frame, in the window, and in the inner labeler, whose tracks of them start again from
        the window's exchanged labels (:meth:`Labeler.seed_markers`)."""
        swap = np.arange(len(self._names) + 1)  # (index -1: the last, itself)
        swap[pairs[:, 0]], swap[pairs[:, 1]] = pairs[:, 1], pairs[:, 0]
        for fr in self._window:
            fr.labels[:] = np.where(fr.labels >= 0, swap[fr.labels], -1)
        glab[:] = np.where(glab >= 0, swap[glab], -1)
        a, b = pairs[:, 0], pairs[:, 1]
        pos[a], pos[b] = pos[b].copy(), pos[a].copy()
        state[a], state[b] = state[b].copy(), state[a].copy()
        if not self._labeled_run and self._window:
            win = [(fr.t, fr.points, fr.labels) for fr in self._window]
            self._inner.seed_markers(pairs.ravel(), win)

    def _withhold(self, s: int, glab: np.ndarray, pos: np.ndarray, state: np.ndarray) -> None:
        """Subject ``s`` gives no label in this frame (its points unlabeled, its markers
        missing)."""
        lo, hi = self._offset[s], self._offset[s + 1]
        glab[(glab >= lo) & (glab < hi)] = -1
        pos[lo:hi] = np.nan
        state[lo:hi] = MarkerState.MISSING

    def _block(self, s: int, ids: np.ndarray, until: float) -> None:
        old_ids, old_until = self._blocked.get(s, (np.zeros(0, np.int64), np.zeros(0)))
        self._blocked[s] = (
            np.concatenate([old_ids, ids.astype(np.int64)]),
            np.concatenate([old_until, np.full(ids.size, until)]),
        )

    def _block_masks(self, ids: np.ndarray, t: float) -> dict[int, np.ndarray]:
        """Per subject with blocked tracks: which of ``ids`` it may not take (expired blocks
        are forgotten)."""
        out = {}
        for s in list(self._blocked):
            bid, until = self._blocked[s]
            live = until > t
            if not live.any():
                del self._blocked[s]
                continue
            self._blocked[s] = (bid[live], until[live])
            # (a sorted search: np.isin's set-up cost ~30 us per subject, every frame)
            keys = np.sort(bid[live])
            at = np.minimum(np.searchsorted(keys, ids), keys.size - 1)
            out[s] = keys[at] == ids
        return out

    def _acquire(
        self,
        pts: np.ndarray,
        ids: np.ndarray,
        glab: np.ndarray,
        pos: np.ndarray,
        state: np.ndarray,
        t: float,
    ) -> None:
        """Free points of this frame labeled from the template as markers of active subjects
        that have no point in it (:meth:`Booter.acquire`): a marker hidden at boot is labeled in
        the frame it appears; the inner labeler takes it over at its next rebuild. A free track
        is looked at in its first ``ACQUIRE_TRIES`` frames only (a ghost, or a point no template
        explains, costs nothing after that: crowds leave many free points while booting)."""
        free = glab < 0
        if not self._active or not free.any():
            self._acq_ids = np.zeros(0, dtype=np.int64)
            self._acq_tries = np.zeros(0, dtype=np.int64)
            return
        fid = ids[free]
        tries = np.zeros(fid.size, dtype=np.int64)
        if self._acq_ids.size:
            at = np.minimum(np.searchsorted(self._acq_ids, fid), self._acq_ids.size - 1)
            hit = self._acq_ids[at] == fid
            tries[hit] = self._acq_tries[at[hit]]
        order = np.argsort(fid)
        self._acq_ids, self._acq_tries = fid[order], tries[order] + 1
        look = free.copy()
        look[free] = tries < ACQUIRE_TRIES
        if not look.any():  # (most frames once booted: no block masks needed)
            return
        for mask in self._block_masks(ids, t).values():
            look &= ~mask  # (withdrawn from a subject: not looked at for a while)
        if not look.any():
            return
        new = self._booter.acquire(pts, np.where(look | ~free, glab, -2), sorted(self._active))
        new[~look & free] = -1
        added = (glab < 0) & (new >= 0)
        if not added.any():
            return
        glab[added] = new[added]
        self.acquired += int(added.sum())
        _mark_observed(np.where(added, glab, -1), pts, pos, state)
        if not np.all(self._inner_known[glab[added]]):
            self._acquired_new = True

    def _extend(self) -> bool:
        """Free points joined to active subjects (markers hidden at boot that appear)."""
        last = self._window[-1]
        frames = [(f.points, f.ids) for f in self._window]
        hist = track_history(frames, last.ids)
        new = extend_blocked(
            self._booter,
            last.points,
            hist,
            last.labels,
            sorted(self._active),
            self._block_masks(last.ids, last.t),
            self._tracker.ages(),
            self._checked(),
        )
        added = (new >= 0) & (new != last.labels)
        if not added.any():
            return False
        # markers the joint fill moved (weakly placed at boot: boot_match._weak_markers) give
        # up their old points first
        self._unlabel(last.labels[(last.labels >= 0) & (new != last.labels)])
        extra = np.where(added, new, -1)
        self._spread(last.ids, extra)
        self._install([])
        return True

    def _checked(self) -> list[int]:
        """The active subjects whose readings the extension re-checks (markers on each other's
        points: :func:`~.boot_match._window_exchange`, mirrors, symmetries, segments read
        again onto free points), with the re-verification on: those booted from the stream's
        points, which it verifies, and, when the model is a trained one (a model file, not a
        window model), those the stream's labels placed once the labels stop (``_from_labels``):
        from then on the labeler is on its own. A 25 Hz tennis serve started from 10 labeled
        frames read its trunk one marker along its chain (RBAK's label on C7's point, RSHO's
        on RBAK's, RUPA's on RSHO's) for the remaining 7 s; re-checked, it is read back within
        frames. They are re-checked only, not verified: the verifier's withdrawals took correct
        labels from a kneeling performer whose model was trained prone (a labeled start knows
        the pose is right; the model does not). Not for a window model: templates from 0.4 s
        of the stream are no reference to check the stream against (measured on the labeled
        matrix, re-checked with them: 23 cells better, 40 worse, 15,352 -> 17,450 wrong or
        unlabeled samples on the tune takes, 26,090 -> 27,117 on the others)."""
        v = self._verifier
        if v is None:
            return []
        reread = self.window_frames is None and not self._labeled_run
        placed = self._from_labels if reread else frozenset()
        return [s for s in sorted(self._active) if v.verifies(s) or s in placed]

    def _unlabel(self, markers: np.ndarray) -> None:
        """Markers withdrawn (re-verification) or moved to other points by an extension: their
        labels leave the window and the inner labeler (:meth:`Labeler.withdraw_markers`); a
        moved marker is seeded again from its new track by the install that follows
        (:meth:`Labeler.seed_markers`)."""
        mk = np.unique(np.asarray(markers, dtype=np.int64))
        if mk.size == 0:
            return
        kill = np.zeros(len(self._names) + 1, dtype=bool)  # (index -1: the last, False)
        kill[mk] = True
        for fr in self._window:
            fr.labels[kill[fr.labels]] = -1
        if not self._labeled_run:
            self._inner.withdraw_markers(mk)
        self._inner_known[mk] = False

    def _spread(self, ids: np.ndarray, labels: np.ndarray) -> None:
        """Gives the labels of the last frame's tracks ``ids`` to the window's free points. A
        label is given only once per frame (a track split may repeat it): the first free point
        with it takes it, unless the frame has it already. One kernel pass over the stacked
        window (:func:`~.kernels.stacked._spread_labels`): per frame, a search and a
        ``np.unique`` cost ~0.4 ms of each install on the frame path (24 frames at 360 Hz)."""
        lab = labels >= 0
        tid, tl = ids[lab], labels[lab]
        if tid.size == 0:
            return
        order = np.argsort(tid)
        win = list(self._window)
        starts = np.zeros(len(win) + 1, dtype=np.int64)
        np.cumsum([fr.ids.shape[0] for fr in win], out=starts[1:])
        out = np.concatenate([fr.labels for fr in win])
        fids = np.concatenate([fr.ids for fr in win])
        if not _spread_labels(
            np.ascontiguousarray(tid[order], dtype=np.int64),
            np.ascontiguousarray(tl[order], dtype=np.int64),
            fids.astype(np.int64, copy=False),
            out,
            starts,
            len(self._names),
        ):
            return
        for k, fr in enumerate(win):
            fr.labels[:] = out[starts[k] : starts[k + 1]]

    def _attempt(self, t: float) -> np.ndarray:
        """One boot on the window, in this frame; returns the model indices booted."""
        snap = self.boot_snapshot()
        return self.install_boot(snap, self.boot_step(snap))

    # ------------------------------------------------------------------ boot off the frame
    def needs_boot(self) -> bool:
        """True when a boot attempt is due: the window is full, some model subject is not
        active and the (backed-off) wait since the last attempt has passed. With
        ``inline_boot=False`` the owner checks this after each frame and runs the attempt
        itself (:meth:`boot_snapshot`, :meth:`boot_step`, :meth:`install_boot`). With
        ``inline_extend=False`` also True when an extension of the active subjects is due."""
        return self._boot_due() or self._extend_due() or self._relearn_pending

    def _boot_due(self) -> bool:
        return (
            len(self._window) == self._window.maxlen
            and len(self._active) < len(self.model.subjects)
            and self._since_attempt >= self._boot_wait
        )

    def _extend_due(self) -> bool:
        return (
            not self.inline_extend
            and bool(self._active)
            and len(self._window) == self._window.maxlen
            and (
                self._since_extend >= self._extend_wait
                or (self._acquired_new and self._since_acquire >= self._extend_every)
            )
            and bool(np.any(self._window[-1].labels < 0) or self._acquired_new or self._checked())
        )

    def boot_snapshot(self) -> BootSnapshot:
        """What a boot attempt needs, copied from the window (cheap: a few ms at most); call it
        in the thread that calls :meth:`process`. Restarts the wait to the next attempt (and,
        with ``inline_extend=False``, to the next extension when one is due)."""
        extend = self._extend_due()
        boot = self._boot_due() or not extend
        last = self._window[-1]
        frames = [(f.points, f.ids) for f in self._window]
        snap = BootSnapshot(
            t=last.t,
            points=last.points.copy(),
            ids=last.ids.copy(),
            history=track_history(frames, last.ids),
            free=last.labels < 0,
            subjects=[],
        )
        if boot:
            self._since_attempt = 0
            snap.subjects = [s for s in range(len(self.model.subjects)) if s not in self._active]
            if snap.subjects and not self._labeled_run:
                # the frames from now on are recorded for the attempt's catch-up
                snap.shadow = self._shadow()
                self._since = snap.since = []
        if self._relearn_pending:
            snap.relearn = self._relearn_take()
        if extend:
            self._since_extend = 0
            snap.labels = last.labels.copy()
            snap.active = sorted(self._active)
            snap.blocked = self._block_masks(last.ids, last.t)
            snap.age = self._tracker.ages()
            snap.checked = self._checked()
        return snap

    def boot_step(self, snapshot: BootSnapshot, runner: StepRunner | None = None) -> BootResult:
        """The heavy part of an attempt (0.1-2 s with several performers): reads only the
        snapshot and the prepared templates, changes no state of this labeler, so it may run in
        another thread while :meth:`process` goes on. ``runner`` runs :func:`boot_step_on`
        elsewhere (the service's worker process, ``service/boot_worker.py``: the attempt's
        Python then holds another interpreter's GIL, not the frame path's); it gets
        ``snapshot.remote()`` (no frames) and returns what :func:`boot_step_on` returns."""
        if runner is None:
            res, extended, ms = boot_step_on(self._booter, snapshot)
        else:
            res, extended, ms = runner(snapshot.remote())
        if snapshot.labels is not None:
            snapshot.extended = extended
        if snapshot.subjects:
            self.boot_ms.append(ms)
        if snapshot.relearn is not None:  # (in the job's thread: off the frame path)
            try:
                snapshot.relearned = self._relearn_build(snapshot.relearn)
            except Exception:  # (a failed relearn must not cost the attempt its result)
                log.exception("relearn failed; the booter keeps its templates")
            snapshot.relearn = None
        return res

    def install_boot(self, snapshot: BootSnapshot, result: BootResult | None) -> np.ndarray:
        """Installs ``result`` (of :meth:`boot_step` on ``snapshot``) between two frames, in
        the thread that calls :meth:`process`; returns the model indices of the subjects booted.

        The labels follow the snapshot's tracks to the current window (frames may have passed
        since the snapshot): a track that ended meanwhile loses its label, a point the inner
        labeler has labeled since keeps its label, and a subject that is active by now or keeps
        fewer than three points is not installed. ``result=None`` (the attempt was abandoned,
        e.g. over its time budget) counts as a fruitless attempt: the wait to the next doubles.

        After :meth:`catch_up` on the same snapshot and result the booted subjects are instead
        installed by swapping in the caught-up inner labeler (:meth:`_install_caught`): no
        label is carried along the tracks and no subject is added on the frame path."""
        if snapshot.relearned is not None:  # the relearn the attempt trained
            self._relearn_use(snapshot.relearned)
            snapshot.relearned = None
        recording = snapshot.since is not None and snapshot.since is self._since
        if snapshot.since is self._since:
            self._since = None  # the attempt ends here: stop recording frames for it
        if result is not None and snapshot.caught is not None and recording:
            # (labeled frames meanwhile stopped the recording: their start wins)
            booted = self._install_caught(snapshot)
            if booted is not None:
                return booted
        if result is None:
            if snapshot.subjects:
                self._boot_wait = min(2 * self._boot_wait, self._boot_every_max)
            return np.zeros(0, dtype=np.int64)
        last = self._window[-1]
        lab = result.labels
        ext = None
        if snapshot.labels is not None and snapshot.extended is not None:
            # markers of active subjects the extension found (disjoint from the boot's), and
            # markers it moved (the joint fill re-reads weakly placed ones)
            add = (snapshot.extended >= 0) & (snapshot.extended != snapshot.labels)
            active = self._subjects_in(self._active)
            add &= active[self._subject_of[np.maximum(snapshot.extended, 0)]]
            gone = snapshot.labels[(snapshot.labels >= 0) & (snapshot.extended != snapshot.labels)]
            self._unlabel(gone[active[self._subject_of[gone]]])
            for s, mask in self._block_masks(snapshot.ids, last.t).items():
                # withdrawn from that subject since the snapshot
                add &= ~(mask & (self._subject_of[np.maximum(snapshot.extended, 0)] == s))
            if add.any():
                ext = np.where(add, snapshot.extended, -1)
                lab = np.where(lab >= 0, lab, ext)
        have = lab >= 0
        order = np.argsort(snapshot.ids[have])
        tid, tl = snapshot.ids[have][order], lab[have][order]
        now = np.full(last.ids.shape[0], -1, dtype=np.int64)
        if tid.size:
            pos = np.minimum(np.searchsorted(tid, last.ids), tid.size - 1)
            hit = (tid[pos] == last.ids) & (last.labels < 0)
            now[hit] = tl[pos[hit]]
        names = {s.name: i for i, s in enumerate(self.model.subjects)}
        keep: list[int] = []
        for n in result.subjects:
            s = names[n]
            mine = (now >= self._offset[s]) & (now < self._offset[s + 1])
            if s in self._active or np.count_nonzero(mine) < 3:
                now[mine] = -1
                continue
            keep.append(s)
        booted = np.array(keep, dtype=np.int64)
        if snapshot.subjects:
            self._boot_wait = (
                self._boot_every if booted.size else min(2 * self._boot_wait, self._boot_every_max)
            )
        extended = False
        if snapshot.labels is not None:  # an extension: back off while it finds nothing
            self._extend_wait = (
                self._extend_every
                if ext is not None
                else min(2 * self._extend_wait, EXTEND_BACKOFF * self._extend_every)
            )
        if ext is not None:  # extension labels that still follow a track to this frame
            ok = self._subjects_in([*self._active, *keep])[self._subject_of[np.maximum(now, 0)]]
            now[~ok] = -1  # a subject dropped since the snapshot
            active = self._subjects_in(self._active)
            extended = bool(np.any(now >= 0)) and bool(
                np.any(active[self._subject_of[np.maximum(now, 0)]] & (now >= 0))
            )
        if not booted.size and not extended and not self._acquired_new:
            return booted
        self._spread(last.ids, now)
        self._active.update(keep)
        for s in keep:
            self.events.append((last.t, "boot", self.model.subjects[s].name))
            if self._verifier is not None:
                self._verifier.start(s)
        self._install(keep)
        return booted

    def catch_up(
        self,
        snapshot: BootSnapshot,
        result: BootResult,
        cancel: threading.Event | None = None,
        remote: CatchUpRemote | None = None,
    ) -> bool:
        """Brings a boot result up to the current frame off the frame path (call it in the
        thread that ran :meth:`boot_step`, after it). The snapshot holds a copy of this
        labeler as it was then (its *shadow*: window, subjects, counters, the point tracker);
        the shadow installs the result at once, as an instant attempt would have (its inner
        labeler adds the booted subjects and those labeled at the snapshot from the window's
        labels, the extension's included), then labels every frame :meth:`process` has seen
        since (recorded for this attempt) with the same frame path (inner labeler, vanishing
        subjects, acquisition from the template), until it has caught up. It reads the
        snapshot and the recorded frames only (the frame thread appends to that list).
        :meth:`install_boot` then labels the frames that arrived meanwhile (normally none or
        one) and takes the shadow's state over. Returns False when there is nothing to catch
        up (no subject booted, frames not recorded, ``cancel`` set): the install then carries
        the labels along the tracks as before.

        Why: a result that arrives 600 frames after its snapshot (a 1.7 s attempt at 360 Hz)
        followed the anonymous tracks that long; a marker hidden for one frame ends its
        track, so most labels were lost (10 hugging performers: 0 of 10 reached 95 % correct),
        and the inner labeler added 10 subjects at once on the frame path (~20-40 ms)."""
        since, shadow = snapshot.since, snapshot.shadow
        if since is None or shadow is None or not result.subjects:
            return False
        if len(since) < CATCH_UP_AFTER_S * self.rate:
            return False
        plain = snapshot.remote()
        stride = max(1, int(self.rate // CATCH_UP_HZ))
        w = self._window.maxlen or 1
        done = rounds = 0
        if remote is None:
            booted = shadow._begin_catch_up(plain, result)
            feed = shadow._catch_up_frames
        else:
            # the inner labeler the shadow restarts from after the hand-back, built now: each
            # ms after the hand-back is a ms of frames labeled in this process (below), while
            # the worker's rounds stride past a delay here (10 performers: ~20 ms of ~30)
            fresh = Labeler.from_model(self.model, self.rate, self.config, subjects=())
            # the shadow's frames run in the worker process (its Python holds the worker's
            # GIL, not the frame path's)
            booted = remote.begin(shadow, plain, result)
            feed = remote.frames
        if booted is None:
            return False
        try:
            while done < len(since):  # the frame thread appends meanwhile
                if cancel is not None and cancel.is_set():
                    if remote is not None:
                        remote.abort()  # the worker holds a shadow that will not finish
                    return False
                tail = rounds < CATCH_UP_TAIL_ROUNDS
                batch, done = _catch_up_plan(since, done, stride, w, tail)
                feed(batch)
                rounds += 1
        except BaseException:
            if remote is not None:
                remote.abort()  # (a no-op when the failed request released it already)
            raise
        if remote is None:
            shadow._catch_up_extend()
        else:
            try:
                remote.extend()
                # the frames that arrived during the extension, at the full rate, there too:
                # labeled here (after the transfer) they held the frame path's GIL, and a frame
                # path that labels at about the frame rate left it few periods (10 hugging
                # performers at 360 Hz: ~200 frames, 0.4 s, after a 0.1 s extension)
                for _ in range(CATCH_UP_TAIL_ROUNDS):
                    if len(since) - done <= 1:
                        break
                    if cancel is not None and cancel.is_set():
                        remote.abort()
                        return False
                    batch = [(f.t, f.points) for f in since[done:]]
                    done += len(batch)
                    feed(batch)
            except BaseException:
                remote.abort()
                raise
            # it comes back without its inner labeler, which is started here from its
            # window's labels (as an install would: ~10 ms)
            shadow = remote.finish()
            shadow._booter, shadow.model = self._booter, self.model
            shadow.boot_model = self.boot_model
            shadow._inner_from_window(fresh)
        done = shadow._catch_last(since, done, cancel)
        if done < 0:
            return False
        snapshot.shadow = shadow  # (the one that caught up: in process, the same object)
        snapshot.caught = _CatchUp(list(booted), done)
        return True

    def _begin_catch_up(self, snapshot: BootSnapshot, result: BootResult) -> list[int] | None:
        """On a shadow (:meth:`catch_up`): a new inner labeler with the subjects labeled at the
        snapshot (from its window), then the result installed as an instant attempt would;
        returns the subjects booted (None: none)."""
        try:
            self._restart_inner()  # the subjects labeled at the snapshot, from its window
            booted = self.install_boot(snapshot, result)
            if booted.size:
                # markers the boot missed, before the booted markers' predictions can take
                # their points (as the live labeler's first extension after a boot)
                self._catch_up_extend()
        except LabelerError:
            return None
        return booted.tolist() if booted.size else None

    def _catch_up_frames(self, batch: list[tuple[float, np.ndarray]]) -> None:
        """On a shadow: labels ``(t, points)`` frames, without the extension: the
        catch-up extends once right after the install (:meth:`_begin_catch_up`) and once at
        its end. 10 hugging performers, result 1.7 s late, correct over the last second: 0.85
        installed at once; caught up with the extension every period 0.84 (5.4 s of catch-up
        on a loaded machine), never 0.76, after the install and at the end 0.80 (1.5 s). An
        extension costs tens to hundreds of ms (a 4-walker catch-up with one per full-rate
        round fell 2 s behind the stream on a loaded machine: 0.4 s a round)."""
        for t, points in batch:
            self.process(points, t)

    def _catch_last(self, since: list[_Frame], done: int, cancel: threading.Event | None) -> int:
        """On a shadow, last: labels the frames that arrived meanwhile (no extension), then
        waits (two frame periods at most) for the next one and labels it too, so the result is
        delivered just after a frame and the install rarely finds a frame left (each costs the
        frame path a frame's labeling). Returns the frames done, -1 when cancelled.

        Only the newest :data:`CATCH_LAST_FULL` frames at the full rate, older ones every
        ``rate // CATCH_UP_HZ``-th, as the catch-up does while behind: after a worker's
        catch-up this runs in the service's process, beside the frame path, which labels every
        frame too. There, at the full rate, 10 hugging performers at 360 Hz (the shadow 18-570
        frames behind when the worker handed it back, 50-80 ms more to start its inner
        labeler) took 0.1-0.7 s on a quiet machine and up to 3.8 s on a loaded one, chasing
        frames that arrived about as fast as it labeled them."""
        deadline = time.perf_counter() + 2.0 / self.rate
        waited = False
        stride = max(1, int(self.rate // CATCH_UP_HZ))
        while True:
            while done < len(since):
                if cancel is not None and cancel.is_set():
                    return -1
                batch, done = _catch_up_plan(since, done, stride, CATCH_LAST_FULL, True)
                self._catch_up_frames(batch)
            if waited:
                return done
            while len(since) == done and time.perf_counter() < deadline:
                time.sleep(0.0002)
            waited = True

    def _catch_up_extend(self) -> None:
        """On a shadow, once at the end of the catch-up: one extension of its subjects (markers
        hidden at boot that appeared meanwhile; without it a booted marker's prediction took
        such a point in a 4-walker scene: 0.953 -> 0.943 correct after boot)."""
        full = len(self._window) == self._window.maxlen
        if self._active and full and np.any(self._window[-1].labels < 0):
            self._extend()

    def _restart_inner(self, fresh: Labeler | None = None) -> None:
        """On a shadow: a new inner labeler (``fresh``, built with no subject, or built here),
        started from the window's labels of the active subjects."""
        if fresh is None:
            fresh = Labeler.from_model(self.model, self.rate, self.config, subjects=())
        self._inner = fresh
        self._inner_known[:] = False
        names = [self.model.subjects[s].name for s in sorted(self._active)]
        if names:
            self._inner.add_subjects(names, [(f.t, f.points, f.labels) for f in self._window])
            for f in self._window:
                self._inner_known[f.labels[f.labels >= 0]] = True

    def _inner_from_window(self, fresh: Labeler | None = None) -> None:
        """On a shadow back from the worker process: its inner labeler (``fresh``, see
        :meth:`_restart_inner`), started from its window's labels (every subject it labels),
        and its marker states from the last frame."""
        self._restart_inner(fresh)
        last = self._window[-1].labels
        self._inner_state = np.zeros(len(self._names), dtype=np.uint8)
        self._inner_state[last[last >= 0]] = MarkerState.OBSERVED

    def for_transfer(self) -> BootingLabeler:
        """This (shadow) labeler without what a worker process has or rebuilds (the booter,
        the model, the inner labeler): what crosses the pipe (~0.5 MB, not ~16 MB). After a
        relearn the model is not the booter's and goes along."""
        out = copy.copy(self)
        out._booter = None  # type: ignore[assignment]
        if self.model is self.boot_model:
            out.model = None  # type: ignore[assignment]
        out.boot_model = None  # type: ignore[assignment]
        out._inner = None  # type: ignore[assignment]
        return out

    def _install_caught(self, snapshot: BootSnapshot) -> np.ndarray | None:
        """The install after :meth:`catch_up`: the shadow labels the frames that arrived since
        it finished, then this labeler takes its state over (the point tracker stays: this
        labeler's, which saw every frame; the shadow saw every stride-th frame while behind, so
        its window's labels come over by frame time). None:
        not applicable (the shadow's tracks differ), the caller installs along the tracks."""
        cu, shadow = snapshot.caught, snapshot.shadow
        assert cu is not None and shadow is not None and snapshot.since is not None
        for f in snapshot.since[cu.done :]:  # arrived after the catch-up ended
            shadow.process(f.points, f.t)
        cu.done = len(snapshot.since)
        if shadow._window[-1].t != self._window[-1].t:
            return None  # (cannot happen: both end with the stream's last frame)
        for name in _SHADOWED:
            setattr(self, name, getattr(shadow, name))
        if self._verifier is not None:  # the shadow's subjects, verified from now on
            for s in range(len(self.model.subjects)):
                # (not those the stream's labels placed: re-checked only, see _checked)
                want = s in self._active and s not in self._from_labels
                if want != self._verifier.verifies(s):
                    (self._verifier.start if want else self._verifier.stop)(s)
        # the shadow's labels on this labeler's frames (their points, its track ids); frames
        # the shadow skipped (the catch-up's stride) keep none
        by_t = {f.t: f.labels for f in shadow._window}
        for f in self._window:
            lab = by_t.get(f.t)
            if lab is not None and lab.shape == f.labels.shape:
                f.labels = lab
            else:
                f.labels = np.full(f.labels.shape, -1, dtype=np.int64)
        # the free tracks count as looked at by the acquisition (the shadow looked at them; a
        # first look at every free point in one frame would cost that frame ms in a crowd)
        last = self._window[-1]
        self._acq_ids = np.sort(last.ids[last.labels < 0])
        self._acq_tries = np.full(self._acq_ids.size, ACQUIRE_TRIES, dtype=np.int64)
        self.acquired += shadow.acquired
        t = self._window[-1].t  # its boots are labeled from the next frame on
        self.events.extend((t, e, n) if e == "boot" else (te, e, n) for te, e, n in shadow.events)
        snapshot.caught = snapshot.shadow = None  # (its state is this labeler's now)
        return np.array([s for s in cu.booted if s in self._active], dtype=np.int64)

    def _shadow(self) -> BootingLabeler:
        """A copy of this labeler's per-frame state for :meth:`catch_up` (frame thread; cheap:
        the window's frames with their labels copied, the small arrays, the point tracker,
        whose arrays are replaced and never changed in place by ``update``). The inner
        labeler is not copied: the catch-up starts a new one."""
        sh = copy.copy(self)
        sh._window = deque(
            (_Frame(f.t, f.points, f.ids, f.labels.copy()) for f in self._window),
            maxlen=self._window.maxlen,
        )
        sh._active = set(self._active)
        for name in ("_gone", "_recent", "_inner_state", "_inner_known", "_acq_ids", "_acq_tries"):
            setattr(sh, name, getattr(self, name).copy())
        # no relearn history: a shallow copy shared this labeler's deques, and the shadow's
        # frames (in the job's thread) went into them; nor its weight across the pipe
        sh._relearn_every = 0
        sh._relearn_pending = False
        sh._relearn_frames, sh._relearn_clean = deque(maxlen=1), deque(maxlen=1)
        sh._tracker = copy.copy(self._tracker)
        # (no re-verification while catching up: the catch-up races the stream within the
        # attempt's budget; the subjects it books are verified from the install on)
        sh._verifier = None
        sh._blocked = dict(self._blocked)
        # catch_up builds the shadow's inner labeler
        sh._inner = None  # type: ignore[assignment]
        sh._since = None
        sh.inline_boot = False  # the shadow never starts attempts
        sh.inline_extend = False  # nor extensions: the catch-up places them (_catch_up_extend)
        sh.events = History()
        sh.boot_ms = History()
        sh.acquired = 0
        return sh

    def _subjects_in(self, subjects) -> np.ndarray:
        """``(S,)`` bool: which model subjects are in ``subjects`` (index it with
        ``self._subject_of[...]``: a lookup, where ``np.isin`` sorts its input each call)."""
        out = np.zeros(len(self.model.subjects), dtype=bool)
        out[list(subjects)] = True
        return out

    def _install(self, added: list[int]) -> None:
        """The inner labeler takes over the window's labels of the subjects ``added`` (booted
        now: :meth:`Labeler.add_subjects`) and of the active subjects' markers it has not got
        (labeled by an extension or acquisition: :meth:`Labeler.seed_markers`); every other
        marker keeps its state. Costs the added markers alone, not a rebuild."""
        if self._labeled_run:  # the rebuild due at the next unlabeled frame takes the window
            return
        win = [(fr.t, fr.points, fr.labels) for fr in self._window]
        if added:
            self._inner.add_subjects([self.model.subjects[s].name for s in added], win)
        old = self._subjects_in([s for s in self._active if s not in added])[self._subject_of]
        last = self._window[-1].labels
        seen = np.zeros(len(self._names), dtype=bool)
        for fr in self._window:
            seen[fr.labels[fr.labels >= 0]] = True
        now = np.zeros(len(self._names), dtype=bool)
        now[last[last >= 0]] = True
        # labeled in this frame but not by the inner labeler, or never known to it
        seed = old & (
            (now & (self._inner_state != MarkerState.OBSERVED)) | (seen & ~self._inner_known)
        )
        if seed.any():
            self._inner.seed_markers(np.flatnonzero(seed), win)
        self._inner_known[self._subjects_in(added)[self._subject_of]] = False  # (booted again)
        self._inner_known |= seen
        self._acquired_new = False
        self._since_acquire = 0

    def _rebuild(self) -> None:
        """A new inner labeler for the active subjects, started from the labeled frames of the
        run that just ended (the last ``LABELED_KEPT_S`` of them); the next frame is its first
        unlabeled one."""
        order = sorted(self._active)
        names = [self.model.subjects[s].name for s in order]
        inner = Labeler.from_model(self.model, self.rate, self.config, subjects=names)
        mine = np.isin(self._subject_of, order)
        if order:
            for fr in self._labeled_frames:
                lab = np.where(fr.labels >= 0, fr.labels, -1)
                lab[lab >= 0] = np.where(mine[lab[lab >= 0]], lab[lab >= 0], -1)
                inner.process(fr.points, fr.t, lab)
        self._inner = inner
        self._labeled_frames.clear()
        self._inner_known[:] = False
        for fr in self._window:
            self._inner_known[fr.labels[fr.labels >= 0]] = True
        self._acquired_new = False
        self._since_acquire = 0

    # ------------------------------------------------------------------ warm-up
    def warmup(self) -> None:
        """Compiles the boot's and the inner labeler's kernels (see :meth:`Labeler.warmup`)
        without touching this labeler's state."""
        warmup_booting(self.rate, self.config)


def warmup_booting(rate: float, config: LabelerConfig) -> None:
    """Compiles (or loads) everything a booting labeler runs: the boot's kernels and the inner
    labeler's (:func:`warmup_labeler`), on tiny labelers of their own."""
    warmup_kernels()
    warmup_labeler(rate, config)


def warmup_labeler(rate: float, config: LabelerConfig) -> None:
    """Compiles (or loads) the inner labeler's kernels, its install's included
    (``Labeler.add_subjects``' warm start), on tiny labelers of their own: what a booting
    labeler's frames run besides the boot (:meth:`BootingLabeler.warmup`; the service's boot
    worker runs it for the catch-up's shadow)."""
    Labeler(["w:a", "w:b", "w:c"], rate, config).warmup()
    rng = np.random.default_rng(0)
    base = rng.normal(0, 100, (6, 3)).astype(np.float32)
    names = [f"w:m{i}" for i in range(6)]
    train = Labeler(names, rate, config)
    frames = []
    # jitter whose second differences stay those of 0.5 mm at 120 Hz at any rate: a fixed 0.5 mm
    # at 2,000 Hz reads as accelerations no body has, and training refused the warm-up itself
    jitter = 0.5 * min(1.0, (120.0 / rate) ** 2)
    for k in range(12):
        pts = base + rng.normal(0, jitter, (6, 3)).astype(np.float32) + np.float32(k)
        frames.append((k / rate, pts, np.arange(6)))
        train.process(pts, k / rate, np.arange(6))
    inner = Labeler.from_model(train.train_model(), rate, config, subjects=())
    inner.add_subjects(["w"], frames[-4:])
    inner.process(base + np.float32(12), 12 / rate)


def warmup_jump_watch(rate: float) -> None:
    """Compiles (or loads) the scan of :class:`JumpWatch` (a service stream's plain labeler
    runs it every frame), through a jump of six points."""
    base = np.random.default_rng(0).normal(0, 100, (6, 3))
    watch = JumpWatch(rate, BootConfig(jump_min_markers=1), np.zeros(6, dtype=np.int64))
    for k, pts in enumerate((base, base + 1.0, base + 2.0, base + 500.0)):
        watch.update(pts, k / rate, np.arange(6))


#: Runs :func:`boot_step_on` somewhere (see :meth:`BootingLabeler.boot_step`).
StepRunner = Callable[[BootSnapshot], tuple[BootResult, np.ndarray | None, float]]


def boot_step_on(
    booter: Booter, snapshot: BootSnapshot, share: HypothesesShare | None = None
) -> tuple[BootResult, np.ndarray | None, float]:
    """One attempt's step on ``snapshot`` (its :meth:`~BootSnapshot.remote` part suffices):
    the extension of the subjects labeled (when the snapshot carries their labels: the new
    labels, else None), then the boot of the others; returns ``(result, extended, boot ms)``.
    A plain function of the booter and the snapshot, so a worker process can run it
    (``share``: :meth:`Booter.run`'s)."""
    extended = None
    if snapshot.labels is not None:
        extended = extend_blocked(
            booter,
            snapshot.points,
            snapshot.history,
            snapshot.labels,
            snapshot.active,
            snapshot.blocked,
            snapshot.age,
            snapshot.checked,
        )
    if not snapshot.subjects:  # an extension only
        empty = BootResult(np.full(snapshot.points.shape[0], -1, dtype=np.int64), [], {})
        return empty, extended, 0.0
    tb = time.perf_counter()
    res = booter.run(
        snapshot.points,
        snapshot.history,
        free=snapshot.free,
        subjects=snapshot.subjects,
        share=share,
    )
    return res, extended, (time.perf_counter() - tb) * 1e3


class CatchUpRemote(Protocol):
    """Runs a catch-up's shadow elsewhere (``service/boot_worker.py``): ``begin`` sends the
    shadow (:meth:`BootingLabeler.for_transfer`) with the snapshot and result and returns what
    :meth:`BootingLabeler._begin_catch_up` returned there; ``frames`` labels a batch there
    (:meth:`BootingLabeler._catch_up_frames`); ``finish`` returns the shadow (without its
    inner labeler, booter and model); ``abort`` ends it without a result."""

    def begin(
        self, shadow: BootingLabeler, snapshot: BootSnapshot, result: BootResult
    ) -> list[int] | None: ...

    def frames(self, batch: list[tuple[float, np.ndarray]]) -> None: ...

    def extend(self) -> None:
        """The extension at the end of the catch-up (:meth:`BootingLabeler._catch_up_extend`)."""

    def finish(self) -> BootingLabeler: ...

    def abort(self) -> None:
        """Ends a catch-up that will not be finished (its job was abandoned)."""


def _catch_up_plan(
    since: list[_Frame], done: int, stride: int, w: int, tail: bool
) -> tuple[list[tuple[float, np.ndarray]], int]:
    """The next round of a catch-up, from ``since[done]`` to the newest frame: every
    ``stride``-th frame (at least ``CATCH_UP_HZ``: the labeler's Kalman takes the longer steps)
    while more than a window (``w``) behind, then (``tail``) every frame, so that the window
    handed over holds the stream's last frames at their rate (the extension's track histories
    and the inner labeler's restart read it: strided, 10 hugging performers lost 0.84 -> 0.76
    correct). A round costs a ``stride``-th of the frames that arrived meanwhile plus a window;
    when frames cost more than a period (a loaded machine) the full-rate window never catches
    up, so after ``CATCH_UP_TAIL_ROUNDS`` rounds the caller asks for no tail (strided to the
    newest frame). Returns ``[(t, points)]`` and the next ``done``."""
    n = len(since)
    out: list[tuple[float, np.ndarray]] = []
    while done < n:
        full = tail and n - done <= w + stride
        out.append((since[done].t, since[done].points))
        if full:
            done += 1
        else:
            done = min(done + stride, n - 1) if done < n - 1 else n
    return out, done


#: The per-frame state a caught-up shadow hands over (:meth:`BootingLabeler._install_caught`).
_SHADOWED = (
    "_active", "_gone", "_recent", "_boot_wait", "_since_attempt", "_since_extend",
    "_extend_wait", "_inner", "_inner_state", "_inner_known", "_acquired_new", "_since_acquire",
    "_blocked", "_from_labels",
)  # fmt: skip


def jumped_subjects(
    prev_ids: np.ndarray,
    prev_labels: np.ndarray,
    ids: np.ndarray,
    born: int,
    subject_of: np.ndarray,
    config: BootConfig,
) -> np.ndarray:
    """The subjects (values of ``subject_of``) a jump of the whole scene took from their tracks
    in this frame; empty when there was none (``BootConfig.jump_fraction``).

    ``prev_ids`` and ``prev_labels``: the anonymous track id (:class:`PointTracker`) and the
    marker index (-1: none) of each point of the previous frame; ``ids``: this frame's track
    ids, of which ``born`` began in it (``PointTracker.born``). A jump ends the tracks of most
    labeled points, and most of the frame's points begin new ones: they are still there, each
    beyond the tracker's gate from where it was (every performer moved at once: a take that
    loops, frames lost with ``seq`` and ``t`` continuous), even when many markers are hidden in
    that frame too. Markers hidden or a performer leaving end tracks while the points left
    continue theirs; a fast limb at a low rate mostly stays inside the tracker's gate, which
    grows with the frame period; a sender's junk (1,200 random points a frame, redrawn each
    time) begins new tracks while the labeled points continue theirs. Left alone, the labeler's
    tracks take whatever points they reach next and keep them (a looped take: a fifth to a
    quarter of the labels wrong for good, among markers that read observed). It is a jump when
    ``jump_fraction`` of the labeled points lost their tracks and ``jump_fraction`` of this
    frame's points are on new ones (each at least ``jump_min_markers``); the subjects hit are
    those whose labeled points lost ``jump_fraction`` of their tracks."""
    if config.jump_fraction <= 0 or prev_ids.size == 0:
        return np.zeros(0, dtype=np.int64)
    # this frame's points mostly on new tracks (most frames stop here, with no track search)
    if born < max(config.jump_min_markers, config.jump_fraction * ids.size):
        return np.zeros(0, dtype=np.int64)
    lab = prev_labels >= 0
    gone = lab & ~np.isin(prev_ids, ids)
    if np.count_nonzero(gone) < max(
        config.jump_min_markers, config.jump_fraction * np.count_nonzero(lab)
    ):
        return np.zeros(0, dtype=np.int64)
    return _subjects_losing(subject_of, prev_labels[lab], prev_labels[gone], config.jump_fraction)


def _subjects_losing(
    subject_of: np.ndarray, had: np.ndarray, lost: np.ndarray, fraction: float
) -> np.ndarray:
    """The subjects of which ``fraction`` of the markers ``had`` are among those ``lost``
    (marker indices; ``subject_of`` maps a marker to its subject)."""
    n = int(subject_of.max()) + 1 if subject_of.size else 0
    n_had = np.bincount(subject_of[had], minlength=n)
    n_lost = np.bincount(subject_of[lost], minlength=n)
    return np.flatnonzero((n_had > 0) & (n_lost >= fraction * n_had))


class JumpWatch:
    """A jump of the whole scene under a labeler that has no point tracks of its own (the plain
    labeler of a service stream), for a few dozen distances a frame.

    Tracking every point (:class:`PointTracker`, as :func:`jumped_subjects` reads a booting
    labeler's tracks) cost 0.21 ms a frame at 500 points: the default 10 x 360 Hz stream's
    latency p50 1.50 -> 1.75 ms. Instead ``SAMPLE`` of the markers the labeler put on points in
    the last frame, a fixed random choice, are looked for among this frame's points within
    their reach of where they were (:func:`marker_reach`: the last step plus the point
    tracker's gate). A jump leaves none there: the points are elsewhere. When
    ``jump_fraction`` of the sample find no point (and at least ``jump_min_markers``) and
    ``jump_fraction`` of up to ``SAMPLE`` of this frame's points continue no marker (none
    within the largest reach: a performer who leaves or is hidden takes his points with him,
    and the others' points continue theirs), every marker labeled in the last frame is looked
    for, and the subjects that lost ``jump_fraction`` of theirs are the ones hit."""

    SAMPLE = 64

    def __init__(self, rate: float, config: BootConfig, subject_of: np.ndarray) -> None:
        self._rate = float(rate)
        self._config = config
        self._subject_of = np.asarray(subject_of, dtype=np.int64)
        m = self._subject_of.size
        self._pos = np.full((m, 3), np.nan)  # the last frame's labeled markers
        self._pos2 = np.full((m, 3), np.nan)  # the frame before
        self._t = np.nan
        self._order = np.random.default_rng(0).permutation(m)  # (the sample's fixed order)
        #: the last frame's share (diagnostics): the smaller of the sample's share that found
        #: no point and, when that reached ``jump_fraction``, the share of new points
        self.share = 0.0

    def update(self, points: np.ndarray, t: float, labels: np.ndarray) -> np.ndarray:
        """The subjects a jump took from their markers in this frame (``labels``: the labeler's
        marker index per point, -1 none); empty when none."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        hit = self._check(pts, float(t))
        lab = np.asarray(labels, dtype=np.int64)
        pos = np.full_like(self._pos, np.nan)
        ok = lab >= 0
        pos[lab[ok]] = pts[ok]
        # (after a jump the last frame's positions give no velocity: they are across it)
        self._pos2 = self._pos if hit.size == 0 else np.full_like(pos, np.nan)
        self._pos, self._t = pos, float(t)
        return hit

    def _check(self, pts: np.ndarray, t: float) -> np.ndarray:
        c = self._config
        none = np.zeros(0, dtype=np.int64)
        self.share = 0.0
        if c.jump_fraction <= 0 or not np.isfinite(self._t) or pts.shape[0] == 0:
            return none
        dt = t - self._t
        if not dt > 0:
            dt = 1.0 / self._rate
        seen = np.isfinite(self._pos[:, 0])
        n_seen = int(np.count_nonzero(seen))
        if n_seen < c.jump_min_markers:
            return none
        sample = self._order[seen[self._order]][: self.SAMPLE]
        missed = int(np.count_nonzero(self._misses(pts, sample, dt)))
        self.share = missed / sample.size
        if missed < max(c.jump_min_markers, c.jump_fraction * sample.size):
            return none
        # and as many of this frame's points continue no marker (a performer who leaves or is
        # hidden takes his points with him; the others' points continue theirs)
        every = np.flatnonzero(seen)
        reach = self._reach(every, dt)
        step = max(1, pts.shape[0] // self.SAMPLE)
        cur = np.ascontiguousarray(pts[::step][: self.SAMPLE])
        wide = np.full(cur.shape[0], float(reach.max()))
        new = int(np.count_nonzero(_no_point_within(self._pos[every], cur, wide)))
        self.share = min(self.share, new / cur.shape[0])
        if new < c.jump_fraction * cur.shape[0]:
            return none
        lost = every[_no_point_within(pts, np.ascontiguousarray(self._pos[every]), reach)]
        return _subjects_losing(self._subject_of, every, lost, c.jump_fraction)

    def _reach(self, markers: np.ndarray, dt: float) -> np.ndarray:
        """``(K,)`` how far from its last position each of ``markers`` can be in this frame
        (:func:`marker_reach`)."""
        return marker_reach(self._pos[markers], self._pos2[markers], dt, self._config)

    def _misses(self, pts: np.ndarray, markers: np.ndarray, dt: float) -> np.ndarray:
        """Per marker of ``markers``: no point of ``pts`` within its reach of its last
        position (:func:`_unreached`)."""
        return _unreached(pts, self._pos[markers], self._pos2[markers], dt, self._config)


class DropoutHold:
    """Runs of frames with no point at all (the cameras saw nothing: a dropout, a sender's
    empty frames), which say nothing of who left: the booting labeler's vanish rule and a
    service stream's watch on the plain labeler skip such frames while the run is shorter than
    ``blackout_hold_s``."""

    def __init__(self) -> None:
        self._since: float | None = None  # the first frame of the current empty run

    def held(self, n_points: int, t: float, hold_s: float) -> bool:
        """A frame of ``n_points`` at ``t``: True when it is empty and its run began less than
        ``hold_s`` ago."""
        if n_points:
            self._since = None
            return False
        if self._since is None:
            self._since = t
        return t - self._since < hold_s


def marker_reach(p1: np.ndarray, p2: np.ndarray, dt: float, config: BootConfig) -> np.ndarray:
    """``(K,)`` how far (mm) from its last position ``p1 (K, 3)`` each marker can be a frame
    ``dt`` later: its last step (from ``p2``, NaN: none) plus the point tracker's gate around a
    constant-velocity prediction (:func:`~labeler_service.labeling.boot_tracks.track_gates`),
    the gate for a point without a velocity where there is no last step. The sphere holds the
    gate around the constant-velocity prediction and around the reversed one: a sender playing
    a take back and forth reverses every velocity at once, which no performer does, but its
    points are where the markers were. At each turn of such a replay (the service tests', 2
    simulated walkers at 120 Hz) the walker's points lay 7-24 mm (median 18.5) from their
    predictions, past the 13 mm gate: both jump rules read a jump, and he was booted again at
    every other turn (a test's accuracy 0.977, where it asks 0.99)."""
    vel = np.isfinite(p2[:, 0])
    moving, still = track_gates(config, dt)
    last = np.linalg.norm(np.where(vel[:, None], p1 - p2, 0.0), axis=1)
    return np.where(vel, moving + last, still).astype(np.float64)


def _unreached(
    points: np.ndarray, p1: np.ndarray, p2: np.ndarray, dt: float, config: BootConfig
) -> np.ndarray:
    """Per marker (last positions ``p1``, the ones before ``p2``): no point of ``points``
    within its reach (:func:`marker_reach`)."""
    reach = marker_reach(p1, p2, dt, config)
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return _no_point_within(pts, np.ascontiguousarray(p1, dtype=np.float64), reach)


def _mark_observed(labels: np.ndarray, pts: np.ndarray, pos: np.ndarray, state: np.ndarray) -> None:
    """Every labeled point becomes its marker's observed position (in place)."""
    ok = labels >= 0
    pos[labels[ok]] = pts[ok]
    state[labels[ok]] = MarkerState.OBSERVED
