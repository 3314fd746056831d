"""What the live view sends a browser, and when: the decimation and per-browser drop policy,
the sliding windows of the overlay, and the page's message formats (``docs/viewer.md``).

Pure and clock-free: every time is passed in, so the policy is tested without sleeping
(``tests/tools/test_view.py``). The server that applies it is :mod:`labeler_service.tools.view`.
"""

from __future__ import annotations

import json
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np

from labeler_service.errors import ConfigError
from labeler_service.labeling.frame import MarkerState
from labeler_service.service.protocol import ModelMsg
from labeler_service.tools.subscribe import Received, percentiles

T = TypeVar("T")


# ----------------------------------------------------------------------------- policy
#: A slot is due this much early: rounding must not push a frame to the next arrival.
_SLACK_S = 1e-6


class Decimator(Generic[T]):
    """Forwards at most one item per ``1 / fps`` seconds, always the newest one offered.

    ``offer`` replaces a pending item (the replaced one is counted in ``decimated``); ``take``
    returns the pending item once its slot has come (leading edge: an idle decimator forwards
    at once; trailing edge: the last item of a burst is forwarded one period later, never
    lost). The clock is passed in, so the policy is tested without sleeping.
    """

    def __init__(self, fps: float) -> None:
        if not fps > 0:
            raise ConfigError(f"viewer fps must be > 0, got {fps}")
        self.period = 1.0 / fps
        self.decimated = 0
        self._pending: T | None = None
        self._next = float("-inf")

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def offer(self, item: T) -> None:
        if self._pending is not None:
            self.decimated += 1
        self._pending = item

    def wait_s(self, now: float) -> float:
        """Seconds until ``take`` may return the pending item (0: now)."""
        return max(0.0, self._next - now)

    def take(self, now: float) -> T | None:
        if self._pending is None or now < self._next - _SLACK_S:
            return None
        item, self._pending = self._pending, None
        # slots keep a steady grid while frames flow; after an idle spell it restarts from now
        nxt = self._next + self.period
        self._next = nxt if now < nxt else now + self.period
        return item


@dataclass
class Outbox:
    """What one browser connection still has to receive: a drop-oldest queue of ``depth``
    encoded frames and a window of at most ``window`` frames in flight (sent, not acked).

    The page acknowledges the ``seq`` it drew; an ack clears every in-flight frame up to it
    (with a window above 1 the page may draw only the newest of two that arrived in one
    display refresh; it counts the other as skipped).
    """

    depth: int = 1
    window: int = 1
    dropped: int = 0
    sent: int = 0
    _queue: deque[tuple[int, bytes]] = field(default_factory=deque)
    _in_flight: deque[int] = field(default_factory=deque)

    def __post_init__(self) -> None:
        if self.depth < 1 or self.window < 1:
            raise ConfigError(f"outbox depth and window must be >= 1, got {self.depth}, "
                              f"{self.window}")  # fmt: skip

    def push(self, seq: int, data: bytes) -> int | None:
        """Queues a frame; returns the ``seq`` of the frame it pushed out (dropped), if any."""
        old = None
        if len(self._queue) >= self.depth:
            old = self._queue.popleft()[0]
            self.dropped += 1
        self._queue.append((seq, data))
        return old

    def pop(self) -> tuple[int, bytes] | None:
        """The next frame to send, or ``None`` (nothing queued, or the window is full)."""
        if not self._queue or len(self._in_flight) >= self.window:
            return None
        seq, data = self._queue.popleft()
        self._in_flight.append(seq)
        self.sent += 1
        return seq, data

    def ack(self, seq: int) -> None:
        while self._in_flight and self._in_flight[0] <= seq:
            self._in_flight.popleft()

    @property
    def queued(self) -> int:
        return len(self._queue)

    @property
    def in_flight(self) -> int:
        return len(self._in_flight)


class Window:
    """Samples of the last ``seconds`` (input rate, latency percentiles); clock passed in."""

    def __init__(self, seconds: float = 5.0) -> None:
        self.seconds = seconds
        self._t: deque[float] = deque()
        self._v: deque[float] = deque()

    def add(self, now: float, value: float = 0.0) -> None:
        self._t.append(now)
        self._v.append(value)
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._t and self._t[0] < now - self.seconds:
            self._t.popleft()
            self._v.popleft()

    def rate(self, now: float) -> float:
        """Samples per second over the window (over the span seen, while it is shorter)."""
        self._trim(now)
        if len(self._t) < 2:
            return 0.0
        span = min(self.seconds, now - self._t[0])
        return len(self._t) / span if span > 0 else 0.0

    def percentiles(self, now: float, qs=(50.0, 99.0)) -> dict[str, float]:
        self._trim(now)
        return percentiles(self._v, qs)


# ----------------------------------------------------------------------------- encoding
def model_message(model: ModelMsg) -> str:
    """The page's model message (JSON text): names, subject slices, rigid bodies, rate."""
    return json.dumps(
        {
            "type": "model",
            "stream": model.stream,
            "model": model.model,
            "names": list(model.names),
            "subjects": [list(s) for s in model.subjects],
            "bodies": [list(b) for b in model.bodies],
            "rate": model.rate,
        }
    )


def encode_view_frame(r: Received) -> bytes:
    """One frame for the page (binary WebSocket message, little-endian)::

        u32 H | H bytes JSON header, space-padded to a multiple of 4 |
        f32 positions (M x 3, NaN = missing) | f32 unlabeled (K x 3) | u8 state (M)

    The header holds ``seq``, ``t``, ``model``, ``m``, ``k`` and the frame's end-to-end
    latency ``lat_ms`` (sender stamp -> viewer receipt; null when the sender sent no stamp).
    """
    m = r.msg
    lat = r.latency_ms
    header = json.dumps(
        {
            "seq": m.seq,
            "t": m.t,
            "model": m.model,
            "m": len(m.state),
            "k": len(m.unlabeled),
            "lat_ms": None if lat is None else round(lat, 3),
        }  # fmt: skip
    ).encode()
    header += b" " * (-(4 + len(header)) % 4)
    return b"".join(
        (
            struct.pack("<I", len(header)),
            header,
            np.ascontiguousarray(m.positions, dtype="<f4").tobytes(),
            np.ascontiguousarray(m.unlabeled, dtype="<f4").tobytes(),
            np.ascontiguousarray(m.state, dtype="u1").tobytes(),
        )
    )


def frame_counts(r: Received, subjects: tuple[tuple[str, int, int], ...]) -> dict:
    """What the page should draw for a frame: markers per subject (observed + recovered),
    observed and recovered markers, unlabeled points (the browser test compares
    ``viewerState`` to this)."""
    st = r.msg.state
    return {
        "drawn": {
            s: int(np.count_nonzero(st[a : a + n] != MarkerState.MISSING)) for s, a, n in subjects
        },  # fmt: skip
        "observed": int(np.count_nonzero(st == MarkerState.OBSERVED)),
        "recovered": int(np.count_nonzero(st == MarkerState.RECOVERED)),
        "unlabeled": len(r.msg.unlabeled),
    }
