"""Shared helpers of the service tests: synthetic streams, a scripted labeler, async runners."""

from __future__ import annotations

import asyncio
import time

import numpy as np
from synthetic import moving_clusters

from labeler_service.capture import Capture
from labeler_service.labeling.frame import LabeledFrame, MarkerState
from labeler_service.service.protocol import encode_frame

__all__ = ["SlowLabeler", "frames_of", "moving_clusters", "run", "stream_payloads", "until"]


def run(coro, timeout: float = 60.0):
    """Runs a coroutine with a hard time limit (network tests stay bounded)."""

    async def bounded():
        async with asyncio.timeout(timeout):
            return await coro

    return asyncio.run(bounded())


async def until(predicate, what: str, timeout: float = 30.0, poll: float = 0.01) -> None:
    """Waits until ``predicate()`` is true: an event, not a clock, decides when a test goes on.

    ``timeout`` is generous (a loaded machine is slow, not wrong); on expiry the test fails
    naming ``what`` it waited for.
    """
    try:
        async with asyncio.timeout(timeout):
            while not predicate():
                await asyncio.sleep(poll)
    except TimeoutError:
        raise AssertionError(f"timed out after {timeout:g} s waiting for {what}") from None


def frames_of(cap: Capture, rng: np.random.Generator):
    """Shuffled frames of a capture: ``(points, truth indices)`` per frame, NaN dropped."""
    out = []
    for f in range(cap.n_frames):
        p = cap.positions[f]
        idx = np.flatnonzero(~np.isnan(p).any(axis=1)).astype(np.int32)
        order = rng.permutation(idx.size)
        out.append((p[idx[order]], idx[order]))
    return out


def stream_payloads(
    cap: Capture, rng: np.random.Generator, init: int, stream: str = "default", seq0: int = 0
) -> list[bytes]:
    """Encoded input frames: the first ``init`` carry labels."""
    out = []
    for f, (p, truth) in enumerate(frames_of(cap, rng)):
        labels = [cap.labels[i] for i in truth] if f < init else None
        out.append(encode_frame(stream, seq0 + f, f / cap.rate, p, labels))
    return out


class SlowLabeler:
    """A labeler that takes ``delay_s`` per frame and labels nothing (backpressure tests)."""

    def __init__(self, marker_names, rate, delay_s: float = 0.0, fail_on: set[int] | None = None):
        self._names = tuple(marker_names)
        self.delay_s = delay_s
        self.calls = 0
        self.fail_on = fail_on or set()

    @property
    def marker_names(self):
        return self._names

    def warmup(self):
        pass

    def body_extent(self):
        return np.full(len(self._names), np.nan)

    def process(self, points, t, labels=None):
        self.calls += 1
        if self.calls in self.fail_on:
            raise RuntimeError(f"scripted failure on call {self.calls}")
        if self.delay_s:
            time.sleep(self.delay_s)
        m = len(self._names)
        return LabeledFrame(
            t=t,
            point_labels=np.full(len(points), -1, dtype=np.int32),
            positions=np.full((m, 3), np.nan, dtype=np.float32),
            state=np.full(m, MarkerState.MISSING, dtype=np.uint8),
        )


def all_handled(srv, sub, stream: str, total: int):
    """A predicate for :func:`until`: ``total`` frames of ``stream`` labeled or dropped by the
    server, and every labeled one received by the subscriber ``sub``."""

    def done() -> bool:
        m = srv.metrics
        out = m.value("mocap_frames_out_total", stream=stream)
        return out + m.drops() >= total and sub.stats.frames >= out

    return done
