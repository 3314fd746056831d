"""Per-stream state: sequence checks, the training window, the labeler, the output message.

A stream (one capture volume) starts in one of two ways:

1. **From a subject model file** (``streams[].model``, the ``train structure`` output): the
   labeler is built at start-up (after the server's kernel warm-up); frames are labeled from
   the first one.
2. **From labeled init frames in the stream** (seed 003's supervised training window): frames
   carrying ``labels`` are buffered; when the first unlabeled frame arrives, the marker set is
   the union of the init labels (sorted by subject, then marker), the rate
   comes from the settings or the init frames' times, the labeler is built and fed the init
   frames with their labels, then labels the new frame.

``seq`` handling: a duplicate or lower ``seq`` is dropped (``duplicate``/``late``); a jump back
of more than :data:`SEQ_RESTART` is taken as a restarted sender (tracking restarts, the labeler
and its state are kept); a forward gap is counted and the labeler simply predicts across it
(its motion model uses ``t``).
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labeler_service.capture import split_label
from labeler_service.errors import LabelerError, ModelError
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import FrameLabeler, LabeledFrame
from labeler_service.service.protocol import FrameMsg, encode_labeled, encode_model
from labeler_service.service.settings import ServiceSettings, StreamSettings

log = logging.getLogger(__name__)

#: A ``seq`` this far below the last one means the sender restarted (not a late frame).
SEQ_RESTART = 1000

LabelerFactory = Callable[[tuple[str, ...], float], FrameLabeler]


# ------------------------------------------------------------------------- labeler factory
def make_labeler(
    kind: str,
    marker_names: tuple[str, ...],
    rate: float,
    config: LabelerConfig | None = None,
    model_path: Path | None = None,
) -> FrameLabeler:
    """The one place that builds a labeler: ``online`` (seed 003) or ``baseline``.

    With ``model_path`` the online labeler starts from the trained subject templates
    (``Labeler.from_model``); otherwise from ``marker_names`` and the labeled init frames the
    caller feeds it.
    """
    if kind == "baseline":
        if model_path is not None and not marker_names:
            from labeler_service.labeling.templates import load_model

            marker_names = load_model(model_path).marker_names
        from labeler_service.labeling.baseline import ClosestPointLabeler

        return ClosestPointLabeler(marker_names, rate)
    from labeler_service.labeling.labeler import Labeler

    if model_path is not None:
        from labeler_service.labeling.templates import load_model

        return Labeler.from_model(load_model(model_path), rate, config)
    return Labeler(marker_names, rate, config)


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
    """``(subject, start, count)`` runs of a subject-grouped marker list (model message)."""
    out: list[tuple[str, int, int]] = []
    for i, n in enumerate(names):
        s = split_label(n)[0] or ""
        if out and out[-1][0] == s and out[-1][1] + out[-1][2] == i:
            out[-1] = (s, out[-1][1], out[-1][2] + 1)
        else:
            out.append((s, i, 1))
    return tuple(out)


def rigid_bodies(labeler: FrameLabeler, names: tuple[str, ...]) -> tuple[tuple[int, ...], ...]:
    """The online labeler's rigid bodies as marker indices into ``names`` (the model message's
    optional ``bodies``); ``()`` for the baseline or before the labeler has its templates."""
    from labeler_service.labeling.labeler import Labeler

    if not isinstance(labeler, Labeler) or labeler.model is None:
        return ()
    index = {n: i for i, n in enumerate(names)}
    return tuple(
        tuple(index[f"{subj.name}:{subj.markers[i]}"] for i in body)
        for subj in labeler.model.subjects
        for body in subj.bodies
    )


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


class StreamState:
    """Everything one stream owns. Not thread-safe: one worker task per stream."""

    def __init__(
        self,
        name: str,
        settings: ServiceSettings,
        stream_settings: StreamSettings | None = None,
        factory: Callable[..., FrameLabeler] = make_labeler,
    ) -> None:
        self.name = name
        self.settings = settings
        self.stream_settings = stream_settings or StreamSettings(name=name)
        self._factory = factory
        self.labeler: FrameLabeler | None = None
        self.names: tuple[str, ...] = ()
        self._index: dict[str, int] = {}
        self.rate: float | None = self.stream_settings.rate
        self.model_id = 0
        self.model_payload: bytes | None = None
        self.last_seq: int | None = None
        self.init_frames: list[FrameMsg] = []
        self._seen_unlabeled = False
        self.bodies: tuple[tuple[int, ...], ...] = ()

    def heavy(self, f: FrameMsg) -> bool:
        """True when labeling ``f`` trains the labeler (first unlabeled frame): the server then
        runs it in a worker thread so other streams keep flowing."""
        return f.labels is None and not self._seen_unlabeled

    # --------------------------------------------------------------------- start-up
    @property
    def started(self) -> bool:
        return self.labeler is not None

    def start_from_model(self) -> None:
        """Builds the labeler from the stream's model file (mode 1)."""
        path = self.stream_settings.model
        if path is None:
            raise ModelError(f"stream {self.name}: no model file configured")
        rate = self.stream_settings.rate
        if rate is None:
            from labeler_service.labeling.templates import load_model

            rate = load_model(path).rate
        self._install(
            self._factory(
                self.settings.labeler, (), rate, self.settings.labeler_config, model_path=path
            ),
            rate,
        )

    def _install(self, labeler: FrameLabeler, rate: float) -> None:
        self.labeler = labeler
        self.names = tuple(labeler.marker_names)
        self._index = {n: i for i, n in enumerate(self.names)}
        self.rate = float(rate)
        self.model_id += 1
        subjects = subject_slices(self.names)
        self.bodies = rigid_bodies(labeler, self.names)
        self.model_payload = self._encode_model()
        log.info(
            "stream %s: labeler ready (%d markers, %d subjects, %.1f Hz)",
            self.name,
            len(self.names),
            len(subjects),
            self.rate,
        )

    def _encode_model(self) -> bytes:
        assert self.rate is not None
        return encode_model(self.name, self.model_id, self.names, subject_slices(self.names),
                            self.rate, bodies=self.bodies or None)  # fmt: skip

    def _estimate_rate(self) -> float:
        if self.rate is not None:
            return self.rate
        t = np.array([f.t for f in self.init_frames], dtype=np.float64)
        dt = np.diff(np.sort(t))
        forward = dt > 0
        if not forward.any():
            raise LabelerError(
                f"stream {self.name}: cannot infer the frame rate from the init frames; set "
                "streams[].rate"
            )
        # seq steps tell how many frames each dt spans (init frames may have gaps)
        seqs = np.array(sorted(f.seq for f in self.init_frames), dtype=np.float64)
        steps = np.diff(seqs)
        ok = (steps > 0) & forward
        if ok.any():
            return float(1.0 / np.median(dt[ok] / steps[ok]))
        return float(1.0 / np.median(dt[forward]))

    def start_from_init_frames(self) -> None:
        """Builds the labeler from the buffered init frames (mode 2) and feeds them to it.

        Their labeled outputs are not published: the training window is the client's own
        labeled data; publishing starts with the first unlabeled frame.
        """
        seen: dict[str, None] = {}
        for f in self.init_frames:
            for lab in f.labels or ():
                if lab is not None:
                    seen.setdefault(lab, None)
        names = group_by_subject(list(seen))
        if not names:
            raise LabelerError(f"stream {self.name}: the init frames carry no labels")
        rate = self._estimate_rate()
        self._install(
            self._factory(self.settings.labeler, names, rate, self.settings.labeler_config),
            rate,
        )
        assert self.labeler is not None
        for f in self.init_frames:
            self.labeler.process(f.points, f.t, self._label_indices(f))
        self.init_frames = []

    def _label_indices(self, f: FrameMsg) -> np.ndarray | None:
        if f.labels is None:
            return None
        idx = self._index
        return np.fromiter(
            (idx.get(lab, -1) if lab is not None else -1 for lab in f.labels),
            dtype=np.int32,
            count=len(f.labels),
        )

    # --------------------------------------------------------------------- per frame
    def check_seq(self, seq: int) -> tuple[str | None, int]:
        """``(drop reason or None, frames skipped)`` for an arriving ``seq``; updates tracking."""
        last = self.last_seq
        if last is None or seq == last + 1:
            self.last_seq = seq
            return None, 0
        if seq == last:
            return "duplicate", 0
        if seq < last:
            if last - seq > SEQ_RESTART:
                log.info("stream %s: seq restarted (%d after %d)", self.name, seq, last)
                self.last_seq = seq
                return None, 0
            return "late", 0
        self.last_seq = seq
        return None, seq - last - 1

    def process(self, f: FrameMsg, recv_ns: int) -> Output | None:
        """Labels one frame. Returns ``None`` while the training window is being buffered.

        Raises :class:`LabelerError` when an unlabeled frame arrives before any model or init
        frame (``no_model``) and ``OverflowError`` when the init buffer is full.
        """
        if self.labeler is None:
            if f.labels is not None:
                if len(self.init_frames) >= self.settings.max_init_frames:
                    raise OverflowError(f"stream {self.name}: init buffer full")
                self.init_frames.append(f)
                return None
            if not self.init_frames:
                raise LabelerError(
                    f"stream {self.name}: unlabeled frame before any model or labeled init frame"
                )
            self.start_from_init_frames()
        assert self.labeler is not None
        t0 = time.perf_counter_ns()
        out = self.labeler.process(f.points, f.t, self._label_indices(f))
        label_ns = time.perf_counter_ns() - t0
        if f.labels is None and not self._seen_unlabeled:
            self._seen_unlabeled = True
            # a labeler trained from init frames has its bodies only now: the model message
            # gains them (same id, same markers); the next model repeat carries it
            bodies = rigid_bodies(self.labeler, self.names)
            if bodies != self.bodies:
                self.bodies = bodies
                self.model_payload = self._encode_model()
        return self.encode(f, out, recv_ns, label_ns)

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
            f.t,
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
        )
