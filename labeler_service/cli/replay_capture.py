"""``mocap-labeler replay FILE --to URL``: stream a capture unlabeled to the service."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from labeler_service.cli.args import check_init_window, seed
from labeler_service.wording import plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="labeled capture (.c3d, .trc, .npz), FILE[:start[:stop]] (frames)")
    p.add_argument("--to", required=True, metavar="URL",
                   help="udp://host:port[/stream] or mqtt://host:port/stream")  # fmt: skip
    p.add_argument("--stream", default=None, help="stream name (default: from the URL, else "
                   "'default')")  # fmt: skip
    p.add_argument("--speed", type=float, default=1.0,
                   help="playback speed x capture rate (0 = as fast as possible)")  # fmt: skip
    p.add_argument("--init-frames", type=int, default=50,
                   help="first frames sent with their labels (training window); 0 sends "
                   "none: the stream must be configured with a model")  # fmt: skip
    p.add_argument("--downsample", type=int, default=1, help="keep every N-th frame")
    p.add_argument("--gaps", type=int, default=0, help="markers removed per subject per gap")
    p.add_argument("--gap-frames", type=int, default=20, help="length of each gap (frames)")
    p.add_argument("--dropouts", type=float, default=0.0, help="fraction of samples dropped")
    p.add_argument("--ghosts", type=float, default=0.0, help="mean ghost points per frame")
    p.add_argument("--jitter", type=float, default=0.0, help="Gaussian noise per axis (mm)")
    p.add_argument(
        "--leave",
        type=int,
        default=0,
        help="subjects that vanish once and come back displaced (re-identification)",
    )
    p.add_argument("--leave-seconds", type=float, default=1.0,
                   help="how long each --leave subject is gone")  # fmt: skip
    p.add_argument("--no-shuffle", action="store_true", help="keep the capture's point order")
    p.add_argument("--loops", type=int, default=1, help="passes, alternating direction")
    p.add_argument("--up", choices=["z", "y"], default="z", help="vertical axis of the file")
    p.add_argument("--seed", type=seed, default=0, help="corruption seed")


async def _main(args: argparse.Namespace) -> int:
    from labeler_service.errors import LabelerError
    from labeler_service.scenes.corrupt import CorruptionSpec
    from labeler_service.service.transports.url import redact_url
    from labeler_service.tools.replay import (
        check_pace,
        open_sender,
        prepare,
        replay,
        replay_stream,
    )

    # every argument checked before the start-up line (a bad URL, stream name, speed)
    stream_name = replay_stream(args.to, args.stream)
    check_pace(args.speed, args.loops)
    if args.init_frames < 0:
        raise LabelerError(
            f"--init-frames must be >= 0 (0: a stream configured with a model), "
            f"got {args.init_frames}"
        )
    spec = CorruptionSpec(
        downsample=args.downsample, gaps=args.gaps, gap_frames=args.gap_frames,
        dropouts=args.dropouts, ghosts=args.ghosts, jitter_mm=args.jitter,
        shuffle=not args.no_shuffle, protect_frames=args.init_frames, seed=args.seed,
        leave=args.leave, leave_seconds=args.leave_seconds,
    )  # fmt: skip
    from labeler_service.capture import read_segment

    cap = read_segment(args.file, up=args.up)
    # (a stream may hold a model that knows a performer the window misses: no subject check)
    check_init_window(cap, args.file, args.init_frames, max(args.downsample, 1), subjects=False)
    frames = prepare(cap, spec)
    if args.init_frames > 0 and not frames.marker_names:
        raise LabelerError(
            f"{args.file}: no labeled markers (only unlabeled *N tracks): --init-frames "
            f"{args.init_frames} would send init frames without labels; use --init-frames 0 "
            "towards a stream configured with a model (serve: [[streams]] model = ...)"
        )
    if frames.n_frames <= args.init_frames:
        raise LabelerError(
            f"{args.file}: {plural(frames.n_frames, 'frame')} (after --downsample), not more "
            f"than {plural(args.init_frames, 'init frame')}: nothing would be left to label"
        )
    print(
        f"replay {Path(args.file).name}: {plural(frames.n_frames, 'frame')} x {args.loops}, "
        f"{plural(len(frames.marker_names), 'marker')}, {frames.rate:g} Hz at speed {args.speed:g} "
        f"-> {redact_url(args.to)}, stream {stream_name}",
        file=sys.stderr,
    )
    for note in frames.notes:
        print(f"replay: note: {note}", file=sys.stderr)
    for subject, gone, back in frames.departures:
        print(
            f"replay: {subject} leaves at frame {gone} ({gone / frames.rate:.2f} s) and is back "
            f"at frame {back} ({back / frames.rate:.2f} s), displaced",
            file=sys.stderr,
        )
    async with open_sender(args.to, stream=args.stream) as (send, stream):
        stats = await replay(
            frames, send, stream=stream, init_frames=args.init_frames,
            speed=args.speed, loops=args.loops,
        )  # fmt: skip
    print(
        f"sent {plural(stats.sent, 'frame')} to stream {stream} ({stats.failed} failed) in "
        f"{stats.seconds:.1f} s "
        f"({stats.rate:.0f}/s, latest send {stats.max_late_ms:.1f} ms behind schedule)"
    )
    if stats.stalls:
        print(
            f"replay: {plural(stats.stalls, 'stall')} ({stats.stalled_s:.1f} s in all): it went "
            "on where it stopped each time, at the capture rate",
            file=sys.stderr,
        )
    if stats.failed:  # (exit 1: frames were lost on the way out, not an error of the input)
        print(f"replay: {plural(stats.failed, 'frame')} could not be sent (exit 1)",
              file=sys.stderr)  # fmt: skip
    return 0 if stats.failed == 0 else 1


def run(args: argparse.Namespace) -> int:
    return asyncio.run(_main(args))
