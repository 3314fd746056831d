"""``mocap-labeler subscribe --from URL [--out FILE]``: live summary of labeled frames; exits 1
when no frame arrived."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import time
from pathlib import Path

from labeler_service.cli.args import positive, positive_int
from labeler_service.cli.stopping import stop_event


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--from", dest="url", required=True, metavar="URL",
                   help="udp://service-host:port[/stream] or mqtt://host:port/stream")  # fmt: skip
    p.add_argument("--out", type=Path, default=None, help="record labeled frames to C3D")
    p.add_argument("--seconds", type=positive, default=None, help="stop after this long")
    p.add_argument("--frames", type=positive_int, default=None, help="stop after this many frames")


async def _main(args: argparse.Namespace) -> int:
    from labeler_service.tools.subscribe import Recorder, Subscriber, ms

    if args.out is not None:
        from labeler_service.capture import check_writable

        check_writable(args.out)  # now, not after a whole session
    stop = stop_event(args.seconds)
    recorder = Recorder() if args.out is not None else None
    tty = sys.stderr.isatty()
    async with Subscriber(args.url) as sub:

        async def consume() -> None:
            last_t, last_n = time.monotonic(), 0
            n = 0
            async for r in sub.frames():
                n += 1
                if recorder is not None:
                    recorder.add(r, sub.models[r.msg.stream].rate)
                now = time.monotonic()
                if now - last_t >= 1.0:
                    line = sub.stats.summary_line(sub.stats.frames - last_n, now - last_t)
                    print(("\r" + line) if tty else line, end="" if tty else "\n",
                          file=sys.stderr, flush=True)  # fmt: skip
                    last_t, last_n = now, sub.stats.frames
                if args.frames is not None and n >= args.frames:
                    stop.set()
                    return

        task = asyncio.create_task(consume(), name="subscribe-consume")
        await stop.wait()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        s = sub.stats
        lat = s.latency_percentiles()
        print(("\n" if tty else "") + f"received {s.frames} labeled frames, missing seq "
              f"{s.missing_seq}, undecodable {s.undecodable}, latency p50 {ms(lat['p50'])} "
              f"p99 {ms(lat['p99'])} p99.9 {ms(lat['p99.9'])}")  # fmt: skip
    if recorder is not None:
        n = recorder.write(args.out)
        print(recorder.report(recorder.written or args.out, n))
    return 0 if s.frames > 0 else 1  # nothing received: a script must not read success


def run(args: argparse.Namespace) -> int:
    return asyncio.run(_main(args))
