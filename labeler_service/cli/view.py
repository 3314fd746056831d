"""``mocap-labeler view --from URL [--port 8765] [--host 127.0.0.1]``: live 3D view in a browser.

Subscribes to the labeled stream like ``subscribe`` and serves a page (three.js, vendored) on
``http://HOST:PORT/`` that draws the markers live; see ``docs/viewer.md``. Loopback only by
default: ``--host`` exposes it to the network (read-only, no authentication: a warning says so).
Runs until Ctrl-C / SIGTERM, at the idle CPU priority (``--priority``, default ``idle``:
Linux ``SCHED_IDLE``) so that a viewer sharing the service's machine never takes the CPU from
it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from labeler_service.cli.args import port, positive
from labeler_service.cli.stopping import stop_event
from labeler_service.tools.priority import PRIORITIES, lower_priority


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--from", dest="url", required=True, metavar="URL",
                   help="udp://service-host:port[/stream] or mqtt://host:port/stream")  # fmt: skip
    p.add_argument("--port", type=port, default=8765, help="HTTP port of the page (0: any free)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default loopback; anything else exposes the "
                        "read-only view without authentication)")  # fmt: skip
    p.add_argument("--fps", type=float, default=60.0, help="frames pushed to a page per second")
    p.add_argument("--seconds", type=positive, default=None, help="stop after this long")
    p.add_argument("--priority", choices=PRIORITIES, default="idle",
                   help="the viewer's CPU priority (default idle: SCHED_IDLE, it only uses CPU "
                        "time the service leaves; low: nice 10; normal: unchanged)")  # fmt: skip
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                   help="how much the view logs to stderr (default INFO)")  # fmt: skip


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
    lower_priority(args.priority)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")  # fmt: skip
    return asyncio.run(_main(args))
