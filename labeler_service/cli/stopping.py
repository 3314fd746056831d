"""The one way a long-running command learns to stop: SIGINT/SIGTERM/SIGHUP, or ``--seconds``.

SIGHUP (the terminal that started it closed) stops it as SIGTERM does: it killed ``serve``
with no ``stopped`` line and no ``offline`` status to its subscribers (exit 129). A SIGHUP the
command was started ignoring (``nohup``) stays ignored: that is asking to outlive the terminal.
"""

from __future__ import annotations

import asyncio
import signal


def _signals() -> tuple[signal.Signals, ...]:
    """The signals that stop a command: SIGINT, SIGTERM, and SIGHUP unless it is ignored."""
    hup = getattr(signal, "SIGHUP", None)  # (no SIGHUP on Windows)
    keep = hup is not None and signal.getsignal(hup) is not signal.SIG_IGN
    return (signal.SIGINT, signal.SIGTERM, *((hup,) if keep else ()))


def stop_event(seconds: float | None = None, stop: asyncio.Event | None = None) -> asyncio.Event:
    """An event (``stop``, or a new one) set by SIGINT, SIGTERM or SIGHUP, or after
    ``seconds``; call it from the running event loop."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in _signals():
        loop.add_signal_handler(sig, stop.set)
    if seconds is not None:
        loop.call_later(seconds, stop.set)
    return stop


def release_signals() -> None:
    """Gives the stopping signals back to their defaults (after :func:`stop_event`)."""
    loop = asyncio.get_running_loop()
    for sig in _signals():  # (a SIGHUP left ignored was never taken: still ignored)
        loop.remove_signal_handler(sig)
