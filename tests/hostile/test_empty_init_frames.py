"""Labeled init frames that hold no point (``replay --init-frames 50`` of a take that starts
before anyone is in view): the service's training error said "the init frames carry no labels",
and the user had sent labels; it now says the init frames hold no labeled point."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
from hostile.helpers import run, settings

from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport


def _training_failure_log(caplog, init_points: np.ndarray, labels: list, then: int = 0) -> str:
    """Five init frames of ``init_points`` with ``labels``, then an unlabeled frame; the log
    once training has failed (and, with ``then``, once that many more unlabeled frames were
    dropped as ``no_model``)."""
    caplog.set_level(logging.WARNING)
    pts = np.random.default_rng(0).normal(scale=300.0, size=(12, 3)).astype(np.float32)

    async def until(srv, reason: str, count: int) -> None:
        async with asyncio.timeout(10):
            while srv.metrics.drops(reason) < count:
                await asyncio.sleep(0.05)

    async def go():
        mem = MemoryTransport()
        async with Server(settings(labeler="baseline"), [mem]) as srv:
            for k in range(5):
                mem.inject(encode_frame("default", k, k / 100, init_points, labels))
            mem.inject(encode_frame("default", 5, 0.05, pts))
            await until(srv, "training_failed", 1)
            for k in range(then):
                mem.inject(encode_frame("default", 6 + k, 0.06 + k / 100, pts))
            await until(srv, "no_model", then)

    run(go(), timeout=30)
    return "\n".join(r.getMessage() for r in caplog.records)


def test_init_frames_without_points_are_named_as_such(caplog):
    text = _training_failure_log(caplog, np.zeros((0, 3), np.float32), [])
    assert "the init frames hold no labeled point" in text, text
    assert "carry no labels" not in text


def test_init_frames_whose_labels_are_all_nil_are_named_as_such(caplog):
    # points were sent, every label nil: the hint must not blame an empty volume
    pts = np.random.default_rng(1).normal(scale=300.0, size=(12, 3)).astype(np.float32)
    text = _training_failure_log(caplog, pts, [None] * 12)
    assert "60 points, every label nil" in text, text
    assert "before anyone is in view" not in text


def test_frames_after_a_failed_training_are_not_said_to_lack_init_frames(caplog):
    """After ``training_failed`` the next unlabeled frames were dropped as ``no_model`` with
    "no model, no labeled init frames before them": the stream had sent them. The line now says
    the training failed and asks for new labeled init frames."""
    _training_failure_log(caplog, np.zeros((0, 3), np.float32), [], then=1)
    lines = [
        r.getMessage() for r in caplog.records if "nothing to start the stream" in r.getMessage()
    ]
    assert lines, [r.getMessage() for r in caplog.records]
    assert "its training on the labeled init frames failed" in lines[-1], lines[-1]
    assert "no labeled init frames before them" not in lines[-1]
    assert "send new labeled init frames" in lines[-1]
