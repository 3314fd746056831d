"""``mocap-labeler view --from URL [--port 8765] [--host 127.0.0.1]``: live 3D view in a browser.

Subscribes to the labeled stream like ``subscribe`` and serves a page (three.js, vendored) on
``http://HOST:PORT/`` that draws the markers live; see ``docs/viewer.md``. Loopback only by
default: ``--host`` exposes it to the network (read-only, no authentication: a warning says so).
Runs until Ctrl-C / SIGTERM, at a lower CPU priority (``--nice``, default 10) so that a
viewer sharing the service's machine never takes the CPU from it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys

from labeler_service.cli.stopping import stop_event


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--from", dest="url", required=True, metavar="URL",
                   help="udp://service-host:port[/stream] or mqtt://host:port/stream")  # fmt: skip
    p.add_argument("--port", type=int, default=8765, help="HTTP port of the page (0: any free)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default loopback; anything else exposes the "
                        "read-only view without authentication)")  # fmt: skip
    p.add_argument("--fps", type=float, default=60.0, help="frames pushed to a page per second")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long")
    p.add_argument("--nice", type=int, default=10,
                   help="lower the viewer's CPU priority by this much (default 10: on a "
                        "machine shared with the service, the service comes first)")  # fmt: skip
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def warn_if_exposed(host: str) -> bool:
    """Prints a warning when ``host`` is not a loopback address; True if it did."""
    from labeler_service.tools.view import is_loopback

    if is_loopback(host):
        return False
    print(f"warning: the viewer listens on {host}: anyone who can reach this address sees the "
          "live capture (read-only, no authentication)", file=sys.stderr)  # fmt: skip
    return True


async def serve_view(url: str, host: str, port: int, fps: float, stop: asyncio.Event) -> None:
    """Runs a viewer until ``stop`` is set; prints its address once it listens."""
    from labeler_service.tools.view import Viewer

    warn_if_exposed(host)
    async with Viewer(url, host=host, port=port, fps=fps) as v:
        print(f"view {v.url} (from {url}); Ctrl-C to stop", flush=True)
        await stop.wait()


async def _main(args: argparse.Namespace) -> int:
    stop = stop_event(args.seconds)
    await serve_view(args.url, args.host, args.port, args.fps, stop)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.nice > 0:
        os.nice(args.nice)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")  # fmt: skip
    return asyncio.run(_main(args))
