"""``mocap-labeler serve [--config FILE]``: the streaming labeling service.

Settings come from the file (TOML or JSON) and ``MOCAP_`` environment variables (see
``docs/service.md``). Prints ``ready ...`` on stdout once the kernels are warm and the
transports are open; SIGINT/SIGTERM shut it down gracefully (status ``offline``, tasks
cancelled and awaited), also during the start (which can take minutes the first time).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path

from labeler_service.cli.stopping import release_signals, stop_event

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None, help="settings file (.toml or .json)")
    p.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level (default INFO)",
    )  # fmt: skip


async def serve(
    settings, stop: asyncio.Event | None = None, abandon: Callable[[], None] | None = None
) -> bool:
    """Runs the server until ``stop`` is set or SIGINT/SIGTERM arrives; False when the stop
    came during the start (the server shut down without serving).

    A start can take minutes (the first after an install compiles the kernels) and its work
    runs in threads that cannot be interrupted: a stop during it cancels the start at once
    (status ``offline``, transports closed) and then calls ``abandon`` (the command ends the
    process there instead of waiting for the thread)."""
    # the signals first: importing the server takes most of a second, and a SIGINT then went
    # to asyncio.run's own handler (KeyboardInterrupt, exit 130, not the documented 0)
    stop = stop_event(stop=stop)
    try:
        from labeler_service.service.server import Server

        srv = Server(settings)
        srv.compile_apart = True  # (the kernels compile in a child: docs/service.md)
        if not await _start_unless_stopped(srv, stop):
            log.warning("stopped during the start; the service did not serve")
            if abandon is not None:
                abandon()
            return False
        try:
            parts = []
            for t in srv.transports or []:
                host, port = t.address
                parts.append(f"{t.name}://{host}:{port}")
            if srv.metrics_port is not None:
                parts.append(f"metrics http://{settings.metrics_host}:{srv.metrics_port}/metrics")
            # the long-lived objects (kernels, templates, state) leave the GC's generations, so
            # collections during streaming only scan per-frame garbage
            gc.collect()
            gc.freeze()
            print(f"ready {' '.join(parts)}", flush=True)
            await stop.wait()
        finally:
            await srv.__aexit__(None, None, None)
        return True
    finally:
        release_signals()


async def _start_unless_stopped(srv, stop: asyncio.Event) -> bool:
    """Enters ``srv`` (its start) unless ``stop`` is set first: then the start is cancelled
    (it shuts down what it opened) and the answer is False. A failed start raises."""
    start = asyncio.ensure_future(srv.__aenter__())
    halt = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({start, halt}, return_when=asyncio.FIRST_COMPLETED)
    except BaseException:  # serve() itself cancelled: the start must not go on alone
        await _cancelled(start)
        raise
    finally:
        halt.cancel()
    if start.done():
        start.result()
        return True
    await _cancelled(start)
    return False


async def _cancelled(task: asyncio.Future) -> None:
    """Cancels ``task`` and waits for it to end (the start shuts down what it opened)."""
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def _leave_now() -> None:
    """Ends the process after a stop during the start, without waiting for the start's
    threads (a kernel compilation runs to its end otherwise, for minutes on a first start)."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def run(args: argparse.Namespace) -> int:
    from labeler_service.service.settings import load_settings

    logging.basicConfig(
        level=args.log_level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    settings = load_settings(args.config)
    asyncio.run(serve(settings, abandon=_leave_now))
    return 0
