"""Capture replay: a labeled capture becomes the unlabeled stream a live system would send.

The capture goes through :func:`labeler_service.scenes.corrupt.corrupt` (shuffle, optional
down-sampling, gaps, drop-outs, ghosts, jitter; everything seeded), then every frame is encoded
(protocol v1, sender stamp ``sent`` = ``time.time_ns()`` at send) and sent at the capture rate
times ``speed``. The first ``init_frames`` frames carry their true labels (the training window;
ghosts get ``nil``). Pacing is against absolute deadlines (``perf_counter``), so a late frame
never makes the next ones late; ``speed=0`` sends as fast as possible. A send more than
``STALL_S`` late (the sender was paused, the machine froze) restarts the schedule from that
frame: the replay goes on where it stopped, at the capture rate, instead of sending the frames
due meanwhile in a burst (which overflows the service's queues).

``loops > 1`` plays the capture forward, then backward, and so on (continuous motion, ``t`` and
``seq`` keep increasing) for long soak runs without a huge scene in memory.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labeler_service.capture import Capture, read_capture
from labeler_service.errors import ConfigError
from labeler_service.scenes.corrupt import CorruptionSpec, StreamFrames, corrupt
from labeler_service.service.protocol import encode_frame
from labeler_service.service.settings import MqttSettings, check_stream_name
from labeler_service.service.transports.url import Endpoint, parse_endpoint

SendFn = Callable[[bytes], Awaitable[bool]]

log = logging.getLogger(__name__)
REFUSED_S = 1.0  # a UDP send this soon after a "connection refused" report counts as failed
#: a send this late (s) is a stall (the sender paused, the machine froze), not jitter: the
#: schedule restarts from it instead of sending the missed frames at once
STALL_S = 0.5


def prepare(source: str | Path | Capture, spec: CorruptionSpec, up: str = "z") -> StreamFrames:
    """Reads (if needed) and corrupts a capture into stream frames with their truth."""
    cap = source if isinstance(source, Capture) else read_capture(source, up=up)
    return corrupt(cap, spec)


@dataclass
class ReplayStats:
    sent: int = 0
    failed: int = 0
    seconds: float = 0.0
    max_late_ms: float = 0.0
    #: stalls after which the schedule restarted (``STALL_S``), and the seconds they lasted
    stalls: int = 0
    stalled_s: float = 0.0

    @property
    def rate(self) -> float:
        return self.sent / self.seconds if self.seconds > 0 else 0.0


def init_labels(frames: StreamFrames, f: int) -> list[str | None]:
    names = frames.marker_names
    return [names[i] if i >= 0 else None for i in frames.truth[f].tolist()]


def frame_order(n: int, loops: int) -> np.ndarray:
    """Frame indices for ``loops`` passes, alternating forward and backward (ping-pong)."""
    if n == 1:
        return np.zeros(loops, dtype=np.intp)
    fwd = np.arange(n, dtype=np.intp)
    parts = [fwd] + [fwd[::-1][1:] if k % 2 else fwd[1:] for k in range(1, loops)]
    return np.concatenate(parts)


def loops_to_cover(n_frames: int, n_total: int) -> int:
    """Passes of :func:`frame_order` over ``n_frames`` frames that give at least ``n_total``."""
    if n_frames == 1:
        return max(1, n_total)
    return max(1, -(-(n_total - 1) // (n_frames - 1)))


async def replay(
    frames: StreamFrames,
    send: SendFn,
    stream: str = "default",
    init_frames: int = 50,
    speed: float = 1.0,
    loops: int = 1,
    seq0: int = 0,
    on_frame: Callable[[int, int], None] | None = None,
    max_frames: int | None = None,
) -> ReplayStats:
    """Sends ``frames`` (see the module docstring); ``on_frame(seq, frame_index)`` after each.

    ``max_frames`` stops after that many frames (e.g. a duration cut from a looped scene).
    """
    check_pace(speed, loops)
    order = frame_order(frames.n_frames, loops)[:max_frames]
    dt = 1.0 / frames.rate
    stats = ReplayStats()
    t_start = time.perf_counter()
    for k, f in enumerate(order):
        if speed > 0:
            target = t_start + k * dt / speed
            delay = target - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            else:
                stats.max_late_ms = max(stats.max_late_ms, -delay * 1e3)
                if -delay > STALL_S:
                    t_start -= delay  # this frame is on time again
                    stats.stalls += 1
                    stats.stalled_s += -delay
                    log.warning(
                        "replay: %.1f s behind schedule (paused or stalled): going on from "
                        "frame %d at the capture rate, not with a burst of the frames due "
                        "meanwhile", -delay, k,
                    )  # fmt: skip
        elif k % 64 == 0:
            await asyncio.sleep(0)
        labels = init_labels(frames, int(f)) if k < init_frames else None
        seq = seq0 + k
        payload = encode_frame(stream, seq, k * dt, frames.points[f], labels)
        if await send(payload):
            stats.sent += 1
        else:
            stats.failed += 1
        if on_frame is not None:
            on_frame(seq, int(f))
    stats.seconds = time.perf_counter() - t_start
    return stats


def check_pace(speed: float, loops: int) -> None:
    """Refuses a playback speed below 0 (or not finite) and fewer than one loop."""
    if speed < 0 or not np.isfinite(speed):
        raise ConfigError(f"--speed must be >= 0 (0 = as fast as possible), got {speed}")
    if loops < 1:
        raise ConfigError(f"--loops must be >= 1, got {loops}")


def replay_stream(url: str, stream: str | None = None) -> str:
    """The stream a replay to ``url`` sends to: ``stream`` (``--stream``), else the URL's, else
    ``default``. Raises :class:`ConfigError` for a bad URL or stream name (the service refuses
    every frame of a stream name it cannot take, so a replay would send them all for nothing)."""
    ep = parse_endpoint(url)
    if stream is not None:
        try:
            check_stream_name(stream)  # (the service's own rule)
        except ValueError as exc:
            raise ConfigError(
                f"--stream {stream!r}: bad stream name ({exc}; the service refuses frames of "
                "such a stream)"
            ) from None
    return stream or ep.stream or "default"


def mqtt_settings_for(ep: Endpoint, base: MqttSettings | None = None) -> MqttSettings:
    """MQTT settings for a tool URL (credentials and TLS from the URL override ``base``)."""
    data = (base or MqttSettings()).model_dump()
    data.update(enabled=True, host=ep.host, port=ep.port)
    if ep.username is not None:
        data.update(username=ep.username, password=ep.password)
    if ep.tls:
        data["tls"] = True
    return MqttSettings(**data)


@asynccontextmanager
async def open_sender(
    url: str,
    mqtt: MqttSettings | None = None,
    connect_timeout: float = 10.0,
    stream: str | None = None,
) -> AsyncIterator[tuple[SendFn, str]]:
    """``(send, stream)`` for a replay URL. MQTT waits up to ``connect_timeout`` to connect.

    ``stream`` overrides the URL's stream (else ``default``); over MQTT the frames go to that
    stream's topic, so topic and payload agree when the caller encodes the returned name.
    """
    ep = parse_endpoint(url)
    stream = replay_stream(url, stream)
    if ep.scheme == "udp":
        from labeler_service.service.transports.udp import UdpClient

        async with UdpClient(ep.host, ep.port) as udp:
            seen = [0, -np.inf]  # refusals counted so far, monotonic time of the last one

            async def send_udp(payload: bytes) -> bool:
                # the kernel reports "connection refused" (ICMP port unreachable: nothing
                # listens there) on a later receive or send, not for each datagram: a send
                # within REFUSED_S of the last report counts as failed (sent as fast as
                # possible, every other datagram read a report, and half were called sent)
                ok = udp.send(payload)
                now = time.monotonic()
                if udp.refused != seen[0]:
                    if now - seen[1] > REFUSED_S:
                        log.warning("replay: nothing listens at udp://%s:%d (connection "
                                    "refused); frames are counted as failed",
                                    ep.host, ep.port)  # fmt: skip
                    seen[:] = [udp.refused, now]
                return ok and now - seen[1] > REFUSED_S

            yield send_udp, stream
        return
    from labeler_service.service.transports.mqtt import MqttEndpoint

    async with MqttEndpoint(mqtt_settings_for(ep, mqtt), stream) as client:
        if not await client.wait_connected(connect_timeout):
            raise ConfigError(f"replay: {client.trouble() or 'not connected'}")

        async def send_mqtt(payload: bytes) -> bool:
            return await client.publish("unlabeled", payload)

        yield send_mqtt, stream
