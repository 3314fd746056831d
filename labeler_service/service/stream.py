"""Per-stream state: sequence checks, the training window, the labeler, the output message.

A stream (one capture volume) starts in one of two ways:

1. **From a subject model file** (``streams[].model``, the ``train structure`` output): the
   labeler is built at start-up (after the server's kernel warm-up); frames are labeled from
   the first one.
2. **From labeled init frames in the stream** (the supervised training window of Yu, Li and
   Deng 2007): frames carrying ``labels`` are buffered; when the first unlabeled frame
   arrives, the marker set is the union of the init labels (sorted by subject, then marker),
   the rate comes from the settings or the init frames' times, the labeler is built and fed the init
   frames with their labels, then labels the new frame.

``seq`` and ``t`` handling (:mod:`labeler_service.service.continuity`): duplicates and slightly
late frames are dropped; a jump of ``seq`` or ``t`` (forward or back) is suspect and dropped
until ``run_confirm_frames`` consecutive frames continue it; then it is a **new run**. A new
run that starts with labeled init frames retrains from them (a model stream rebuilds from its
model); an unlabeled one continues with the current labeler, time re-based so the labeler sees
one frame period across the jump, unless ``t`` jumped: then (a gap of unknown length) the
stream recovers by boot (below) when its labeler has a model.

**The window start** (``labeled_start`` ``auto`` where it applies, or ``model``): the server's
training job (:meth:`StreamState.train_staged`) trains the plain labeler, as the ``labeler``
start does, and returns a :class:`~labeler_service.service.handover.Handover`; frames flow at
once, each one recorded after the plain labeler labeled it. The window model, its booting
labeler and the catch-up on the recorded frames run off the event loop
(:meth:`StreamState.handover_job`, through the same ``Background``); the next frame after the
job installs the window labeler (:meth:`StreamState._install_handover`: the frames recorded
since the job ended, normally 0-2, fed on the frame path, more sent back for another job). A
new run, a recovery, another install or the stream's removal abandon it (the plain labeler
stays). :meth:`StreamState.train` (in-process use, :meth:`StreamState.process`) still builds
the window labeler at once.

Limits (counted by the server when hit): ``max_init_frames`` and ``max_init_bytes`` of buffered
init frames (``init_overflow``), ``max_markers`` distinct labels (``marker_cap``). Training runs
off the event loop through :class:`~labeler_service.service.background.Background`
(:meth:`StreamState.train` is the job).

**Boot** (a stream with a ``model`` and ``boot = true``; off by default): the labeler is a
:class:`~labeler_service.labeling.booting.BootingLabeler` built with ``inline_boot=False``, so
labeling a frame never boots. After a frame, :meth:`StreamState.boot_request` (frame thread)
takes a snapshot when an attempt is due and none is in flight; the server runs
:meth:`StreamState.boot_job` through the same ``Background`` as training (budget
``boot_budget_s``) and hands the result back with :meth:`StreamState.boot_done`; the next
:meth:`StreamState.process` installs it before labeling (its cost counts in that frame's
labeling time). Until a subject boots its points go out unlabeled; frames keep flowing. A frame
that carries labels is used as the answer for its subjects (no boot needed for them), so a
client that sends labeled init frames still starts as before. A performer who leaves is dropped
by the labeler and booted again when back (the ``lost`` status needs nothing more). A new run
whose ``t`` jumped starts a fresh booting labeler of the same model (:meth:`StreamState.reboot`).

Health: the labeled fraction (observed markers / model markers; for a booting labeler, / the
markers of the subjects it has booted, so a model listing performers who are not in the volume
does not read ``degraded``) and the recovered fraction are exponential averages with the time
constant ``health_window_s``;
below ``degraded_below`` / ``lost_below`` the stream's status becomes ``degraded`` / ``lost``
(:meth:`StreamState.update_health`). ``on_lost`` is the hook the
server calls then (a booting model stream's only logs: its labeler re-boots by itself); without
one the server starts a recovery.

**Recovery** (:meth:`StreamState.start_recovery`): an online labeler that has subject templates
(trained from the init frames, or a model file with ``boot = false``) is replaced by a
:class:`~labeler_service.labeling.booting.BootingLabeler` of that model, booted off the frame
path exactly like a model stream's (``boot_due`` / ``boot_request`` / ``boot_job`` /
``boot_done``); points go out unlabeled until their performer is booted. Once every subject of
the model has been labeled for ``HANDBACK_FRAMES`` frames, and every marker of a trained body
in one of them, a plain labeler of the model is started from those frames' labels and takes
over (no booting cost afterwards; a marker not in them it would never label: a forearm the boot
had not placed yet stayed unlabeled for good). Markers still missing are waited for at most
``HANDBACK_WAIT_S`` of stream (a marker fallen off must not keep the booting cost), then named
in the log. A subject that never comes back keeps the stream on the booting labeler, which
boots it when it does. A model
stream with ``boot = false`` whose first frame carries no labels (a live source, ``replay
--init-frames 0``) starts the same way instead of refusing every frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from labeler_service.capture import Capture, is_ghost, split_label, subject_groups
from labeler_service.capture.model import rate_problem
from labeler_service.errors import InitBufferFullError, LabelerError, LimitExceeded, ModelError
from labeler_service.labeling.boot_config import VERIFY_EVENTS
from labeler_service.labeling.booting import BootingLabeler, DropoutHold, JumpWatch, prepare_boot
from labeler_service.labeling.frame import FrameLabeler, LabeledFrame, MarkerState
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import (
    LabelerFactory,
    make_labeler,
    make_window_labeler,
    resolve_labeled_start,
    thin_subjects,
)
from labeler_service.labeling.structure import window_model
from labeler_service.labeling.templates import LabelerModel
from labeler_service.service.background import run_in_process
from labeler_service.service.continuity import ACCEPT, Continuity, Verdict
from labeler_service.service.handover import (
    CATCH_UP_HZ,
    HANDOVER_LEFT_MAX,
    MAX_ROUNDS,
    SLICE_S,
    TAIL_ROUNDS,
    TAIL_S,
    AnyOf,
    Handover,
    catch_up_plan,
)
from labeler_service.service.metrics import RateLimitedLog
from labeler_service.service.protocol import FrameMsg, encode_labeled, encode_model
from labeler_service.service.settings import ServiceSettings, StreamSettings
from labeler_service.service.units import RateCheck, UnitCheck, init_span_warning
from labeler_service.wording import plural

if TYPE_CHECKING:
    from labeler_service.labeling.boot import BootResult
    from labeler_service.labeling.boot_config import BootConfig
    from labeler_service.labeling.booting import BootSnapshot
    from labeler_service.service.boot_worker import BootWorker

log = logging.getLogger(__name__)

#: Frames every subject must have been labeled by a recovery labeler before the stream is
#: handed back to a plain labeler (they are its labeled first frames).
HANDBACK_FRAMES = 4
#: Stream seconds the hand-back waits, every subject labeled, for markers not labeled yet.
HANDBACK_WAIT_S = 2.0
#: a stream's boot and reboot lines for one kind of reason said at most this often (s); this
#: many new runs within it ask about two senders
RUNS_LOG_S = 5.0
RUNS_MANY = 8
#: Sources whose frame counts a stream keeps (``StreamState.busier_than_sender``).
SOURCES_KEPT = 8
#: A second sender takes a sending stream only sending this many times as many frames (two
#: equal senders: the first keeps it; a 120 Hz sender against bursts of 3 every 0.5 s: ~20x).
BUSIER = 2.0
#: Bytes an init frame costs besides its arrays' data (the message object, two array headers),
#: counted against ``max_init_bytes``.
INIT_FRAME_OVERHEAD = 320


#: A gap of dropped frames (``recover_gap_s``) is also longer than this many frame periods: at
#: 2 Hz every frame comes 0.5 s after the last one, and each would start a recovery.
GAP_PERIODS = 3.0


def _natural(s: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s))


def group_by_subject(names: list[str]) -> tuple[str, ...]:
    """Sorts labels by subject then marker (natural order: ``m2`` before ``m10``), so each
    subject's markers are contiguous and the order does not depend on the shuffle."""
    return tuple(
        sorted(
            set(names),
            key=lambda n: (_natural(split_label(n)[0] or ""), _natural(split_label(n)[1])),
        )
    )


def subject_slices(names: tuple[str, ...]) -> tuple[tuple[str, int, int], ...]:
    """``(subject, start, count)`` runs of a subject-grouped marker list (model message); a
    subject whose markers are not contiguous gets one run per stretch."""
    out: list[tuple[str, int, int]] = []
    for subject, cols in subject_groups(names).items():
        start = prev = cols[0]
        for i in cols[1:]:
            if i != prev + 1:
                out.append((subject, start, prev - start + 1))
                start = i
            prev = i
        out.append((subject, start, prev - start + 1))
    return tuple(sorted(out, key=lambda run: run[1]))


@dataclass(slots=True)
class InitWindow:
    """Buffered init frames handed to training: ``frames`` (labels stripped), ``idx`` (per
    frame, int16 (int32 when ``max_markers`` needs it) indices into ``names``, -1 = unlabeled
    point) and ``names`` (first seen first)."""

    frames: list[FrameMsg]
    idx: list[np.ndarray]
    names: list[str]


def rigid_bodies(labeler: FrameLabeler, names: tuple[str, ...]) -> tuple[tuple[int, ...], ...]:
    """The online labeler's rigid bodies as marker indices into ``names`` (the model message's
    optional ``bodies``); ``()`` for the baseline or before the labeler has its templates."""
    from labeler_service.labeling.labeler import Labeler

    if not isinstance(labeler, Labeler | BootingLabeler) or labeler.model is None:
        return ()
    index = {n: i for i, n in enumerate(names)}
    return tuple(
        tuple(index[subj.labels[i]] for i in body)
        for subj in labeler.model.subjects
        for body in subj.bodies
    )


def _reason_key(what: str, why: str) -> str:
    """The rate-limit key of a boot line: its kind of reason, numbers left out (a key per
    "0.30 s of stream dropped" would keep one entry per gap for the stream's life)."""
    return f"{what}-{re.sub(r'[0-9.]+', '#', why)}"


def _off_the_loop(labeler: FrameLabeler) -> bool:
    """A :class:`BootingLabeler` the server drives: its boot and its extension to new markers
    run off the event loop (``inline_boot``/``inline_extend`` off). False for another labeler
    (left as it is)."""
    if not isinstance(labeler, BootingLabeler):
        return False
    labeler.inline_boot = False
    labeler.inline_extend = False
    return True


@dataclass(slots=True)
class BootRequest:
    """One boot attempt in flight: the labeler it belongs to and its snapshot."""

    labeler: BootingLabeler
    snapshot: BootSnapshot
    #: runs the boot step in a worker process (None: in the job's thread)
    worker: BootWorker | None = None


@dataclass(slots=True)
class BootOutcome:
    """What a boot job returns: the boot's result, its wall time and the thread it ran in
    (``worker``: its step ran in the boot worker process), and the frames the catch-up
    labeled."""

    result: BootResult
    seconds: float
    thread: str
    worker: bool = False
    caught_frames: int = 0


@dataclass(slots=True)
class BootRecord:
    """One finished attempt (:attr:`StreamState.boots`), recorded when installed: ``booted``
    subjects (empty: nothing found), ``failed`` (abandoned over budget or raised), the job's
    thread and wall time."""

    boot: bool  # an attempt to boot subjects (False: an extension of booted ones only)
    t: float  # the snapshot's (labeler) time
    #: the (labeler) time of the first frame labeled with it (installed in that frame, or
    #: just before it: :meth:`StreamState.install_pending`; NaN until that frame)
    installed_t: float
    booted: tuple[str, ...]
    failed: bool
    thread: str
    seconds: float
    worker: bool = False  # its step ran in the boot worker process
    caught_frames: int = 0  # frames the catch-up labeled (0: installed along the tracks)


@dataclass(slots=True)
class Output:
    """What processing one frame produced: the encoded labeled message and its counts."""

    payload: bytes
    label_s: float
    latency_s: float | None
    observed: int
    recovered: int
    missing: int
    unlabeled: int
    #: markers the health counts: those of the subjects a booting labeler has booted (a model
    #: may list performers who are not in the volume), every marker otherwise or before the
    #: first boot; 0 = all
    scope: int = 0


class StreamState:
    """Everything one stream owns. Not thread-safe: one worker task per stream (the training
    job, :meth:`train`, reads only what it is given)."""

    def __init__(
        self,
        name: str,
        settings: ServiceSettings,
        stream_settings: StreamSettings | None = None,
        factory: LabelerFactory = make_labeler,
    ) -> None:
        self.name = name
        self.settings = settings
        self.configured = stream_settings is not None
        self.stream_settings = stream_settings or StreamSettings(name=name)
        self._factory = factory
        self.labeler: FrameLabeler | None = None
        self.names: tuple[str, ...] = ()
        self._index: dict[str, int] = {}
        self.rate: float | None = self.stream_settings.rate
        self.model_id = 0
        self.model_payload: bytes | None = None
        self.bodies: tuple[tuple[int, ...], ...] = ()  # model message (live view)
        self._health_alpha = 1.0  # per-frame weight of the health averages (set by _install)
        self.continuity = Continuity(
            max_seq_step=settings.max_seq_step,
            max_time_step_s=settings.max_time_step_s,
            confirm=settings.run_confirm_frames,
        )
        #: buffered init frames (their ``labels`` moved into ``_init_idx``, compactly)
        self.init_frames: list[FrameMsg] = []
        self._init_idx: list[np.ndarray] = []  # per frame: int16/int32 index into _init_labels
        self._init_bytes = 0
        self._init_labels: dict[str, int] = {}  # label -> buffer index, first seen first
        self._init_subjects: dict[str, int] = {}  # subject -> distinct markers in the buffer
        self._t_offset = 0.0  # added to t before the labeler sees it (re-based runs)
        self._t_last: float | None = None  # last (re-based) t given to the labeler
        #: the last (re-based) t of a frame with a point given to this labeler (a blackout)
        self._t_points: float | None = None
        self._rebase = False  # re-base time at the next frame (the run's t jumped)
        self.runs = 1
        self.last_activity = time.monotonic()
        #: evidence that a real client feeds the stream (slot eviction, server): consecutive
        #: frames accepted by the restart rule (next seq, plausible t); 0 after a dropped frame
        self.progress = 0
        #: who took the stream's slot (UDP: the sender address; else the transport's name)
        self.source: object = None
        self.training = False  # a training job for this stream is running (server)
        #: the labeled start through a window model (``labeled_start``, :meth:`_labeler_for`):
        #: the init frames its model was trained on; None for any other start. A recovery
        #: boots from that model and hands back to such a labeler.
        self.window_frames: int | None = None
        #: the window start in progress (:mod:`~labeler_service.service.handover`): the plain
        #: labeler labels while the window labeler trains off the loop; None otherwise
        self.handover: Handover | None = None
        self.handovers = 0  # window labelers that took over from the plain labeler
        self.handovers_abandoned = 0  # handovers given up (new run, recovery, failure)
        #: the handover trains its window model in a child process (``window_worker``)
        self.window_in_process = False
        # health
        self.status = "online"
        #: the stream has labeled: a subject of its booting labeler was booted, or a labeler
        #: that does not boot gave an output (until then the status reads ``booting``, not
        #: ``lost``: nothing is wrong yet; a recovery boot after a loss still reads ``lost``)
        self._booted_once = False
        #: monotonic time of the first of the frames that failed in a row (server); None
        self.failing_since: float | None = None
        #: who sent the last accepted frame (UDP: its address; MQTT: the transport)
        self.sender: object = None
        #: when the sender's last frame was accepted (monotonic s): a frame from another
        #: sender while this one is quiet is a sender's restart, not a second sender
        self.sender_at = 0.0
        #: wall seconds between the last accepted frames (the silence rule's "usual gap")
        self.arrival_gaps: deque[float] = deque(maxlen=9)
        #: per source: (frames arriving, decayed over ``silent_after_s``; monotonic s of the
        #: last), the few busiest kept (:meth:`busier_than_sender`)
        self.source_rate: dict[object, tuple[float, float]] = {}
        #: monotonic time of the first of the frames in a row that arrive and continue nothing
        #: (dropped by the continuity rule, server ``_stalled``), None while frames are accepted
        self.stalled_since: float | None = None
        self.stalled_last = 0.0  # monotonic time of the last of those frames
        self.labeled_fraction = float("nan")
        self.recovered_fraction = float("nan")
        #: Called (by the server) when the status turns ``lost``: the hook for boot from a
        #: subject model. ``None``: the labeler's own re-acquisition is the only recovery.
        self.on_lost: Callable[[StreamState], None] | None = None
        # boot (model streams, see the module docstring)
        self.boot_inflight = False  # a boot job runs or waits to be installed
        #: the boot job out (None: none): a labeler replaced meanwhile keeps the stream's one
        #: job in flight until it returns (its result discarded), so the new labeler's first
        #: attempt is not queued behind a stale one (:meth:`boot_done`)
        self._boot_request: BootRequest | None = None
        self._labels_seen = False  # a labeled frame reached the current labeler (_install)
        self._warned_unknown = False
        #: the stream's model file as read at its first start (``start_from_model``)
        self._model_file: LabelerModel | None = None
        #: a model stream's next booting labeler, built unused at its start
        #: (:meth:`start_from_model`) and again after each one is taken (:meth:`build_spare`,
        #: off the loop), taken by the next recovery (``boot = false``) or reboot (``boot =
        #: true``); ``_spare_for``: the model it is built for
        self._spare: BootingLabeler | None = None
        self._spare_for: LabelerModel | None = None
        self.spare_building = False  # a build_spare job is out (the server's)
        #: points in another unit than the model's (metres): warned by the server
        self.units = UnitCheck()
        self.rate_check = RateCheck()
        #: the server's boot worker process (None: the step runs in the job's thread)
        self.boot_worker: BootWorker | None = None
        self._boot_result: tuple[BootRequest, BootOutcome | None] | None = None
        #: finished attempts, newest last (bounded)
        self.boots: deque[BootRecord] = deque(maxlen=256)
        #: installed between frames (install_pending): its installed_t is the next frame's
        self._installed_before: BootRecord | None = None
        self.just_booted: tuple[str, ...] = ()  # subjects installed by the last process()
        #: the last process()'s re-verification and drop events of the booting labeler:
        #: (kind, subject), kind "withdraw" (markers' labels withdrawn), "reject" (dropped by
        #: the re-verification), "drop" (vanished), "jump" (the scene jumped past its
        #: tracks) or "blackout" (points back after blackout_reboot_s without any); each such
        #: subject is booted again
        self.verify_events: tuple[tuple[str, str], ...] = ()
        # recovery by boot (see "Recovery" in the module docstring)
        #: the labeler is a recovery BootingLabeler, handed back to a plain one once every
        #: subject of the model is labeled again
        self.recovering = False
        self.recoveries = 0  # recoveries started (lost, or a new run after a long gap)
        self.handbacks = 0  # recoveries that ended with every subject labeled again
        self.reboots = 0  # booting labelers started afresh (a new run after a time jump)
        #: the recovery labeler's last frames (points, t, labels) while it labels every subject
        self._handback: deque[tuple[np.ndarray, float, np.ndarray]] = deque(maxlen=HANDBACK_FRAMES)
        #: the plain online labeler's last frames (points, t, labels) and, per subject, the frame
        #: time it last had a marker observed (NaN: not yet): :meth:`_watch_subjects`
        self._recent: deque[tuple[np.ndarray, float, np.ndarray]] = deque(maxlen=HANDBACK_FRAMES)
        self._seen_t: np.ndarray | None = None
        #: the plain labeler's watch: the last frame's time, and the first of a run of frames
        #: with no point at all (a dropout: nobody leaves in it, ``blackout_hold_s``)
        self._watch_t: float | None = None
        self._dropout = DropoutHold()
        #: stream time since which every subject is labeled but markers are missing (the
        #: hand-back waits for them, at most ``HANDBACK_WAIT_S``); None otherwise
        self._handback_since: float | None = None
        #: the hand-back's "stays until" line, once per wait (a subject that flickers restarts
        #: the wait, not the line)
        self._handback_log = RateLimitedLog(log, period=HANDBACK_WAIT_S)
        #: a boot or reboot for one reason said at most once per ``RUNS_LOG_S`` (two senders on one
        #: MQTT stream start a new run every few frames: 36 such lines a second, a helper's run;
        #: a different reason is said at once: a recovery after a reboot is news)
        self._runs_log = RateLimitedLog(log, period=RUNS_LOG_S)
        self._run_times: deque[float] = deque(maxlen=RUNS_MANY)  # (monotonic) of new runs
        #: (model, its markers in a trained body) of the last hand-back check
        self._body_mask: tuple[object, np.ndarray] = (None, np.zeros(0, dtype=bool))

    @property
    def last_seq(self) -> int | None:
        return self.continuity.last_seq

    def check_frame(self, f: FrameMsg) -> Verdict:
        """The restart rule's verdict for an arriving frame (updates the run tracking and
        :attr:`progress`)."""
        self.last_activity = time.monotonic()
        verdict = self.continuity.check(f.seq, f.t)
        if verdict.reason is not None:
            self.progress = 0  # a dropped frame (duplicate, late, suspect jump): no evidence
        elif verdict.new_run or verdict.gap:
            self.progress = 1  # a new run or a gap starts over
        else:
            self.progress += 1
        return verdict

    def busier_than_sender(self, source: object, now: float, tau: float) -> bool:
        """Counts a frame of ``source`` (arrival time ``now``; counts decay with time constant
        ``tau``) and tells whether ``source`` now sends ``BUSIER`` times as many frames as the
        stream's sender: a second sender's frames go to the restart rule only then (or once
        the sender is quiet). A burst sender that got the stream first must not keep a steady
        sender out, and a steady sender must not lose the stream to bursts."""

        def count(src: object) -> float:
            n, t = self.source_rate.get(src, (0.0, now))
            return n * math.exp(-(now - t) / tau)

        self.source_rate[source] = (count(source) + 1.0, now)
        if len(self.source_rate) > SOURCES_KEPT:  # (spoofed sources: the quietest forgotten)
            del self.source_rate[min(self.source_rate, key=count)]
        return count(source) > BUSIER * count(self.sender)

    def needs_training(self, f: FrameMsg) -> bool:
        """True when labeling ``f`` trains the labeler (first unlabeled frame after the init
        frames): the server runs :meth:`train` off the event loop."""
        return self.labeler is None and f.labels is None and bool(self.init_frames)

    # --------------------------------------------------------------------- start-up
    @property
    def started(self) -> bool:
        return self.labeler is not None

    def start_from_model(self, spare: bool = True, model: LabelerModel | None = None) -> None:
        """Builds the labeler from the stream's model file (mode 1); with ``spare`` (not on
        the frame path) also the spare booting labeler an online stream's recovery (``boot =
        false``) or reboot (``boot = true``) will take. ``model``: the file as the service's
        start already read it (it checks every stream's model before it binds a port).

        The file is read once, at the stream's first start; a new labeled run rebuilds from
        that model. It used to be read again at every new run: a model file replaced, deleted
        or half-written while the service ran broke the stream at its next run (one
        ``labeler_error``, then every frame published unlabeled until a restart), and a file
        replaced by another marker set's model switched the stream's markers mid-session.
        Replacing the model takes a restart of the service."""
        path = self.stream_settings.model
        if path is None:
            raise ModelError(f"stream {self.name}: no model file configured")
        if self._model_file is None:
            from labeler_service.labeling.templates import load_model, same_templates

            self._model_file = model if model is not None else load_model(path)
            for a, b in same_templates(self._model_file):
                log.warning("stream %s: subjects %s and %s of %s have one template: a boot "
                            "cannot tell them apart (each keeps its name only by continuity; "
                            "which is which at the first boot is arbitrary)", self.name, a, b,
                            path)  # fmt: skip
            if self.stream_settings.labeled_start == "auto":
                log.info("stream %s: starts from its model file %s (labeled_start = 'auto' "
                         "trains a window model only for a stream without one)", self.name,
                         path)  # fmt: skip
        model = self._model_file
        rate = self.stream_settings.rate
        if rate is None:
            rate = model.rate
        boot = self.settings.boot and self.settings.labeler == "online"
        cfg = self.settings.labeler_config
        labeler: FrameLabeler | None = None
        if boot:  # (a new labeled run, in the frame: the spare built off the loop)
            labeler = self._take_spare(model, rate, self.settings.boot_config)
        if labeler is None:
            labeler = self._factory(self.settings.labeler, rate=rate, config=cfg, model=model,
                                    boot=self.settings.boot_config if boot else False)  # fmt: skip
        _off_the_loop(labeler)
        if self.settings.labeler == "online":
            # boot = false: the first unlabeled frame (or a performer who leaves) starts a
            # recovery, a BootingLabeler of this model; built in that frame it took 0.1 s for
            # two walkers, 0.4-1 s for ten hugging performers (its boot's preparation, then
            # 0.06-0.1 s for the rest). boot = true: a new run after a time jump (a restarted
            # sender) boots every subject again with a fresh one (reboot), built in that
            # frame in 16-27 ms at ten performers. Built here, at the stream's start and off
            # the loop, and again by the server after each one is taken (spare_due)
            self._spare_for = model
        self.boot_inflight = self._boot_request is not None
        self._boot_result = None
        self._install(labeler, rate)
        if spare:
            self.build_spare()

    def _install(self, labeler: FrameLabeler, rate: float) -> None:
        self.abandon_handover("another labeler was installed")
        self.labeler = labeler
        self._labels_seen = False  # a labeled frame reached this labeler
        self._warned_unknown = False  # labels naming no marker of the stream were logged
        self.recovering = False
        self._handback.clear()
        self.labeled_fraction = self.recovered_fraction = float("nan")
        self.names = tuple(labeler.marker_names)
        self._index = {n: i for i, n in enumerate(self.names)}
        self.rate = float(rate)
        self._health_alpha = min(1.0, 1.0 / max(1.0, self.rate * self.settings.health_window_s))
        self.model_id += 1
        subjects = subject_slices(self.names)
        groups = subject_groups(self.names)
        #: (subject names, each marker's subject index): :meth:`_watch_subjects`
        self._subject_of = (list(groups), np.zeros(len(self.names), dtype=np.int64))
        for k, cols in enumerate(groups.values()):
            self._subject_of[1][cols] = k
        self._seen_t = None
        self._jump: JumpWatch | None = None  # (the plain labeler's: _jumped)
        self.bodies = rigid_bodies(labeler, self.names)
        self.model_payload = self._encode_model()
        self.window_frames = labeler.window_frames if isinstance(labeler, BootingLabeler) else None
        window = self.window_frames is not None
        log.info(
            "stream %s: labeler ready (%s, %s, %.1f Hz%s)",
            self.name,
            plural(len(self.names), "marker"),
            plural(len(subjects), "subject"),
            self.rate,
            ", labeled start through the init window's model" if window else "",
        )

    def _encode_model(self) -> bytes:
        assert self.rate is not None
        return encode_model(self.name, self.model_id, self.names, subject_slices(self.names),
                            self.rate, bodies=self.bodies or None)  # fmt: skip

    def _estimate_rate(self, init: list[FrameMsg]) -> float:
        if self.stream_settings.rate is not None:
            return self.stream_settings.rate
        seqs = np.array([f.seq for f in init], dtype=np.float64)
        order = np.argsort(seqs, kind="stable")
        seqs = seqs[order]
        t = np.array([f.t for f in init], dtype=np.float64)[order]
        # the slope of t over seq between frames half the window apart (their median): a
        # jittered clock's steps (each frame's own, 139 Hz read for 120 Hz at 3 ms) and gaps
        # average out, and a seq that counts by 2 (every other capture frame number) is
        # counted in its own step (the median step per seq read twice the rate)
        ds = np.diff(seqs)
        stride = float(ds[ds > 0].min()) if np.any(ds > 0) else 1.0
        h = max(1, len(t) // 2)
        span = seqs[h:] - seqs[:-h]
        slope = np.divide(t[h:] - t[:-h], span, out=np.zeros_like(span), where=span > 0)
        forward = slope > 0
        if not forward.any():
            raise LabelerError(
                f"stream {self.name}: cannot infer the frame rate from the init frames; set "
                "streams[].rate"
            )
        rate = float(1.0 / (np.median(slope[forward]) * stride))
        why = rate_problem(rate)
        if why is not None:  # (t in milliseconds reads as 0.12 Hz: a labeler at that rate)
            raise LabelerError(
                f"stream {self.name}: the frame rate the init frames' times give {why} (is "
                "t in seconds? it must be); set streams[].rate"
            )
        return rate

    @property
    def t_last(self) -> float | None:
        """The last (re-based) time given to the labeler (kept with a cached labeler)."""
        return self._t_last

    def resume(self, labeler: FrameLabeler, rate: float, t_last: float | None) -> None:
        """Continues with a cached labeler of this stream (it expired and came back): the
        first frame's time is re-based onto the labeler's last one."""
        self._install(labeler, rate)
        self._t_last = t_last
        self._t_points = None
        self._rebase = True

    def _labeler_for(
        self, init: InitWindow, staged: bool = False
    ) -> tuple[FrameLabeler, float, np.ndarray, bool]:
        """A new labeler for the init window's markers (subject-grouped), its rate, the remap
        from the window's label indices to the labeler's markers (``-1`` stays ``-1``), and
        whether a window start was deferred: with ``staged`` the window start's labeler is the
        plain one, the window labeler comes later (:mod:`~labeler_service.service.handover`)."""
        # a *N label is a ghost point (DESIGN.md): it stays unlabeled, never becomes a marker
        names = group_by_subject([n for n in init.names if not is_ghost(n)])
        if not names:
            points = sum(len(f.points) for f in init.frames)
            if init.names:
                hint = " (only ghost *N labels)"
            elif points:
                hint = (
                    f" ({points} points, every label nil: send subject:marker labels on the "
                    "init frames, or start from a model with none)"
                )
            else:
                hint = (
                    " (no points: a take that starts before anyone is in view? start the "
                    "replay where the performers are: replay FILE:start)"
                )
            raise LabelerError(f"stream {self.name}: the init frames hold no labeled point" + hint)
        empty = [n for n in names if split_label(n)[0] == ""]
        if empty:
            raise LabelerError(
                f"stream {self.name}: label {empty[0]!r} has an empty subject name: send "
                "subject:marker or a bare marker name"
            )
        for note in thin_subjects(names, self.settings.labeler_config.presence_min_markers):
            log.warning("stream %s: %s", self.name, note)
        rate = self._estimate_rate(init.frames)
        labeler: FrameLabeler
        start, why = resolve_labeled_start(
            self.stream_settings.labeled_start,
            online=self.settings.labeler == "online",
            init_frames=len(init.frames),
            labels=names,
            source=f"stream {self.name}",
            advice="set labeled_start = 'labeler' on this stream (it accepts bare marker names)",
        )
        if why is not None:
            log.info("stream %s: labeled start: the labeler trained in place (%s)", self.name, why)
        deferred = start == "model" and staged
        if start == "model" and not staged:
            labeler = self._window_labeler(init, names, rate)
            names = tuple(labeler.marker_names)
        else:
            labeler = self._factory(
                self.settings.labeler,
                marker_names=names,
                rate=rate,
                config=self.settings.labeler_config,
            )
        return labeler, rate, _remap(names, init.names), deferred

    def window_model(self, h: Handover, cancel=None):
        """The handover's window model alone, in a ``spawn`` child process
        (``window_worker = "process"``); the server runs it before the handover's first job,
        outside the ``Background`` slot: the child holds none of this process's GIL, and a
        second stream's training waited the whole window model behind it (hostile run: 0.7 s
        of a 120 Hz stream's start at 62 markers x 1000 init frames). ``cancel``: stops and
        terminates the child (the handover's abandonment stops it too)."""
        assert h.init is not None
        return self._train_window(h.init, h.names, h.rate, AnyOf(cancel, h.cancel), True)

    def _train_window(
        self, init: InitWindow, names: tuple[str, ...], rate: float, cancel=None,
        in_process: bool = False,
    ) -> LabelerModel:  # fmt: skip
        """The subject templates of the init window's frames (as a capture, ``train
        structure``'s trainer): in a ``spawn`` child with ``in_process`` (``cancel`` stops and
        terminates it; its Python holds the child's GIL, not the frame path's: ~1-2 s at 10
        people, labeling p99 0.6-1.9 -> 12-17 ms beside it in a thread, loaded machine), else
        here."""
        column = {n: i for i, n in enumerate(names)}
        to_col = np.array([column.get(n, -1) for n in init.names] + [-1], dtype=np.int64)
        pos = np.full((len(init.frames), len(names), 3), np.nan, dtype=np.float32)
        for k, (f, idx) in enumerate(zip(init.frames, init.idx, strict=True)):
            c = to_col[idx]  # -1 (unlabeled) picks the last entry, -1
            pos[k, c[c >= 0]] = f.points[c >= 0]
        window = Capture(pos, names, rate, source=f"stream {self.name} init window")
        if not in_process:
            return window_model(window)
        return run_in_process(window_model, window, cancel=cancel,
                              name=f"window-model-{self.name}")  # fmt: skip

    def _window_labeler(
        self, init: InitWindow, names: tuple[str, ...], rate: float, cancel=None, model=None
    ) -> FrameLabeler:
        """``labeled_start = "model"``: subject templates trained on the init window (its
        frames as a capture, ``train structure``'s trainer), and the booting labeler from them
        (:func:`~labeler_service.labeling.registry.make_window_labeler`), its boot kernels
        compiled here (off the event loop) when the service warms up."""
        if model is None:  # (else trained already: StreamState.window_model)
            model = self._train_window(init, names, rate, cancel, self.window_in_process)
        labeler = make_window_labeler(
            model,
            rate=rate,
            window_frames=len(init.frames),
            config=self.settings.labeler_config,
            relearn_every_s=self.stream_settings.relearn_every_s,
        )
        if self.settings.warmup:
            labeler.warmup()
        return labeler

    def train(
        self, init: InitWindow, first: FrameMsg, cancel=None
    ) -> tuple[FrameLabeler, float, LabeledFrame, int]:
        """The training job (runs off the event loop): a labeler built from the init frames
        ``init`` and fed them, then the first unlabeled frame ``first`` (which trains it).
        Returns ``(labeler, rate, labeled first frame, labeling ns)``; touches no state, so an
        abandoned job leaves the stream as it was. ``cancel`` (an Event) stops it between
        frames."""
        labeler, rate, out, label_ns, _ = self._train(init, first, cancel, staged=False)
        return labeler, rate, out, label_ns

    def train_staged(
        self, init: InitWindow, first: FrameMsg, cancel=None
    ) -> tuple[FrameLabeler, float, LabeledFrame, int, Handover | None]:
        """The server's training job: as :meth:`train`, but a window start trains the plain
        labeler (the ``labeler`` start's short stall) and returns with it the
        :class:`Handover` that trains the window labeler off the loop afterwards
        (:meth:`handover_job`); None for any other start."""
        return self._train(init, first, cancel, staged=True)

    def _train(
        self, init: InitWindow, first: FrameMsg, cancel, staged: bool
    ) -> tuple[FrameLabeler, float, LabeledFrame, int, Handover | None]:
        units = init_span_warning(self.name, [f.points for f in init.frames], init.idx,
                                  init.names)  # fmt: skip
        if units is not None:
            log.warning("%s", units)
        labeler, rate, remap, deferred = self._labeler_for(init, staged)
        for f, idx in zip(init.frames, init.idx, strict=True):
            if cancel is not None and cancel.is_set():
                raise LabelerError(f"stream {self.name}: training cancelled")
            labeler.process(f.points, f.t, remap[idx])  # -1 stays -1 (remap's last entry)
        t0 = time.perf_counter_ns()
        out = labeler.process(first.points, first.t, None)
        _off_the_loop(labeler)  # (labeled_start = "model": from now on, as a model stream's)
        label_ns = time.perf_counter_ns() - t0
        model = getattr(labeler, "model", None)
        if self.settings.labeler == "online" and model is not None:
            # a recovery builds a BootingLabeler of this model on the frame path: its boot is
            # prepared here, off the loop (1,000 markers: 2.8 s during which every stream of
            # the service waited; 30-90 ms for a take of one or two performers)
            prepare_boot(model, self.settings.boot_config, rate)
        handover = None
        if deferred:
            handover = Handover(init, tuple(labeler.marker_names), rate)
            # the first frame is the first one the window labeler catches up on
            handover.record(first.points, first.t)
        return labeler, rate, out, label_ns, handover

    def take_init(self) -> InitWindow:
        """Hands the buffered init frames to a training job and empties the buffer."""
        init = InitWindow(self.init_frames, self._init_idx, list(self._init_labels))
        self.init_frames, self._init_idx = [], []
        self._init_bytes = 0
        self._init_labels = {}
        self._init_subjects = {}
        return init

    def install_trained(
        self, labeler: FrameLabeler, rate: float, first: FrameMsg, out: LabeledFrame,
        recv_ns: int, label_ns: int, handover: Handover | None = None,
    ) -> Output:  # fmt: skip
        """Installs a labeler from :meth:`train` (or :meth:`train_staged`, with its
        ``handover``) and encodes its first labeled frame."""
        self._install(labeler, rate)
        self._t_offset = 0.0
        self._t_last = first.t
        self._t_points = None
        if handover is not None:
            handover.plain = labeler
            self.handover = handover
            log.info("stream %s: labeling with the labeler trained in place while the init "
                     "window's model trains off the frame path", self.name)  # fmt: skip
        return self.encode(first, out, recv_ns, label_ns)

    # --------------------------------------------------------------------- handover
    def handover_due(self) -> bool:
        """Cheap: True when the handover needs a job (the first, or another catch-up round
        because the last one left too many frames)."""
        h = self.handover
        return (
            h is not None
            and not h.inflight
            and (h.labeler is None or h.again)
            and not (h.ready or h.abandoned)
        )

    def handover_job(self, h: Handover, cancel: threading.Event | None = None) -> int:
        """The heavy part of the handover (runs off the event loop; touches no stream state,
        only ``h``): the first time, the window model trained on the init window and the
        window labeler built from it and fed the window with its labels (as :meth:`train`);
        then the catch-up on the frames the plain labeler labeled since (module docstring of
        :mod:`~labeler_service.service.handover`). Returns the frames fed; raises
        :class:`LabelerError` when abandoned or behind the record."""

        def check() -> None:
            if h.abandoned or (cancel is not None and cancel.is_set()):
                raise LabelerError(f"stream {self.name}: handover abandoned")

        if h.labeler is None:
            assert h.init is not None
            lab = self._window_labeler(h.init, h.names, h.rate, AnyOf(cancel, h.cancel), h.model)
            remap = _remap(lab.marker_names, h.init.names)
            for f, idx in zip(h.init.frames, h.init.idx, strict=True):
                check()
                lab.process(f.points, f.t, remap[idx])
            h.init = h.model = None  # (its frames are the model's now)
            h.labeler = lab
        lab = h.labeler
        h.more = False
        until = time.perf_counter() + SLICE_S
        stride = max(1, int(h.rate // CATCH_UP_HZ))
        tail = max(2, int(round(TAIL_S * h.rate)))
        fed = rounds = 0
        waited = False
        while rounds < MAX_ROUNDS:
            check()
            pending = h.pending()
            if pending is None:
                raise LabelerError(
                    f"stream {self.name}: the window labeler fell more than the recorded "
                    "frames behind the stream; handover abandoned"
                )
            if not pending:
                # wait (two frame periods at most) for the next frame and label it too, so
                # the result arrives just after a frame and the swap rarely finds one left
                if waited or not h.wait_for_frame(2.0 / h.rate):
                    break
                waited = True
                continue
            plan = catch_up_plan(len(pending), stride, tail if rounds < TAIL_ROUNDS else 0)
            for i in plan:
                check()
                p, t = pending[i]
                lab.process(p, t, None)
            fed += len(plan)
            h.done += len(pending)
            rounds += 1
            if time.perf_counter() > until and h.received - h.done > HANDOVER_LEFT_MAX:
                h.more = True  # the slot goes to other jobs; the server runs the next slice
                break
        _off_the_loop(lab)  # from now on boot and extension are the server's (frame thread)
        h.rounds += 1
        return fed

    def handover_done(self, h: Handover, ok: bool, why: str = "") -> None:
        """Hands a finished job to the next :meth:`process` (``ok``) or abandons the handover
        (a failure or over budget: the plain labeler stays)."""
        h.inflight = False
        if h is not self.handover:
            return
        if ok:
            h.ready = True
        else:
            self.abandon_handover(why or "its job failed")

    def abandon_handover(self, why: str) -> None:
        """Gives the handover up (the plain labeler stays); its job stops at its next frame."""
        h, self.handover = self.handover, None
        if h is None:
            return
        h.cancel.set()
        self.handovers_abandoned += 1
        log.info("stream %s: the window start's handover abandoned (%s); the labeler trained "
                 "in place stays", self.name, why)  # fmt: skip

    def _install_handover(self) -> None:
        """At a frame boundary (before the frame is labeled): the window labeler is fed the
        frames recorded since its job ended and replaces the plain labeler; with more than
        ``HANDOVER_LEFT_MAX`` left it goes back for another round off the loop."""
        h = self.handover
        assert h is not None and h.ready
        h.ready = False
        if self.labeler is not h.plain or h.labeler is None:
            self.abandon_handover("the stream's labeler changed")
            return
        pending = h.pending()
        if pending is None:
            self.abandon_handover("the window labeler fell behind the recorded frames")
            return
        if len(pending) > HANDOVER_LEFT_MAX:
            h.again = True
            return
        lab = h.labeler
        for p, t in pending:
            lab.process(p, t, None)
        self.handover = None
        self.window_frames = lab.window_frames if isinstance(lab, BootingLabeler) else None
        self._boot_result = None
        self.boot_inflight = self._boot_request is not None
        self._handback.clear()
        self.recovering = False
        self.labeler = lab
        if tuple(lab.marker_names) != self.names:  # (the window model's order differs)
            self.names = tuple(lab.marker_names)
            self._index = {n: i for i, n in enumerate(self.names)}
        self.bodies = rigid_bodies(lab, self.names)
        self.model_id += 1  # the window model's bodies (and marker order) for the view
        self.model_payload = self._encode_model()
        self.handovers += 1
        log.info("stream %s: the init window's model took over from the labeler trained in "
                 "place (%d catch-up rounds, %d frames at the swap)", self.name, h.rounds,
                 len(pending))  # fmt: skip

    def _label_indices(self, f: FrameMsg) -> np.ndarray | None:
        """The frame's labels as indices into the stream's marker names; ``None`` when it
        carries none or none of them names a marker of the stream (a replay of another
        take, subjects named otherwise than in the model): such a frame is labeled as an
        unlabeled one. Labels the stream does not know are logged once per labeler."""
        idx = _indices(self._index, f.labels)
        if idx is None or f.labels is None:
            return idx
        unknown = [
            x for x, i in zip(f.labels, idx.tolist(), strict=True) if x is not None and i < 0
        ]
        if unknown and not self._warned_unknown:
            self._warned_unknown = True
            known = int((idx >= 0).sum())
            subjects = ", ".join(subject_groups(list(self.names))) or "none"
            log.warning(
                "stream %s: %s of a frame %s no marker of the stream (e.g. %r; its "
                "subjects: %s): %s; send labels named as the stream's markers are (e.g. %r), "
                "or give the stream a model of these performers (train structure)",
                self.name, plural(len(unknown), "label"),
                "names" if len(unknown) == 1 else "name", unknown[0], subjects,
                f"ignored, {plural(known, 'label')} used" if known
                else "the frame is labeled as an unlabeled one",
                self.names[0] if self.names else "subject:marker",
            )  # fmt: skip
        return idx if (idx >= 0).any() else None

    def buffer_init(self, f: FrameMsg) -> None:
        """Buffers one labeled init frame (points as they are, labels as int16 indices into
        the stream's label list); raises :class:`InitBufferFullError` (frames or bytes cap) or
        :class:`LimitExceeded` (``marker_cap``) without buffering it."""
        s = self.settings
        labels = f.labels or ()
        if len(self.init_frames) >= s.max_init_frames:
            raise InitBufferFullError(
                f"stream {self.name}: init buffer full ({s.max_init_frames} frames)"
            )
        known = self._init_labels
        new = {x: None for x in labels if x is not None and x not in known}
        # int16 label indices while max_markers allows (half of int32); the frame's Python
        # objects (message, two array headers) count too, so tiny frames are not undercounted
        itype = np.int16 if s.max_markers < 2**15 else np.int32
        nbytes = (
            f.points.nbytes
            + np.dtype(itype).itemsize * len(labels)
            + INIT_FRAME_OVERHEAD
            + sum(len(x) + 64 for x in new)
        )
        if self._init_bytes + nbytes > s.max_init_bytes:
            raise InitBufferFullError(
                f"stream {self.name}: init buffer full ({s.max_init_bytes} bytes, max_init_bytes)"
            )
        if len(known) + len(new) > s.max_markers:
            raise LimitExceeded(
                f"stream {self.name}: init frames name more than max_markers = {s.max_markers} "
                "distinct markers; frame dropped",
                "marker_cap",
            )
        per = self._init_subjects
        grow: dict[str, int] = {}
        for x in new:
            subj = split_label(x)[0] or ""
            grow[subj] = grow.get(subj, 0) + 1
        for subj, n in grow.items():
            if per.get(subj, 0) + n > s.max_markers_per_subject:
                raise LimitExceeded(
                    f"stream {self.name}: init frames name more than max_markers_per_subject = "
                    f"{s.max_markers_per_subject} markers of subject {subj!r}; frame dropped",
                    "marker_cap",
                )
        for subj, n in grow.items():
            per[subj] = per.get(subj, 0) + n
        for x in new:
            known[x] = len(known)
        # -1 (unknown point) indexes the remap table's last entry, which is -1 too
        idx = np.fromiter((known[x] if x is not None else -1 for x in labels), itype,
                          count=len(labels))  # fmt: skip
        self._init_bytes += nbytes
        self.init_frames.append(dataclasses.replace(f, labels=None))
        self._init_idx.append(idx)

    def release(self) -> None:
        """Drops what the stream holds (init buffer, labeler, boot state) when it is removed:
        references to the state that outlive it (a cancelled worker's frame, an abandoned job)
        then hold nothing large."""
        self.take_init()
        self.abandon_handover("the stream was removed")
        self.labeler = None
        self._boot_result = None
        self._handback.clear()
        self.boots.clear()

    def new_run(self, f: FrameMsg, verdict: Verdict) -> None:
        """Applies a new run (see the module docstring) before ``f`` is processed."""
        self.runs += 1
        now = time.monotonic()
        self._run_times.append(now)
        if len(self._run_times) == RUNS_MANY and now - self._run_times[0] < RUNS_LOG_S:
            self._runs_log.warning(
                "many-runs", "stream %s: %d new runs in %.1f s: are two senders sending to "
                "this stream (over MQTT the service cannot tell them apart)? Give each sender "
                "its own stream name", self.name, RUNS_MANY, now - self._run_times[0])  # fmt: skip
        self.units.new_run()
        self.abandon_handover(f"new run {self.runs}")
        if f.labels is not None:
            log.info("stream %s: new run %d with labeled init frames: retraining", self.name,
                     self.runs)  # fmt: skip
            self.take_init()
            self.recovering = False
            self._t_offset = 0.0
            self._t_last = None
            self._t_points = None
            if self.stream_settings.model is not None:
                self.start_from_model(spare=False)  # (the frame path: prepared at the start)
            else:
                self.labeler = None
            return
        if verdict.time_jumped:
            self._rebase = True
            # a gap of unknown length: the performers may be anywhere, the tracks cannot be
            # trusted; boot them from the stream's model (its own trained templates)
            if self.start_recovery("new run after a time jump"):
                return
            if self.reboot("new run after a time jump"):
                return
        log.info("stream %s: new run %d without labels: continuing from the current model",
                 self.name, self.runs)  # fmt: skip

    # --------------------------------------------------------------------- recovery
    def recovery_model(self) -> LabelerModel | None:
        """The subject model a recovery boots from: the online labeler's templates (trained
        from the init frames, the window start's window model, or the model file of a stream
        that does not boot); None for the baseline, a labeler without templates yet, or one
        that boots from a model file already."""
        lab = self.labeler
        if lab is None or self.settings.labeler != "online":
            return None
        if self.booting is not None:
            # the window start's labeler boots already, but only the subjects it drops: a
            # recovery boots every subject from its window model (not while recovering; not
            # from a relearned model: prepared for the recovery's settings on the frame path,
            # 0.1 s for two walkers, seconds for a large model, where the window model's
            # preparation was made off it)
            return lab.model if self.window_frames is not None and not self.recovering else None
        return lab.model

    def _waits_for_labels(self) -> bool:
        """The plain online labeler of a model stream that has not had its first labeled
        frame yet (``boot = false``): an unlabeled frame would be refused."""
        lab = self.labeler
        return (
            isinstance(lab, Labeler)
            and not lab.trained
            and not self._labels_seen
            and self.settings.labeler == "online"
        )

    def _dropped_gap(self, t: float) -> float:
        """Seconds from the last frame labeled to frame time ``t`` when more than
        ``recover_gap_s`` and more than ``GAP_PERIODS`` frame periods (a slow sender's frames
        are not a gap), and no recovery runs already; else 0."""
        gap_s = self.settings.recover_gap_s
        if gap_s <= 0 or self._t_last is None or self.recovering:
            return 0.0
        if self.rate:
            gap_s = max(gap_s, GAP_PERIODS / self.rate)
        gap = t - self._t_last
        return gap if gap > gap_s else 0.0

    def _blackout_gap(self, t: float, n_points: int) -> float:
        """Seconds from the last frame with a point to frame time ``t`` when this frame has
        points again after more than ``recover_gap_s`` (and ``GAP_PERIODS`` frame periods) of
        frames with none, and no recovery runs already; else 0. Shorter dropouts are held
        (the booting labeler's ``blackout_hold_s``)."""
        last = self._t_points
        if n_points:
            self._t_points = t
        gap_s = self.settings.recover_gap_s
        if not n_points or last is None or gap_s <= 0 or self.recovering:
            return 0.0
        if self.rate:
            gap_s = max(gap_s, GAP_PERIODS / self.rate)
        gap = t - last
        return gap if gap > gap_s else 0.0

    def start_recovery(self, why: str, keep: list | None = None) -> bool:
        """Replaces the labeler by a :class:`BootingLabeler` of its own model (boot off the
        frame path, driven by the server like a model stream's boot); False when there is no
        model to boot from (the labeler's own re-acquisition is then the only recovery).
        ``keep``: the last frames ``(points, t, labels)`` of the labeler replaced, given to the
        new one with their labels, so that the subjects labeled in them stay labeled (only the
        others are booted)."""
        model = self.recovery_model()
        if model is None or self.rate is None:
            return False
        self.abandon_handover(f"recovery: {why}")
        lab = self._take_spare(model, self.rate, self.settings.boot_config)
        if lab is None:
            lab = self._recovery_labeler(model, self.rate)
        if lab is None:
            return False
        keep = keep if keep and tuple(lab.marker_names) == self.names else None
        for pts, t, labels in keep or ():
            lab.process(pts, t, labels)
        self._swap(lab)
        self.recovering = True
        self.recoveries += 1
        n = plural(len(model.subjects), "subject")
        what = "whoever is missing (the others keep their labels)" if keep else f"its {n}"
        self._runs_log.warning(_reason_key("recovery", why), "stream %s: %s: booting %s from "
                               "the stream's model (recovery %d)", self.name, why, what,
                               self.recoveries)  # fmt: skip
        return True

    @property
    def spare(self) -> BootingLabeler | None:
        """The spare booting labeler (built off the loop; None when none is ready)."""
        return self._spare

    def spare_due(self) -> bool:
        """A model stream whose spare booting labeler was taken (by a recovery or a reboot):
        the server builds the next one off the loop (:meth:`build_spare`), after a recovery
        once it has handed back (during one, no other can start). Built in the frame, a
        leaver's recovery after a hand-back held it 7-10 ms at two performers, 0.06-0.1 s at
        ten (a review); a reboot 16-27 ms at ten."""
        return (
            self._spare_for is not None
            and self._spare is None
            and not self.spare_building
            and not self.recovering
            and self.rate is not None
        )

    def build_spare(self) -> None:
        """Builds the spare booting labeler when the stream wants one and has none (at its
        start; in a job thread after a recovery's hand-back, a reboot or a labeled new run took
        it: :meth:`spare_due`). Kept only if the stream still wants one of that model and rate
        when it is done."""
        model, rate = self._spare_for, self.rate
        if model is None or rate is None or self._spare is not None:
            return
        lab = self._recovery_labeler(model, rate)
        if lab is None:
            self._spare_for = None  # (a labeler kind that does not boot: never again)
            return
        if self._spare is None and self._spare_for is model and self.rate == rate:
            self._spare = lab

    def _take_spare(
        self, model: LabelerModel, rate: float, boot: BootConfig
    ) -> BootingLabeler | None:
        """The spare booting labeler (built off the loop: :meth:`build_spare`) when it is one
        of ``model``, ``rate`` and ``boot`` settings, else None; taken either way (the server
        builds the next one: :meth:`spare_due`)."""
        lab, self._spare = self._spare, None
        if lab is None or lab.model is not model or lab.rate != rate or lab.boot_config != boot:
            return None
        return lab

    def _recovery_labeler(
        self, model: LabelerModel, rate: float, boot: BootConfig | None = None
    ) -> BootingLabeler | None:
        """A :class:`BootingLabeler` of ``model`` as a recovery or a reboot runs it (boot off
        the frame path; ``boot``: its settings, the service's by default); None when the
        stream's labeler kind does not boot."""
        lab = self._factory(self.settings.labeler, rate=rate, model=model,
                            config=self.settings.labeler_config,
                            boot=boot or self.settings.boot_config)  # fmt: skip
        if not _off_the_loop(lab):
            return None
        assert isinstance(lab, BootingLabeler)
        return lab

    def _watch_subjects(self, pts: np.ndarray, t: float, out: LabeledFrame) -> None:
        """The plain online labeler of a model (``boot = false``, after a recovery's hand-back,
        or trained from the init frames): a subject labeled before that has had no marker
        observed for the boot's ``drop_after_s`` left the volume, and the plain labeler would
        never label him again when he comes back (it re-acquires markers near where they were;
        a helper's replay: a performer of two who left for 1 s was unlabeled for the remaining
        7 s, the stream ``degraded``). Starts a recovery that keeps the others' labels (the
        last frames go to the booting labeler with them), which boots him when he returns and
        hands back once every subject is labeled again."""
        lab = self.labeler
        if (
            self.recovering
            or not isinstance(lab, Labeler)
            or self.settings.labeler != "online"
            or self.rate is None
        ):
            return
        names, subject_of = self._subject_of
        if self._jumped(pts, t, out):
            return
        self._recent.append((pts, t, out.point_labels))
        if self._seen_t is None:
            self._seen_t = np.full(len(names), np.nan)
        prev, self._watch_t = self._watch_t, t
        hold = self.settings.boot_config.blackout_hold_s
        if self._dropout.held(pts.shape[0], t, hold) and prev is not None:
            self._seen_t += max(t - prev, 0.0)  # (a dropout counts toward no one's absence)
            return
        self._seen_t[subject_of[out.state == MarkerState.OBSERVED]] = t
        gone = np.flatnonzero(t - self._seen_t > self.settings.boot_config.drop_after_s)
        if gone.size == 0:
            return
        who = ", ".join(names[int(k)] for k in gone)
        keep = list(self._recent)
        self._seen_t = None
        self._recent.clear()
        drop = self.settings.boot_config.drop_after_s
        self.start_recovery(f"{who}: no marker seen for {drop:g} s", keep)

    def _jumped(self, pts: np.ndarray, t: float, out: LabeledFrame) -> bool:
        """The plain labeler's frame after a jump of the whole scene
        (:class:`~labeler_service.labeling.booting.JumpWatch`: most of its markers found no
        point within reach of where they were and most points continue no marker; a sender that
        loops a take, frames lost with ``seq`` and ``t`` continuous): the subjects hit give no label
        in it, and a recovery boots them again (the others keep their labels). Left alone,
        the tracks took the nearest points and kept them, the stream ``online`` with a fifth
        of its labels wrong. True when it started one."""
        names, subject_of = self._subject_of
        assert self.rate is not None
        if self._jump is None:
            self._jump = JumpWatch(self.rate, self.settings.boot_config, subject_of)
        hit = self._jump.update(pts, t, out.point_labels)
        if hit.size == 0:
            return False
        gone = np.isin(subject_of, hit)

        def without(labels: np.ndarray) -> np.ndarray:  # (the subjects hit's labels removed)
            return np.where((labels >= 0) & gone[np.maximum(labels, 0)], -1, labels)

        out.point_labels[:] = without(out.point_labels)
        out.positions[gone] = np.nan
        out.state[gone] = MarkerState.MISSING
        # the frames before, without the subjects hit: they are booted, not given
        keep = [(p, tk, without(labels)) for p, tk, labels in self._recent]
        keep.append((pts, t, out.point_labels.copy()))
        self._seen_t = None
        self._recent.clear()
        # (counted and logged as a booting labeler's drops are: mocap_boot_verify_total)
        self.verify_events = (*self.verify_events, *(("jump", names[int(k)]) for k in hit))
        who = ", ".join(names[int(k)] for k in hit)
        why = "most markers found no point within reach of where they were, most points are new"
        self.start_recovery(f"{who}: the scene jumped past the tracks ({why})", keep)
        return True

    def reboot(self, why: str) -> bool:
        """A booting labeler that no recovery replaces (a model stream that boots, or a
        recovery in progress) is replaced by a fresh one of the same model and settings: every
        subject is booted again. Its tracks, active subjects and window belong to the frames
        before ``why``; kept, they carried labels over a restarted sender's take (a second
        replay of the tennis take: 200 wrong labels against the first replay's 67, two marker
        pairs exchanged to its end, the stream ``online``). False when the labeler does not
        boot."""
        lab = self.booting
        if lab is None:
            return False
        fresh = self._take_spare(lab.model, lab.rate, lab.boot_config)
        if fresh is None:
            fresh = self._recovery_labeler(lab.model, lab.rate, lab.boot_config)
        if fresh is None:
            return False
        # the boot worker's booter for the old key serves the fresh labeler: it depends only
        # on the model and the boot settings, both the same, and is read-only; unless a
        # relearn replaced the old labeler's booter (the fresh one starts from the model)
        if lab.boot_model is lab.model:
            fresh.key = lab.key
        recovering = self.recovering
        self._swap(fresh)
        self.recovering = recovering
        # its status reads ``booting`` until a subject is booted again (the averages of the
        # labeler replaced decayed to ``lost`` over frames nobody could be labeled in)
        self._booted_once = False
        self.labeled_fraction = self.recovered_fraction = float("nan")
        self.reboots += 1
        self.recoveries += 1  # (mocap_recoveries_total: a boot from the stream's model)
        self._runs_log.warning(_reason_key("reboot", why), "stream %s: %s: booting its %s "
                               "again (the tracks before it are stale)", self.name, why,
                               plural(len(lab.model.subjects), "subject"))  # fmt: skip
        return True

    def _swap(self, labeler: FrameLabeler) -> None:
        """Installs another labeler of the same marker set (recovery, hand-back): the model
        message and the health averages stay as they are."""
        self.boot_inflight = self._boot_request is not None  # (a job out stays: boot_done)
        self._boot_result = None
        self._handback.clear()
        self._handback_since = None
        self._recent.clear()  # (the watcher starts over with the labeler: _watch_subjects)
        self._seen_t = None
        self._jump = None
        if tuple(labeler.marker_names) != self.names:
            assert self.rate is not None
            self._install(labeler, self.rate)
        else:
            self.labeler = labeler
            self.recovering = False

    def _after_recovery_frame(self, f: FrameMsg, t: float, out: LabeledFrame) -> None:
        """While recovering: once every subject of the model has been labeled for
        ``HANDBACK_FRAMES`` frames (and no boot is in flight), hands the stream back to a plain
        labeler of the model started from those frames' labels (as the boot's own rebuild
        does); the next frame is its first unlabeled one."""
        lab = self.labeler
        assert isinstance(lab, BootingLabeler)
        if lab.n_active < len(lab.model.subjects):
            self._handback.clear()
            self._handback_since = None
            return
        self._handback.append((f.points, t, out.point_labels))
        # (not while a job is out: the next frame without one hands back; the wait goes on
        # meanwhile: started over at every job, it never ended when jobs came every 0.1 s, a
        # hostile run's 8 hugging performers)
        if len(self._handback) < HANDBACK_FRAMES or self.boot_inflight:
            return
        # the plain labeler labels only markers its first frames carry (one never labeled in
        # them stays unlabeled for good): the stream stays on the booting labeler, which
        # places markers as they appear, until every marker of a body is in them, for at
        # most HANDBACK_WAIT_S (a marker fallen off, or not worn, must not keep the booting
        # labeler's cost for good); a marker in no trained body no labeler labels
        if self._body_mask[0] is not lab.model:
            self._body_mask = (lab.model, _body_markers(lab.model))
        held = ~self._body_mask[1]
        for _, _, labels in self._handback:
            held[labels[labels >= 0]] = True
        back = "the window start's" if self.window_frames is not None else "the plain"
        if not held.all():
            missing = [lab.marker_names[i] for i in np.flatnonzero(~held)]
            shown = ", ".join(missing[:6]) + (", ..." if len(missing) > 6 else "")
            if self._handback_since is None:
                self._handback_since = t
                self._handback_log.info("handback", "stream %s: every subject labeled again; "
                                        "the booting labeler stays until it labels %s too (%s), "
                                        "at most %g s", self.name, plural(len(missing), "marker"),
                                        shown, HANDBACK_WAIT_S)  # fmt: skip
            if t - self._handback_since < HANDBACK_WAIT_S:
                return
            log.warning("stream %s: %s not labeled within %g s (%s): back to %s labeler "
                        "without them (%s)", self.name, plural(len(missing), "marker"),
                        HANDBACK_WAIT_S, shown, back, self._handback_advice())  # fmt: skip
        plain: FrameLabeler
        if self.window_frames is not None:  # back to the window start's labeler
            plain = make_window_labeler(
                lab.model,
                rate=lab.rate,
                window_frames=self.window_frames,
                config=self.settings.labeler_config,
                relearn_every_s=self.stream_settings.relearn_every_s,
            )
        else:
            plain = self._factory(self.settings.labeler, rate=lab.rate, model=lab.model,
                                  config=self.settings.labeler_config)  # fmt: skip
        for pts, tt, labels in self._handback:
            plain.process(pts, tt, labels)
        _off_the_loop(plain)
        self._swap(plain)
        self._labels_seen = True  # it starts from the hand-back frames' labels
        self.handbacks += 1
        log.info("stream %s: recovered: every subject labeled again; back to %s labeler",
                 self.name, back)  # fmt: skip

    def _handback_advice(self) -> str:
        """What becomes of markers a hand-back goes without, and what would label them, for
        this stream's start (a stream without a model file has no ``boot`` to turn on)."""
        if self.window_frames is not None:
            return "the window start's labeler places them when they appear"
        if self.stream_settings.model is not None:
            return (
                "the plain labeler will not label them; boot = true labels markers as they appear"
            )
        return (
            'the plain labeler will not label them; labeled_start = "auto" starts a labeler '
            "that places markers as they appear"
        )

    # --------------------------------------------------------------------- per frame
    def process(
        self, f: FrameMsg, recv_ns: int, verdict: Verdict = ACCEPT, before_ns: int = 0
    ) -> Output | None:
        """Labels one frame. Returns ``None`` while the training window is being buffered.
        ``before_ns``: time this frame already took before the call (the server's
        :meth:`new_run` on the event loop), counted in its labeling time.

        Raises :class:`LabelerError` when an unlabeled frame arrives before any model or init
        frame (``no_model``), :class:`InitBufferFullError`/:class:`LimitExceeded` when an
        init-buffer cap is hit. Trains inline when needed (the server trains off the loop
        instead, through :meth:`train`).
        """
        self.verify_events = ()
        # (a new run's rebuild or reboot counts in this frame)
        t0 = time.perf_counter_ns() - before_ns
        if verdict.new_run:
            self.new_run(f, verdict)
        if self.labeler is None:
            if f.labels is not None:
                self.buffer_init(f)
                return None
            if not self.init_frames:
                raise LabelerError(no_start(self.name, failed=self.status == "training_failed"))
            labeler, rate, out, label_ns = self.train(self.take_init(), f)
            return self.install_trained(labeler, rate, f, out, recv_ns, label_ns)
        if self._rebase:
            self._rebase = False
            if self._t_last is not None and self.rate:
                self._t_offset = self._t_last + 1.0 / self.rate - f.t
        t = f.t + self._t_offset
        self.just_booted = ()
        blackout = self._blackout_gap(t, len(f.points))
        labels = self._label_indices(f)
        if labels is not None:
            self._labels_seen = True
        elif gap := self._dropped_gap(t):
            # frames dropped in the service (a training stall, a busy machine): the tracks
            # cannot follow the performers over that gap, and the labeler trained in place
            # went on labeling ~75 % of them wrong while its labeled fraction stayed high
            # (10 performers at 360 Hz after the training's 0.7 s stall); a stream that boots
            # from its model file has no recovery to start: it boots everyone again (kept, a
            # hostile run's 0.8 s gap left 47 % of the labels wrong, the stream online)
            why = f"{gap:.2f} s of stream dropped before this frame"
            if not self.start_recovery(why):
                self.reboot(why)
        elif blackout:
            # the same gap sent as frames with no point (a camera dropout): a hostile run's
            # 0.3 s of empty frames left two performers' pelvis mirrored and feet exchanged
            # to the end of the stream (540-765 wrong labels a half second), the stream online
            # (or every performer out of view: the stream cannot tell the two apart)
            why = (
                f"{blackout:.2f} s without a point (a camera dropout, or every performer out of "
                "view) before this frame"
            )
            if not self.start_recovery(why):
                self.reboot(why)
        elif self._waits_for_labels():
            # boot = false and no labeled frame: the plain labeler could only refuse every
            # frame (labeler_error); boot the performers from the model instead
            self.start_recovery("frames without labels and boot = false (no labeled frame to "
                                "start from)")  # fmt: skip
        if self.handover is not None and self.handover.ready:
            self._install_handover()
            if labels is not None and f.labels is not None:
                labels = self._label_indices(f)  # (the window model's marker order)
        lab = self.labeler
        n_events = lab.events.total if isinstance(lab, BootingLabeler) else 0
        if self._installed_before is not None:
            self._installed_before.installed_t = t
            self._installed_before = None
        if self._boot_result is not None:
            self._install_boot(t)
        out = self.labeler.process(f.points, t, labels)
        h = self.handover
        if h is not None and lab is h.plain:
            h.record(f.points, t)
        self.verify_events = _verify_events(lab, n_events)
        if self.recovering:
            self._after_recovery_frame(f, t, out)
        else:
            self._watch_subjects(f.points, t, out)
        label_ns = time.perf_counter_ns() - t0
        self._t_last = t
        return self.encode(f, out, recv_ns, label_ns)

    # --------------------------------------------------------------------- boot
    @property
    def booting(self) -> BootingLabeler | None:
        """The labeler when it boots off the frame path (model stream, ``boot = true``)."""
        lab = self.labeler
        if isinstance(lab, BootingLabeler) and not lab.inline_boot:
            return lab
        return None

    @property
    def subjects_booted(self) -> tuple[str, ...]:
        """Subjects the booting labeler labels now (booted or given by labeled frames)."""
        lab = self.booting
        return lab.active_subjects if lab is not None else ()

    def boot_due(self) -> bool:
        """Cheap: True when :meth:`boot_request` would start an attempt."""
        lab = self.booting
        return (
            lab is not None
            and not self.boot_inflight
            and self._boot_result is None
            and lab.needs_boot()
        )

    def boot_request(self) -> BootRequest | None:
        """After a frame, in the thread that labels: the snapshot of a due boot attempt (marks
        it in flight), else None."""
        lab = self.booting
        if lab is None or not self.boot_due():
            return None
        self.boot_inflight = True
        # the worker process only once started and warm (by the server: at its start for
        # streams that boot, at a stream's first recovery otherwise): an attempt before boots
        # in the job's thread rather than wait for the worker's start-up (seconds: imports and
        # kernels); a worker killed since (an abandoned attempt) is started again by the
        # request
        w = self.boot_worker
        req = BootRequest(lab, lab.boot_snapshot(), w if w is not None and w.enabled else None)
        self._boot_request = req
        return req

    @staticmethod
    def boot_job(request: BootRequest, cancel: threading.Event | None = None) -> BootOutcome:
        """The heavy part of an attempt (runs off the event loop; touches no stream state):
        the boot step, then the catch-up of what it booted over the frames labeled since the
        snapshot (:meth:`BootingLabeler.catch_up`: the install then takes the caught-up state
        over), both in the boot worker process when the request has one."""
        lab = request.labeler
        t0 = time.perf_counter()
        runner = None if request.worker is None else request.worker.runner(lab, cancel)
        result = lab.boot_step(request.snapshot, runner)
        t1 = time.perf_counter()
        remote = None if request.worker is None else request.worker.catch_up(lab, cancel)
        try:
            caught = lab.catch_up(request.snapshot, result, cancel, remote)
        except LabelerError as exc:  # (the worker lost or failed): the result still counts
            log.warning("boot catch-up failed, the result follows the tracks instead: %s", exc)
            caught = False
        thread = threading.current_thread().name
        frames = request.snapshot.caught.done if caught and request.snapshot.caught else 0
        return BootOutcome(result, t1 - t0, thread, runner is not None, frames)

    def boot_done(self, request: BootRequest, outcome: BootOutcome | None) -> None:
        """Hands a finished attempt to the next :meth:`process` (``None``: abandoned or
        failed). A result for a labeler replaced meanwhile (a new run) is discarded, and the
        next attempt may start."""
        if request is self._boot_request:
            self._boot_request = None
        if request.labeler is not self.labeler:
            if self._boot_request is None and self._boot_result is None:
                self.boot_inflight = False
            return
        self._boot_result = (request, outcome)

    @property
    def install_due(self) -> bool:
        """A finished attempt waits for its install (:meth:`install_pending`, else the next
        :meth:`process`)."""
        return self._boot_result is not None

    def install_pending(self) -> float | None:
        """Installs a finished attempt's result now, between two frames (the server calls it
        on the event loop when the result comes and no frame waits: the install then costs
        no frame its labeling time, where :meth:`process` put it in the next frame's).
        The same install at the same frame boundary as that frame's would be: after the last
        frame labeled, before the next. Sets :attr:`just_booted` and :attr:`verify_events`
        (the next :meth:`process` resets them). Returns its wall time (s), or None when
        nothing was installed (no result waits, no frame was labeled yet, or the result was
        for a labeler replaced since: discarded)."""
        if self._boot_result is None or self._t_last is None:
            return None
        t0 = time.perf_counter()
        lab = self.labeler
        n_events = lab.events.total if isinstance(lab, BootingLabeler) else 0
        self.just_booted = ()
        self._installed_before = self._install_boot(float("nan"))
        self.verify_events = _verify_events(lab, n_events)
        if self._installed_before is None:  # (for a labeler replaced meanwhile: discarded)
            return None
        return time.perf_counter() - t0

    def _install_boot(self, t: float) -> BootRecord | None:
        """Installs the finished attempt; returns its record (None: its labeler was replaced
        meanwhile, the result is discarded)."""
        assert self._boot_result is not None
        request, outcome = self._boot_result
        self._boot_result = None
        self.boot_inflight = False
        lab = request.labeler
        if lab is not self.labeler:
            return None
        booted = lab.install_boot(request.snapshot, None if outcome is None else outcome.result)
        names = tuple(lab.model.subjects[int(i)].name for i in booted)
        self.just_booted = names
        self.boots.append(
            BootRecord(
                boot=bool(request.snapshot.subjects),
                t=request.snapshot.t,
                installed_t=t,
                booted=names,
                failed=outcome is None,
                thread="" if outcome is None else outcome.thread,
                seconds=float("nan") if outcome is None else outcome.seconds,
                worker=outcome is not None and outcome.worker,
                caught_frames=0 if outcome is None else outcome.caught_frames,
            )
        )
        return self.boots[-1]

    def ready_status(self) -> str:
        """The status the stream announces when the service is ready (or the stream gets its
        slot): ``booting`` while nobody can be labeled yet — the stream boots its performers
        from a model, or it has no labeler until its labeled init frames have trained one
        (the server turns it ``online`` then, :meth:`Server._train`), or its plain labeler of a
        model (``boot = false``) waits for a first labeled frame —, else ``online``."""
        waiting = (
            self.labeler is None
            or isinstance(self.labeler, BootingLabeler)
            or self._waits_for_labels()
        )
        self.status = "booting" if waiting else "online"
        return self.status

    def update_health(self, out: Output) -> str | None:
        """Folds one output into the labeled/recovered fractions; returns the new status when
        it changed (``online``, ``degraded``, ``lost``; ``booting`` while a booting labeler has
        not labeled any subject of the stream yet), else None."""
        m = out.scope or out.observed + out.recovered + out.missing
        if m <= 0:
            return None
        s = self.settings
        alpha = self._health_alpha
        lab, rec = out.observed / m, out.recovered / m
        bl = self.labeler if isinstance(self.labeler, BootingLabeler) else None
        if not self._booted_once and (bl is None or bl.n_active > 0):
            # the first boot (or a labeler that does not boot): the fractions start from this
            # frame (their average over the frames before it would read lost for a moment)
            self._booted_once = True
            self.labeled_fraction = float("nan")
        if math.isnan(self.labeled_fraction):
            self.labeled_fraction, self.recovered_fraction = lab, rec
        else:
            self.labeled_fraction += alpha * (lab - self.labeled_fraction)
            self.recovered_fraction += alpha * (rec - self.recovered_fraction)
        x = self.labeled_fraction
        hyst = 0.05  # back to a better status only clearly above the threshold
        if bl is not None and not self._booted_once:
            status = "booting"  # the first boot of the stream has not labeled anyone yet
        elif x < s.lost_below:
            status = "lost"
        elif x < s.degraded_below:
            status = "lost" if self.status == "lost" and x < s.lost_below + hyst else "degraded"
        elif self.status != "online" and x < s.degraded_below + hyst:
            status = "degraded"
        else:
            status = "online"
        if status == self.status:
            return None
        self.status = status
        return status

    def encode(self, f: FrameMsg, out: LabeledFrame, recv_ns: int, label_ns: int) -> Output:
        unl = out.point_labels < 0
        unlabeled = f.points[unl]
        state = out.state
        observed, recovered = out.n_observed, out.n_recovered
        sent = time.time_ns()
        payload = encode_labeled(
            self.name,
            self.model_id,
            f.seq,
            f.t if f.t_sent is None else f.t_sent,
            out.positions,
            state,
            unlabeled,
            f.sent,
            recv_ns,
            label_ns / 1e3,
            sent,
        )
        return Output(
            payload=payload,
            label_s=label_ns / 1e9,
            latency_s=(sent - f.sent) / 1e9 if f.sent is not None else None,
            observed=observed,
            recovered=recovered,
            missing=len(state) - observed - recovered,
            unlabeled=int(unlabeled.shape[0]),
            # (0 for another labeler, or before a boot: the health counts every marker)
            scope=self.labeler.n_active_markers if isinstance(self.labeler, BootingLabeler) else 0,
        )


def _verify_events(lab: FrameLabeler | None, n_events: int) -> tuple[tuple[str, str], ...]:
    """``(kind, subject)`` of the re-verification's and the vanishing's events
    (``boot_config.VERIFY_EVENTS``) a booting labeler logged since it counted
    ``n_events``."""
    if not isinstance(lab, BootingLabeler) or lab.events.total <= n_events:
        return ()
    return tuple(
        (kind, name)
        for _, kind, name in lab.events[n_events - lab.events.total :]
        if kind in VERIFY_EVENTS
    )


def _body_markers(model: LabelerModel) -> np.ndarray:
    """``(M,)`` the model's markers in a trained body (the others no labeler labels)."""
    out = []
    for subj in model.subjects:
        inside = np.zeros(len(subj.markers), dtype=bool)
        for body in subj.bodies:
            inside[list(body)] = True
        out.append(inside)
    return np.concatenate(out) if out else np.zeros(0, dtype=bool)


def no_start(stream: str, failed: bool = False) -> str:
    """Why a stream's unlabeled frames are dropped before it started, and the two fixes: the
    one sentence for the ``no_model`` drop and the UDP pre-filter's ``unknown_stream``.
    ``failed``: the stream's training on its labeled init frames failed (``training_failed``);
    it said "no labeled init frames" of a stream that had sent them."""
    why = (
        "its training on the labeled init frames failed, as logged above, and it has no model"
        if failed
        else "no model, no labeled init frames before them"
    )
    return (
        f"stream {stream}: unlabeled frames, and nothing to start the stream from ({why}): "
        "give it a model (a [[streams]] table with name = "
        f'"{stream}" and model = "MODEL.json" from train structure, with boot = true at the '
        "top of the settings, outside any table), or send "
        f"{'new ' if failed else ''}labeled init frames first (replay --init-frames 50)"
    )


def _remap(names: Sequence[str], window_names: Sequence[str]) -> np.ndarray:
    """From the init window's label indices to indices into a labeler's ``names``, one more
    entry (-1) at the end so that an unlabeled ``-1`` stays ``-1``."""
    index = {n: i for i, n in enumerate(names)}
    return np.array([index.get(n, -1) for n in window_names] + [-1], dtype=np.int32)


def _indices(index: dict[str, int], labels: Sequence[str | None] | None) -> np.ndarray | None:
    if labels is None:
        return None
    return np.fromiter(
        (index.get(lab, -1) if lab is not None else -1 for lab in labels),
        dtype=np.int32,
        count=len(labels),
    )
