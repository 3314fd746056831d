"""The one way a long-running command learns to stop: SIGINT/SIGTERM, or ``--seconds``."""

from __future__ import annotations

import asyncio
import signal


def stop_event(seconds: float | None = None, stop: asyncio.Event | None = None) -> asyncio.Event:
    """An event (``stop``, or a new one) set by SIGINT or SIGTERM, or after ``seconds``; call it
    from the running event loop."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if seconds is not None:
        loop.call_later(seconds, stop.set)
    return stop


def release_signals() -> None:
    """Gives SIGINT/SIGTERM back to their defaults (after :func:`stop_event`)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.remove_signal_handler(sig)
