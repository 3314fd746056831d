"""Shared helpers of the hostile-input tests: a server over the memory transport, accuracy."""

from __future__ import annotations

import asyncio

import numpy as np
from service.helpers import frames_of, moving_clusters, run

from labeler_service.capture import Capture
from labeler_service.labeling.frame import MarkerState
from labeler_service.service.protocol import LabeledMsg, decode, encode_frame
from labeler_service.service.settings import load_settings

__all__ = [
    "accuracy", "collect", "frames_of", "model_names", "moving_clusters", "observed_fraction",
    "payloads", "run", "settings",
]  # fmt: skip


def settings(**over):
    base = {"labeler": "online", "metrics_port": None, "warmup": False, "queue_size": 4096}
    base.update(over)
    return load_settings(**base)


def payloads(
    cap: Capture,
    rng: np.random.Generator,
    init: int,
    stream: str = "default",
    seq0: int = 0,
    t0: float = 0.0,
    frames: range | None = None,
) -> list[bytes]:
    """Encoded frames of ``cap`` (shuffled points, the first ``init`` with labels); the truth
    of each point travels in a side table: :func:`accuracy` reads it from the capture."""
    out = []
    fr = frames_of(cap, rng)
    for k, f in enumerate(frames if frames is not None else range(cap.n_frames)):
        p, truth = fr[f]
        labels = [cap.labels[i] for i in truth] if k < init else None
        out.append(encode_frame(stream, seq0 + k, t0 + k / cap.rate, p, labels))
    return out


async def collect(srv, mem, stream: str | None = None, quiet: float = 0.3) -> list[LabeledMsg]:
    """Every labeled message sent, once the server is idle (queues empty, no training job,
    nothing sent for ``quiet`` seconds)."""
    n = -1
    while True:
        await asyncio.sleep(quiet)
        busy = any(len(q) for q in srv._queues.values()) or srv.background.running
        if not busy and len(mem.sent) == n:
            break
        n = len(mem.sent)
    out = []
    for s, kind, payload, _ in mem.sent:
        if kind == "labeled" and (stream is None or s == stream):
            out.append(decode(payload))
    return out


def observed_fraction(msgs: list[LabeledMsg]) -> float:
    """Mean fraction of model markers marked observed in ``msgs``."""
    if not msgs:
        return 0.0
    return float(np.mean([np.mean(m.state == MarkerState.OBSERVED) for m in msgs]))


def model_names(mem, stream: str = "default") -> tuple[str, ...]:
    """Marker names of the last model message sent for ``stream``."""
    names: tuple[str, ...] = ()
    for s, kind, payload, _ in mem.sent:
        if kind == "model" and s == stream:
            names = decode(payload).names
    return names


def accuracy(msgs: list[LabeledMsg], names, cap: Capture, frame_of_seq) -> float:
    """Observed markers at the true position of their label / true visible markers, over
    ``msgs`` (``names``: model order; ``frame_of_seq(seq)`` -> capture frame or None)."""
    col = np.array([cap.labels.index(n) for n in names])
    ok = total = 0
    for m in msgs:
        f = frame_of_seq(m.seq)
        if f is None:
            continue
        truth = cap.positions[f][col]
        vis = ~np.isnan(truth).any(axis=1)
        total += int(vis.sum())
        obs = (m.state == MarkerState.OBSERVED) & vis
        close = np.linalg.norm(m.positions[obs] - truth[obs], axis=1) < 1e-3
        ok += int(close.sum())
    return ok / max(total, 1)
