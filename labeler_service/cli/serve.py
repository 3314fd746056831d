"""``mocap-labeler serve [--config FILE]``: the streaming labeling service.

Settings come from the file (TOML or JSON) and ``MOCAP_`` environment variables (see
``docs/service.md``). Prints ``ready ...`` on stdout once the kernels are warm and the
transports are open; SIGINT/SIGTERM shut it down gracefully (status ``offline``, tasks
cancelled and awaited).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import logging
import sys
from pathlib import Path

from labeler_service.cli.stopping import release_signals, stop_event


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None, help="settings file (.toml or .json)")
    p.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level (default INFO)",
    )  # fmt: skip


async def serve(settings, stop: asyncio.Event | None = None) -> None:
    """Runs the server until ``stop`` is set or SIGINT/SIGTERM arrives."""
    from labeler_service.service.server import Server

    stop = stop_event(stop=stop)
    try:
        async with Server(settings) as srv:
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
        release_signals()


def run(args: argparse.Namespace) -> int:
    from labeler_service.service.settings import load_settings

    logging.basicConfig(
        level=args.log_level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    settings = load_settings(args.config)
    asyncio.run(serve(settings))
    return 0
