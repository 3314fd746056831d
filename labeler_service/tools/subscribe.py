"""The subscriber client: receives labeled frames, decodes them with the model message.

Over UDP it registers with the service (a padded ``subscribe`` datagram, renewed every second),
answers the service's ``challenge`` by echoing its token (the service confirms our address
before it sends anything larger than our request) and then gets the retained model and status;
over MQTT it subscribes to ``mocap/<stream>/{labeled,model,status}`` (model and status are
retained). A labeled frame whose
model has not arrived yet is counted as ``undecodable`` (at most a second, the model repeat).

End-to-end latency of a frame = subscriber receipt (``time.time_ns()`` when the message was
read from the socket) - the sender's stamp carried through the service (``src``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from labeler_service.errors import ProtocolError
from labeler_service.labeling.frame import MarkerState
from labeler_service.service.protocol import (
    ChallengeMsg,
    LabeledMsg,
    ModelMsg,
    StatusMsg,
    decode,
    encode_subscribe,
)
from labeler_service.service.settings import MqttSettings
from labeler_service.service.transports.base import DropOldestQueue, Incoming, cancel_and_wait
from labeler_service.service.transports.url import Endpoint, parse_endpoint
from labeler_service.wording import plural

if TYPE_CHECKING:
    from labeler_service.service.transports.mqtt import MqttEndpoint
    from labeler_service.service.transports.udp import UdpClient

log = logging.getLogger(__name__)


def percentiles(values, qs=(50.0, 99.0, 99.9)) -> dict[str, float]:
    """``{"p50": ..., "p99": ..., "p99.9": ...}`` of ``values`` (NaN for none)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {f"p{q:g}": float("nan") for q in qs}
    return {f"p{q:g}": float(x) for q, x in zip(qs, np.percentile(v, qs), strict=True)}


def no_nan(value):
    """A measurement a run could not make (NaN: no frame to take a percentile of) as ``None``,
    through dicts, lists and tuples: JSON has no NaN, and a strict parser (``jq``) refuses the
    bare token (``bench latency --json``, the demo's ``report.json``)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: no_nan(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [no_nan(v) for v in value]
    return value


def strict_json(value, **kwargs) -> str:
    """``value`` as strict JSON text (:func:`no_nan`: ``null`` for a measurement a run could
    not make, never ``NaN``); ``kwargs`` go to :func:`json.dumps` (``indent``)."""
    import json

    return json.dumps(no_nan(value), allow_nan=False, **kwargs)


#: the statuses of a stream the service is ready to label: ``online``, or ``booting`` for a
#: stream that has labeled no one yet (it boots its performers from a model, or waits for the
#: labeled init frames that train its labeler)
READY = ("online", "booting")


@dataclass(slots=True)
class Received:
    """One decoded labeled frame with the marker names of its model."""

    msg: LabeledMsg
    names: tuple[str, ...]
    recv_ns: int
    nbytes: int = 0  # encoded message size

    @property
    def latency_ms(self) -> float | None:
        return (self.recv_ns - self.msg.src) / 1e6 if self.msg.src is not None else None


@dataclass
class SubscriberStats:
    """Running totals; ``latencies_ms`` keeps every sample (floats: 2 MB per 10 min at 360 Hz)."""

    frames: int = 0
    undecodable: int = 0
    rejected: int = 0
    missing_seq: int = 0
    out_of_order: int = 0
    observed: int = 0
    recovered: int = 0
    missing: int = 0
    unlabeled: int = 0
    latencies_ms: list[float] = field(default_factory=list)
    last_seq: dict[str, int] = field(default_factory=dict)

    def add(self, r: Received) -> None:
        m = r.msg
        self.frames += 1
        last = self.last_seq.get(m.stream)
        if last is not None:
            if m.seq > last + 1:
                self.missing_seq += m.seq - last - 1
            elif m.seq <= last:
                self.out_of_order += 1
        if last is None or m.seq > last:
            self.last_seq[m.stream] = m.seq
        st = m.state
        obs = int(np.count_nonzero(st == MarkerState.OBSERVED))
        rec = int(np.count_nonzero(st == MarkerState.RECOVERED))
        self.observed += obs
        self.recovered += rec
        self.missing += len(st) - obs - rec
        self.unlabeled += len(m.unlabeled)
        lat = r.latency_ms
        if lat is not None:
            self.latencies_ms.append(lat)

    def latency_percentiles(self, qs=(50.0, 99.0, 99.9)) -> dict[str, float]:
        return percentiles(self.latencies_ms, qs)

    def summary_line(self, window_frames: int, window_s: float) -> str:
        lat = self.latency_percentiles((50.0, 99.0))
        per = max(self.frames, 1)
        return (
            f"frames {self.frames} ({window_frames / max(window_s, 1e-9):.0f}/s)  "
            f"latency since start p50 {ms(lat['p50'])} p99 {ms(lat['p99'])}  "
            f"missing seq {self.missing_seq}  markers/frame observed {self.observed / per:.1f} "
            f"recovered {self.recovered / per:.1f} missing {self.missing / per:.1f}  "
            f"unlabeled {self.unlabeled / per:.1f}"
        )


class Subscriber:
    """``async with Subscriber(url) as sub: async for r in sub.frames(): ...``"""

    def __init__(
        self,
        url: str | Endpoint,
        mqtt: MqttSettings | None = None,
        queue_size: int = 8192,
        renew_s: float = 1.0,
        silence_s: float | None = 1.0,
    ) -> None:
        self.endpoint = parse_endpoint(url) if isinstance(url, str) else url
        self.stream = self.endpoint.stream
        self._mqtt_base = mqtt
        self.renew_s = renew_s
        self.models: dict[str, ModelMsg] = {}
        self.status: dict[str, str] = {}
        self._labeled: dict[str, bool] = {}  # a frame of the stream had a labeled marker
        self.stats = SubscriberStats()
        self._out: DropOldestQueue[Received] = DropOldestQueue(queue_size)
        self._status_changed = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._stack = contextlib.AsyncExitStack()
        self._transport: UdpClient | MqttEndpoint | None = None
        self._udp: UdpClient | None = None  # the same transport, when it is UDP
        self._token: bytes | None = None  # UDP challenge token to echo
        #: liveness warnings (see :meth:`_watch`): after this long without a labeled frame
        #: (None: no watch)
        self.silence_s = silence_s
        self._last_frame = time.monotonic()  # last labeled frame (or the start)
        self._refused_before = 0  # UDP refusals counted when the last labeled frame came
        self._heard = False  # any message from the service so far
        self._any_frame = False  # any labeled frame so far
        self.silent = False  # a silence warning is out and no frame came since
        self.warnings: list[str] = []  # every liveness line, oldest first (bounded)

    @property
    def dropped(self) -> int:
        """Frames lost inside this client because the consumer fell behind."""
        return self._out.dropped + (self._transport.received_dropped if self._transport else 0)

    async def __aenter__(self) -> Subscriber:
        ep = self.endpoint
        if ep.scheme == "udp":
            from labeler_service.service.transports.udp import UdpClient

            udp = await self._stack.enter_async_context(UdpClient(ep.host, ep.port))
            self._transport = self._udp = udp
            self._tasks.append(asyncio.create_task(self._renew(), name="subscribe-renew"))
        else:
            from labeler_service.service.transports.mqtt import MqttEndpoint, topic
            from labeler_service.tools.replay import mqtt_settings_for

            settings = mqtt_settings_for(ep, self._mqtt_base)
            s = self.stream or "+"
            topics = [topic(settings.topic_prefix, s, k) for k in ("model", "status", "labeled")]
            self._transport = await self._stack.enter_async_context(
                MqttEndpoint(settings, s, topics)
            )
        self._tasks.append(asyncio.create_task(self._pump(), name="subscribe-pump"))
        if self.silence_s is not None:
            self._last_frame = time.monotonic()
            self._tasks.append(asyncio.create_task(self._watch(), name="subscribe-watch"))
        return self

    def _warn(self, msg: str, *args: object, level: int = logging.WARNING) -> None:
        line = msg % args
        if len(self.warnings) >= 1000:
            del self.warnings[:500]
        self.warnings.append(line)
        log.log(level, "%s", line)

    def _what(self) -> str:
        ep = self.endpoint
        return f"{ep.scheme}://{ep.host}:{ep.port}/{self.stream or '*'}"

    async def _watch(self) -> None:
        """Says when the labeled frames stop for more than ``silence_s`` (the service died,
        the stream stopped or the network dropped them) and when they resume; says so too
        when nothing answers at all (UDP: the kernel's "connection refused" reports)."""
        assert self.silence_s is not None
        while True:
            await asyncio.sleep(min(0.25, self.silence_s / 4))
            quiet = time.monotonic() - self._last_frame
            if self.silent or quiet <= self.silence_s:
                continue
            self.silent = True
            udp = self._udp
            trouble = self._transport.trouble() if self._transport is not None else None
            # refused since the last frame (not during an earlier outage the frames ended:
            # a service restarted since said "nothing listens there" at the next silence)
            if udp is not None and udp.refused > self._refused_before:
                why = "nothing listens there (connection refused): is the service running?"
            elif trouble is not None:  # MQTT: the broker, not the service, is out of reach
                why = trouble
            elif not self._heard:
                why = "no answer from the service yet: is it running, is the address right?"
                if self.endpoint.scheme == "mqtt" and self.stream:
                    # (it hears only its stream's topics: a stream the service's settings do
                    # not list is silent there, the service running or not)
                    why += (
                        f" Over MQTT the service serves only the streams its settings list: "
                        f"is {self.stream!r} in its [[streams]]?"
                    )
            elif (
                self.stream
                and self.stream not in self.status
                and self.stream not in self.models
                and self.stats.frames == 0
            ):
                why = (
                    f"the service answers but has announced no stream {self.stream!r} (no "
                    "status, no model): is the stream name right? (an unlisted stream appears "
                    "with its first labeled frames; unlabeled ones need a model for it in the "
                    "service's settings: its log says so; or the service refused this "
                    "subscriber over UDP, e.g. too many from one remote host: its log names "
                    "the limit)"
                )
            elif self.stats.frames == 0 and self.stats.undecodable == 0:
                # (a stream announced online may be idle: its sender between two takes)
                state = self.status.get(self.stream) if self.stream else None
                why = (
                    f"the service answers and says the stream is {state}, but no frame came "
                    "to this subscriber yet: is the stream's sender sending?"
                    if state
                    else "the service answers; the stream has not sent labeled frames yet"
                )
            else:
                why = "the service stopped, the stream paused, or the network drops them"
            self._warn("subscribe %s: no labeled frames for %.1f s: %s", self._what(), quiet,
                       why)  # fmt: skip

    async def __aexit__(self, *exc: object) -> None:
        tasks, self._tasks = self._tasks, []
        await cancel_and_wait(tasks)
        await self._stack.aclose()

    async def _renew(self) -> None:
        while True:
            self._send_subscribe()
            await asyncio.sleep(self.renew_s)

    def _send_subscribe(self) -> None:
        """A (padded) subscribe datagram, echoing the service's challenge token once known."""
        assert self._udp is not None
        with contextlib.suppress(OSError):
            self._udp.send(encode_subscribe(self.stream or "*", self._token))

    async def _pump(self) -> None:
        assert self._transport is not None
        async for inc in self._transport.messages():
            self._handle(inc)

    def _handle(self, inc: Incoming) -> None:
        try:
            msg = decode(inc.payload, max_points=1 << 16, max_bytes=1 << 24)
        except ProtocolError:
            self.stats.rejected += 1
            return
        self._heard = True
        if isinstance(msg, LabeledMsg):
            now = time.monotonic()
            if self.silent:
                self.silent = False
                # the first frame after a silence since the start is no resumption
                # (a booting stream's frames carry no label yet: not called labeled)
                noun = "labeled frames" if (msg.state == MarkerState.OBSERVED).any() else "frames"
                what = f"{noun} again" if self._any_frame else f"first {noun}"
                if noun == "frames":
                    what += " with no marker labeled yet"
                self._warn("subscribe %s: %s (stream %s) after %.1f s", self._what(), what,
                           msg.stream, now - self._last_frame)  # fmt: skip
            self._any_frame = True
            self._last_frame = now
            if self._udp is not None:
                self._refused_before = self._udp.refused
            model = self.models.get(msg.stream)
            if model is None or model.model != msg.model or len(model.names) != len(msg.state):
                self.stats.undecodable += 1
                return
            r = Received(msg, model.names, inc.recv_ns, len(inc.payload))
            if not self._labeled.get(msg.stream) and (msg.state == MarkerState.OBSERVED).any():
                self._labeled[msg.stream] = True
            self.stats.add(r)
            self._out.put(r)
        elif isinstance(msg, ModelMsg):
            self.models[msg.stream] = msg
        elif isinstance(msg, StatusMsg):
            if self.silence_s is not None and self.status.get(msg.stream) != msg.state:
                why = ""
                if msg.state == "booting" and msg.stream not in self.models:
                    # no model message (yet): a stream that starts from labeled init frames,
                    # or a model stream whose model message comes with its first frames
                    why = (" (no one labeled yet: it boots its performers from a model, or "
                           "waits for labeled init frames to train its labeler)")  # fmt: skip
                elif msg.state == "booting":
                    why = " (booting its performers from the model: no one labeled yet)"
                elif msg.state == "training_failed":
                    why = (" (training on its labeled init frames failed or ran over "
                           "train_budget_s: the service log says why; it waits for new "
                           "labeled init frames)")  # fmt: skip
                elif msg.state in ("lost", "degraded") and not self._labeled.get(msg.stream):
                    # a model stream that has not booted anyone yet reads as lost: say so
                    why = (" (no marker labeled yet: the service is booting its performers "
                           "from the model, or the model does not match them)")  # fmt: skip
                # (a stream turning online is news, not a warning: the viewer logged it so)
                level = logging.INFO if msg.state == "online" else logging.WARNING
                self._warn("subscribe %s: stream %s is %s%s", self._what(), msg.stream,
                           msg.state, why, level=level)  # fmt: skip
            self.status[msg.stream] = msg.state
            self._status_changed.set()
        elif isinstance(msg, ChallengeMsg):
            # UDP: the service confirms our address before it sends us frames
            self._token = msg.token
            if self._transport is not None and self.endpoint.scheme == "udp":
                self._send_subscribe()

    async def wait_status(self, stream: str, state: str | tuple[str, ...], timeout: float) -> bool:
        """True once ``stream`` reports ``state`` (e.g. ``online``; a tuple: any of them, e.g.
        :data:`READY` for a service ready to label it) within ``timeout`` s."""
        wanted = (state,) if isinstance(state, str) else tuple(state)
        try:
            async with asyncio.timeout(timeout):
                while self.status.get(stream) not in wanted:
                    self._status_changed.clear()
                    await self._status_changed.wait()
        except TimeoutError:
            return False
        return True

    async def frames(self) -> AsyncIterator[Received]:
        while True:
            yield await self._out.get()

    def drain(self) -> list[Received]:
        """Every frame received and not consumed yet (no waiting)."""
        out = []
        while (r := self._out.get_nowait()) is not None:
            out.append(r)
        return out


def ms(value: float) -> str:
    """A latency for a reader: ``1.23 ms``, or ``-`` when there is none (no frame)."""
    return "-" if value != value else f"{value:.2f} ms"


class Recorder:
    """Collects labeled frames for writing a C3D (observed and recovered positions).

    The file's rate is the stream's, measured from the frames' ``t`` (median step between
    consecutive ``seq``), not the model's: a stream sent at another rate than the model was
    trained at (``replay --downsample``) keeps its duration. Frames missing in a ``seq`` gap
    (lost on the network, dropped by the service) are written as missing samples, up to
    :attr:`MAX_FILL_S` of them, so later frames stay at their time; a larger jump or a restart
    (``seq`` back: a second replay) just continues the file. One stream is recorded, the
    first one heard (a URL without a stream hears every stream: their frames interleaved in
    one file, tens of thousands of missing frames filled between their ``seq``); the others'
    frames are counted and named in :meth:`report`.
    """

    MAX_FILL_S = 10.0

    def __init__(self) -> None:
        self.stream: str | None = None  # the stream recorded (the first one heard)
        self.others: dict[str, int] = {}  # frames of other streams, not recorded
        self.names: tuple[str, ...] | None = None
        self.rate: float | None = None
        self.positions: list[np.ndarray] = []
        self.skipped = 0
        self.written: Path | None = None  # where write() put the frames (.npz past a C3D's 65,535)
        self.filled = 0  # missing frames written for seq gaps
        self._last: tuple[int, float] | None = None  # seq, t of the last frame kept
        self._steps: list[float] = []  # t steps between consecutive seq

    def add(self, r: Received, rate: float) -> None:
        if self.stream is None:
            self.stream = r.msg.stream
        if r.msg.stream != self.stream:
            self.others[r.msg.stream] = self.others.get(r.msg.stream, 0) + 1
            return
        if self.names is None:
            self.names, self.rate = r.names, rate
        if r.names != self.names:
            self.skipped += 1  # model changed mid-recording: keep the first model's frames
            return
        seq, t = r.msg.seq, r.msg.t
        if self._last is not None:
            step = seq - self._last[0]
            dt = t - self._last[1]
            if step == 1 and dt > 0 and len(self._steps) < 10_000:
                self._steps.append(dt)
            elif 1 < step <= 1 + self.MAX_FILL_S * self.file_rate() and dt > 0:
                gap = np.full_like(r.msg.positions, np.nan)
                self.positions.extend([gap] * (step - 1))
                self.filled += step - 1
        self._last = (seq, t)
        self.positions.append(r.msg.positions)

    def file_rate(self) -> float:
        """The stream's rate from its ``t`` steps; the rate given to :meth:`add` before two
        consecutive frames arrived."""
        if self._steps:
            return round(1.0 / float(np.median(self._steps)), 3)
        return self.rate or 1.0

    def report(self, path, n: int) -> str:
        """The line the subscriber prints after :meth:`write` returned ``n``: what was written
        and what was not (frames of a later model or of other streams, missing frames written
        for seq gaps)."""
        if not n:
            why = (
                f" ({plural(self.skipped, 'frame')} of a later model not recorded)"
                if self.skipped
                else ""
            )
            return f"no frames received: {path} not written{why}"
        rate = self.file_rate()
        line = f"wrote {plural(n, 'frame')} of stream {self.stream} to {path} at {rate:g} Hz"
        if self.filled:
            line += f"; {plural(self.filled, 'frame')} lost in seq gaps written as missing"
        if self.skipped:
            line += (
                f"; {plural(self.skipped, 'frame')} of a later model (marker set changed "
                "mid-session) "
                "not recorded"
            )
        if self.others:
            names = ", ".join(sorted(self.others))
            line += (
                f"; {plural(sum(self.others.values()), 'frame')} of other streams ({names}) not "
                "recorded: one file holds one stream (name it in the URL: "
                "udp://HOST:PORT/STREAM)"
            )
        return line

    def write(self, path) -> int:
        from labeler_service.capture import Capture, c3d_frames_fit, write_capture
        from labeler_service.errors import CaptureError

        if not self.positions or self.names is None:
            return 0
        rate = self.file_rate()
        cap = Capture(np.stack(self.positions), self.names, rate, source=str(path))
        try:
            c3d_frames_fit(path, cap.n_frames)
        except CaptureError as exc:  # a session longer than a C3D holds: nothing is lost
            path = Path(path).with_suffix(".npz")
            log.warning("%s; written as %s instead", exc, path)
        write_capture(cap, path)
        self.written = path
        return len(self.positions)
