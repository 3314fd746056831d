"""Service metrics: Prometheus counters/histograms on a private registry, plus a log line.

Exposed as Prometheus text on ``metrics_host:metrics_port`` (``/metrics``) and summarised by a
periodic log line. Every drop has a ``reason``: the protocol's reject reasons
(:data:`~labeler_service.service.protocol.REJECT_REASONS`) and the service's own ones
(:data:`SERVICE_DROP_REASONS`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

from labeler_service.labeling.boot_config import VERIFY_EVENTS

log = logging.getLogger(__name__)

SERVICE_DROP_REASONS = (
    "queue_full",  # processing fell behind: the oldest queued frame was discarded
    "starting",  # unlabeled, received before the service was ready (stale by then)
    "duplicate",  # seq equal to the last one seen on the stream
    "late",  # seq lower than the last one seen, by at most max_seq_step
    "seq_jump",  # seq jumped (forward or back beyond max_seq_step): suspect, not yet a new run
    "time_jump",  # t did not advance, or jumped beyond max_time_step_s: suspect
    "second_sender",  # another sender's frame while the stream's sender sends (silent_after_s)
    "marker_cap",  # init frames would define more than max_markers distinct markers
    "training_failed",  # in-stream training failed or ran over train_budget_s
    "no_model",  # unlabeled frame on a stream with neither model nor labeled init frames
    "unknown_stream",  # stream not configured and allow_new_streams is off, no free slot, or
    # an unlabeled frame for a stream that never started (counted under stream "" only)
    "stream_mismatch",  # MQTT topic and payload disagree on the stream
    "init_overflow",  # more init frames than max_init_frames
    "labeler_error",  # the labeler raised on this frame (logged; state kept)
    "output_oversize",  # labeled frame larger than a datagram (not sent on UDP)
    "send_error",  # a transport failed to send (e.g. broker down; UDP: per refused datagram)
    "rx_overflow",  # a transport's receive queue was full: the oldest raw message was discarded
    "internal",  # an unexpected error while handling one message (logged with traceback)
    "kernel_rx_overflow",  # UDP: datagrams the kernel dropped, receive buffer full (Linux)
    "subscribe_short",  # UDP subscribe smaller than the challenge: not answered
    "subscribe_token",  # UDP subscribe echoed a wrong or stale challenge token
    "subscribe_host_limit",  # more than max_subscribers_per_host from one IP
    "subscribe_full",  # max_subscribers confirmed subscribers already
    "retained_spoofed",  # MQTT: another client replaced our retained model/status (re-asserted)
)

_MS_BUCKETS = (
    0.00005, 0.0001, 0.0002, 0.0003, 0.0005, 0.00075, 0.001, 0.0015, 0.002, 0.0025,
    0.003, 0.004, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0,
)  # fmt: skip


def _ms(x: float) -> str:
    """A time in ms for the log line; ``-`` before any frame is labeled (not ``nan``)."""
    return f"{x:.2f}" if np.isfinite(x) else "-"


@dataclass
class _Recent:
    """A ring of the latest samples (seconds) for the log line's percentiles."""

    size: int = 4096
    values: np.ndarray = field(default_factory=lambda: np.full(4096, np.nan))
    i: int = 0

    def add(self, v: float) -> None:
        self.values[self.i % self.size] = v
        self.i += 1

    def percentiles(self, qs: tuple[float, ...]) -> tuple[float, ...]:
        v = self.values[: min(self.i, self.size)]
        if v.size == 0:
            return tuple(float("nan") for _ in qs)
        return tuple(float(x) for x in np.percentile(v, qs))


@dataclass(slots=True)
class _StreamOut:
    """One stream's bound metric children for :meth:`ServiceMetrics.frame_out` (no label
    lookups per frame)."""

    frames_out: Counter
    labeling: Histogram
    latency: Histogram | None  # bound at the first frame with a sender stamp
    observed: Counter
    recovered: Counter
    missing: Counter
    unlabeled: Counter
    recent_label: _Recent
    recent_latency: _Recent


class ServiceMetrics:
    """All counters of one server. ``snapshot()`` gives plain numbers for tests and logs."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames_in = Counter(
            "mocap_frames_in", "Frames accepted into the stream's queue", ["stream"], registry=r
        )
        self.frames_out = Counter(
            "mocap_frames_out", "Labeled frames published", ["stream"], registry=r
        )
        self.dropped = Counter(
            "mocap_dropped", "Messages dropped, by reason", ["stream", "reason"], registry=r
        )
        self.seq_gap = Counter(
            "mocap_seq_gap_frames", "Frames missing from seq gaps (predicted across)",
            ["stream"], registry=r,
        )  # fmt: skip
        self.labeling = Histogram(
            "mocap_labeling_seconds", "Labeler time per frame", ["stream"],
            buckets=_MS_BUCKETS, registry=r,
        )  # fmt: skip
        self.latency = Histogram(
            "mocap_latency_seconds",
            "Service-side end-to-end latency: sender stamp to labeled frame sent",
            ["stream"], buckets=_MS_BUCKETS, registry=r,
        )  # fmt: skip
        self.markers = Counter(
            "mocap_markers", "Markers per state in published frames", ["stream", "state"],
            registry=r,
        )  # fmt: skip
        self.unlabeled = Counter(
            "mocap_unlabeled_points", "Input points left unlabeled", ["stream"], registry=r
        )
        self.queue_depth = Gauge("mocap_queue_depth", "Queued frames", ["stream"], registry=r)
        self.ready = Gauge("mocap_ready", "1 once kernels are warm and serving", registry=r)
        self.labeled_fraction = Gauge(
            "mocap_labeled_fraction",
            "Observed (labeled) markers / model markers, exponential average over health_window_s",
            ["stream"], registry=r,
        )  # fmt: skip
        self.recovered_fraction = Gauge(
            "mocap_recovered_fraction",
            "Recovered (predicted) markers / model markers, exp. average over health_window_s",
            ["stream"], registry=r,
        )  # fmt: skip
        self.streams_active = Gauge("mocap_streams", "Streams with a slot", registry=r)
        self.receive_buffer = Gauge(
            "mocap_udp_receive_buffer_bytes",
            "Kernel receive buffer of the UDP socket as the OS granted it (getsockopt)",
            registry=r,
        )  # fmt: skip
        self.transport_up = Gauge(
            "mocap_transport_up",
            "1 while the transport carries frames, 0 while it cannot (MQTT: the broker "
            "unreachable; the log says why)",
            ["transport"], registry=r,
        )  # fmt: skip
        self.training = Gauge(
            "mocap_training_jobs", "In-stream trainings running or waiting (off the loop)",
            registry=r,
        )  # fmt: skip
        self.background_threads = Gauge(
            "mocap_background_threads",
            "Background job threads alive (trainings, boots), abandoned ones included",
            registry=r,
        )  # fmt: skip
        self.streams_expired = Counter(
            "mocap_streams_expired", "Unconfigured streams removed after stream_idle_s idle",
            registry=r,
        )  # fmt: skip
        self.boot_attempts = Counter(
            "mocap_boot_attempts", "Boot attempts started (off the event loop)", ["stream"],
            registry=r,
        )  # fmt: skip
        self.boot_failures = Counter(
            "mocap_boot_failed", "Boot attempts abandoned over boot_budget_s or failed",
            ["stream"], registry=r,
        )  # fmt: skip
        self.boot_duration = Histogram(
            "mocap_boot_seconds", "Wall time of finished boot attempts", ["stream"],
            buckets=(0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0), registry=r,
        )  # fmt: skip
        self.boot_install_duration = Histogram(
            "mocap_boot_install_seconds",
            "Wall time of boot results installed between frames (a result that finds a frame "
            "waiting is installed in that frame's labeling instead)", ["stream"],
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1), registry=r,
        )  # fmt: skip
        self.subjects_booted = Gauge(
            "mocap_subjects_booted", "Subjects of the model labeled now (booted)", ["stream"],
            registry=r,
        )  # fmt: skip
        self.boot_verify = Counter(
            "mocap_boot_verify",
            "Booted subjects' events: markers withdrawn by the re-verification (withdraw), "
            "subject dropped by it (reject), because it vanished (drop), the scene jumped past "
            "its tracks (jump) or after a camera dropout (blackout); left and right exchanged "
            "back (exchange)",
            ["stream", "event"], registry=r,
        )  # fmt: skip
        self.recoveries = Counter(
            "mocap_recoveries",
            "Recoveries by boot from the stream's own model (lost, or a new run after a time "
            "jump)", ["stream"], registry=r,
        )  # fmt: skip
        self.handovers = Counter(
            "mocap_handovers",
            "The window start's handovers (labeled_start auto/model): the window labeler took "
            "over from the labeler trained in place (took_over), or the handover was given up "
            "and the plain labeler stayed (abandoned)", ["stream", "outcome"], registry=r,
        )  # fmt: skip
        self._handovers_seen: dict[tuple[str, str], int] = {}
        self._recent_label: dict[str, _Recent] = {}
        self._recent_latency: dict[str, _Recent] = {}
        #: per stream (unlabeled points, frames out) at the last log line
        self._logged: dict[str, tuple[float, float]] = {}
        self._out: dict[str, _StreamOut] = {}
        self._children: dict[tuple, object] = {}
        self._http: tuple | None = None
        self._drops: dict[tuple[str, str], int] = {}

    # ---------------------------------------------------------------- recording
    def _child(self, metric, *labels: str):
        key = (id(metric), labels)
        c = self._children.get(key)
        if c is None:
            c = self._children[key] = metric.labels(*labels)
        return c

    def drop(self, reason: str, stream: str = "", n: int = 1) -> None:
        self._child(self.dropped, stream, reason).inc(n)
        self._drops[(stream, reason)] = self._drops.get((stream, reason), 0) + n

    def health(self, stream: str, labeled: float, recovered: float) -> None:
        self._child(self.labeled_fraction, stream).set(labeled)
        self._child(self.recovered_fraction, stream).set(recovered)

    def boot_attempt(self, stream: str) -> None:
        self._child(self.boot_attempts, stream).inc()

    def boot_failed(self, stream: str) -> None:
        self._child(self.boot_failures, stream).inc()

    def boot_seconds(self, stream: str, seconds: float) -> None:
        self._child(self.boot_duration, stream).observe(seconds)

    def boot_install(self, stream: str, seconds: float) -> None:
        self._child(self.boot_install_duration, stream).observe(seconds)

    def verify_event(self, stream: str, event: str) -> None:
        self._child(self.boot_verify, stream, event).inc()

    def recovery(self, stream: str) -> None:
        self._child(self.recoveries, stream).inc()

    def handover_totals(self, stream: str, took_over: int, abandoned: int) -> None:
        """Brings ``mocap_handovers`` up to a stream's running totals (the stream counts its
        handovers wherever they end: a frame, the handover's job, a recovery, a new run)."""
        for outcome, total in (("took_over", took_over), ("abandoned", abandoned)):
            seen = self._handovers_seen.get((stream, outcome), 0)
            if total > seen:
                self._child(self.handovers, stream, outcome).inc(total - seen)
                self._handovers_seen[(stream, outcome)] = total

    def subjects(self, stream: str, n: int) -> None:
        self._child(self.subjects_booted, stream).set(n)

    def forget(self, stream: str) -> None:
        """Removes every series of ``stream`` (an expired unconfigured stream): the label
        cardinality stays bounded by the stream slots. Its drops are folded into stream ""."""
        for key in [k for k in self._children if k[1] and k[1][0] == stream]:
            del self._children[key]
        for metric in (
            self.frames_in, self.frames_out, self.seq_gap, self.labeling, self.latency,
            self.unlabeled, self.queue_depth, self.labeled_fraction, self.recovered_fraction,
            self.boot_attempts, self.boot_failures, self.boot_duration, self.boot_install_duration,
            self.subjects_booted,
            self.recoveries,
        ):  # fmt: skip
            with contextlib.suppress(KeyError):
                metric.remove(stream)
        for state in ("observed", "recovered", "missing"):
            with contextlib.suppress(KeyError):
                self.markers.remove(stream, state)
        for event in VERIFY_EVENTS:
            with contextlib.suppress(KeyError):
                self.boot_verify.remove(stream, event)
        for outcome in ("took_over", "abandoned"):
            self._handovers_seen.pop((stream, outcome), None)
            with contextlib.suppress(KeyError):
                self.handovers.remove(stream, outcome)
        for (s, reason), n in list(self._drops.items()):
            if s == stream:
                del self._drops[(s, reason)]
                with contextlib.suppress(KeyError):
                    self.dropped.remove(stream, reason)
                self.drop(reason, "", n)
        self._out.pop(stream, None)
        self._recent_label.pop(stream, None)
        self._logged.pop(stream, None)
        self._recent_latency.pop(stream, None)

    def series(self) -> int:
        """Number of exported samples (tests: label cardinality stays bounded)."""
        return sum(len(m.samples) for m in self.registry.collect())

    def frame_in(self, stream: str) -> None:
        self._child(self.frames_in, stream).inc()

    def queue(self, stream: str, depth: int) -> None:
        self._child(self.queue_depth, stream).set(depth)

    def gap(self, stream: str, n: int) -> None:
        self._child(self.seq_gap, stream).inc(n)

    def frame_out(
        self,
        stream: str,
        label_s: float,
        latency_s: float | None,
        observed: int,
        recovered: int,
        missing: int,
        unlabeled: int,
    ) -> None:
        c = self._out.get(stream)
        if c is None:
            c = self._out[stream] = self._bind_out(stream)
        c.frames_out.inc()
        c.labeling.observe(label_s)
        c.recent_label.add(label_s)
        if latency_s is not None:
            if c.latency is None:
                c.latency = self._child(self.latency, stream)
            c.latency.observe(latency_s)
            c.recent_latency.add(latency_s)
        c.observed.inc(observed)
        c.recovered.inc(recovered)
        c.missing.inc(missing)
        c.unlabeled.inc(unlabeled)

    def _bind_out(self, stream: str) -> _StreamOut:
        label = self._recent_label[stream] = _Recent()
        latency = self._recent_latency[stream] = _Recent()
        return _StreamOut(
            self._child(self.frames_out, stream),
            self._child(self.labeling, stream),
            None,
            self._child(self.markers, stream, "observed"),
            self._child(self.markers, stream, "recovered"),
            self._child(self.markers, stream, "missing"),
            self._child(self.unlabeled, stream),
            label,
            latency,
        )

    # ---------------------------------------------------------------- reading
    def value(self, name: str, **labels: str) -> float:
        v = self.registry.get_sample_value(name, labels)
        return 0.0 if v is None else float(v)

    def drops(self, reason: str | None = None, stream: str | None = None) -> int:
        return sum(
            n
            for (s, r), n in self._drops.items()
            if (reason is None or r == reason) and (stream is None or s == stream)
        )

    def _sample_values(self) -> Callable[..., float]:
        """``value(name, **labels)`` over one read of the registry. ``value`` reads the whole
        registry per sample (``get_sample_value``): the log line's ~14 per stream took 0.5 s
        at 16 streams, on the event loop, and dropped frames at every line (a hostile run)."""
        samples: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
        for metric in self.registry.collect():
            for x in metric.samples:
                samples[(x.name, tuple(sorted(x.labels.items())))] = float(x.value)

        def value(name: str, **labels: str) -> float:
            return samples.get((name, tuple(sorted(labels.items()))), 0.0)

        return value

    def snapshot(self) -> dict:
        """Totals per stream and drops per reason, as plain numbers."""
        value = self._sample_values()
        streams = sorted(
            {k[1][0] for k in self._children if k[0] == id(self.frames_in)}
            | {k[1][0] for k in self._children if k[0] == id(self.frames_out)}
        )
        out: dict = {"streams": {}, "drops": {}}
        for (_, reason), n in self._drops.items():
            out["drops"][reason] = out["drops"].get(reason, 0) + n
        for s in streams:
            lab = self._recent_label.get(s, _Recent()).percentiles((50, 99))
            lat = self._recent_latency.get(s, _Recent()).percentiles((50, 99))
            out["streams"][s] = {
                "frames_in": value("mocap_frames_in_total", stream=s),
                "frames_out": value("mocap_frames_out_total", stream=s),
                "observed": value("mocap_markers_total", stream=s, state="observed"),
                "recovered": value("mocap_markers_total", stream=s, state="recovered"),
                "unlabeled": value("mocap_unlabeled_points_total", stream=s),
                "gap_frames": value("mocap_seq_gap_frames_total", stream=s),
                "labeling_ms_p50": lab[0] * 1e3,
                "labeling_ms_p99": lab[1] * 1e3,
                "latency_ms_p50": lat[0] * 1e3,
                "latency_ms_p99": lat[1] * 1e3,
                "boot_attempts": value("mocap_boot_attempts_total", stream=s),
                "boot_failed": value("mocap_boot_failed_total", stream=s),
                "subjects_booted": value("mocap_subjects_booted", stream=s),
                "labeled_fraction": value("mocap_labeled_fraction", stream=s),
                "handovers": value("mocap_handovers_total", stream=s, outcome="took_over"),
                "handovers_abandoned": value(
                    "mocap_handovers_total", stream=s, outcome="abandoned"
                ),
            }
        return out

    def log_line(self, streams: dict[str, tuple[str, int]] | None = None) -> str:
        """The periodic log line. ``streams``: per stream its status and, for a stream that
        boots, the number of its model's subjects: the line then says the status (with the
        labeled fraction) and how many subjects are booted after how many attempts, so a
        stream that labels nothing says so; a stream in ``streams`` that has had no frame yet
        (a configured stream before its first frame) reads ``[name] no frames yet``. Each
        stream's part ends with its own drops by reason (``drops=queue_full:3`` or
        ``drops=none``); the line ends with the drops of the whole service, those of no
        stream included (``| service drops: ...``: a hostile user read ``drops=seq_jump:2
        drops: rx_overflow=258`` as two contradicting counts)."""
        snap = self.snapshot()
        parts = []
        for s, v in snap["streams"].items():
            line = (
                f"[{s}] in={v['frames_in']:.0f} out={v['frames_out']:.0f} "
                f"label p50/p99={_ms(v['labeling_ms_p50'])}/{_ms(v['labeling_ms_p99'])} ms "
                f"latency p99={_ms(v['latency_ms_p99'])} ms recovered={v['recovered']:.0f}"
            )
            # points left unlabeled per frame since the last line (a performer the labeler
            # does not know, ghosts): the labeled fraction counts only the known markers
            seen = (v["unlabeled"], v["frames_out"])
            before = self._logged.get(s, (0.0, 0.0))
            self._logged[s] = seen
            if seen[1] > before[1]:
                line += f" unlabeled={(seen[0] - before[0]) / (seen[1] - before[1]):.1f}/frame"
            status, n_subjects = (streams or {}).get(s, ("", 0))
            if status:
                line += f" status={status} labeled={v['labeled_fraction']:.2f}"
            if n_subjects:
                line += (
                    f" booted={v['subjects_booted']:.0f}/{n_subjects} "
                    f"(boot attempts {v['boot_attempts']:.0f}, failed {v['boot_failed']:.0f})"
                )
            mine = sorted((r, n) for (st, r), n in self._drops.items() if st == s)
            line += " drops=" + (",".join(f"{r}:{n}" for r, n in mine) or "none")
            parts.append(line)
        for s, (status, _) in (streams or {}).items():
            if s not in snap["streams"]:  # a configured stream that has had no frame yet
                parts.append(f"[{s}] no frames yet" + (f" status={status}" if status else ""))
        # every stream's drops, and those of no stream (a datagram that names none, a stream
        # removed since): each stream's own are on its part (``drops=``)
        drops = ", ".join(f"{r}={n}" for r, n in sorted(snap["drops"].items())) or "none"
        return " ".join(parts or ["no streams yet"]) + f" | service drops: {drops}"

    # ---------------------------------------------------------------- HTTP endpoint
    def serve_http(self, host: str, port: int) -> int:
        """Starts the Prometheus text endpoint in a daemon thread; returns the bound port."""
        server, thread = start_http_server(port, addr=host, registry=self.registry)
        self._http = (server, thread)
        return int(server.server_address[1])

    def close(self) -> None:
        if self._http is not None:
            server, thread = self._http
            server.shutdown()
            server.server_close()
            thread.join(timeout=5)
            self._http = None


class RateLimitedLog:
    """Logs at most one line per key every ``period`` seconds, counting what it suppressed."""

    def __init__(self, logger: logging.Logger, period: float = 5.0) -> None:
        self.logger = logger
        self.period = period
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, msg: str, *args: object) -> bool:
        return self.log(logging.WARNING, key, msg, *args)

    def info(self, key: str, msg: str, *args: object) -> bool:
        return self.log(logging.INFO, key, msg, *args)

    def log(self, level: int, key: str, msg: str, *args: object) -> bool:
        """Logs ``msg`` at ``level`` unless ``key`` logged less than ``period`` ago; True when
        it did. The first line after a quiet period tells how many were suppressed."""
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        suffix = f" ({n} similar suppressed)" if n else ""
        self.logger.log(level, msg + suffix, *args)
        return True
