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

``seq`` handling: a duplicate or lower ``seq`` is dropped (``duplicate``/``late``); a jump back
of more than :data:`SEQ_RESTART` is taken as a restarted sender (tracking restarts, the labeler
and its state are kept); a forward gap is counted and the labeler simply predicts across it
(its motion model uses ``t``).
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass

import numpy as np

from labeler_service.capture import split_label, subject_groups
from labeler_service.errors import InitBufferFullError, LabelerError, ModelError
from labeler_service.labeling.frame import FrameLabeler, LabeledFrame
from labeler_service.labeling.registry import LabelerFactory, make_labeler
from labeler_service.service.protocol import FrameMsg, encode_labeled, encode_model
from labeler_service.service.settings import ServiceSettings, StreamSettings

log = logging.getLogger(__name__)

#: A ``seq`` this far below the last one means the sender restarted (not a late frame).
SEQ_RESTART = 1000


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
        factory: LabelerFactory = make_labeler,
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
                self.settings.labeler, rate=rate, config=self.settings.labeler_config, model=path
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
        self.model_payload = encode_model(self.name, self.model_id, self.names, subjects, self.rate)
        log.info(
            "stream %s: labeler ready (%d markers, %d subjects, %.1f Hz)",
            self.name,
            len(self.names),
            len(subjects),
            self.rate,
        )

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
            self._factory(
                self.settings.labeler,
                marker_names=names,
                rate=rate,
                config=self.settings.labeler_config,
            ),
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
        frame (``no_model``) and :class:`InitBufferFullError` when the init buffer is full.
        """
        if self.labeler is None:
            if f.labels is not None:
                if len(self.init_frames) >= self.settings.max_init_frames:
                    raise InitBufferFullError(f"stream {self.name}: init buffer full")
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
        if f.labels is None:
            self._seen_unlabeled = True
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
