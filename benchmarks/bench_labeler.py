"""Speed and memory of the online labeler over a long stream (prints one JSON object).

Default: a simulated 6-performer hug long enough for ``--frames`` (10,000) frames after the
50-frame training window, corrupted like ``evaluate`` (shuffled, the simulator's own ghosts and
occlusions). ``--capture FILE`` replays a labeled capture instead, back and forth (ping-pong)
until ``--frames`` frames were labeled.

Reported: ``ms_per_frame_p50/p99/max`` (wall time of ``Labeler.process`` after warm-up),
``cpu_ms_per_frame_p50/p99`` (thread CPU time: the same without preemption by other processes
on a shared machine; ``load_average_1min`` says how shared it was),
``ms_per_performer_p50``, ``accuracy``, and memory growth between frame 1,000 and the end: process
RSS (``rss_growth_kib``), live Python objects (``gc_objects_growth``) and, with ``--trace-heap``
(which slows every frame, so timings are then not representative), the tracemalloc heap.

    .venv/bin/python benchmarks/bench_labeler.py --performers 6 --frames 10000 --out bench.json
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from _common import emit

from labeler_service.capture import Capture, read_capture
from labeler_service.evaluation.scoring import WARMUP_FRAMES, Scorer
from labeler_service.labeling.frame import FrameLabeler
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import make_window_labeler
from labeler_service.labeling.structure import window_model
from labeler_service.scenes.corrupt import CorruptionSpec, iter_stream
from labeler_service.scenes.sim import SCENARIOS

INIT = 50
MARK = 1000  # memory baseline frame


def _rss_kib() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


def _load() -> float:
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return float("nan")


def _capture(args: argparse.Namespace) -> Capture:
    if args.capture:
        cap = read_capture(args.capture)
        need = args.frames + INIT
        idx = []
        forward = True
        while len(idx) < need:
            seq = range(cap.n_frames) if forward else range(cap.n_frames - 2, 0, -1)
            idx.extend(seq)
            forward = not forward
        return Capture(cap.positions[idx[:need]], cap.labels, cap.rate, source=cap.source)
    from labeler_service.scenes.simulate import simulate_scene

    seconds = (args.frames + INIT) / args.rate + 0.05
    return simulate_scene(args.performers, seconds, args.scenario, args.seed, rate=args.rate)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--performers", type=int, default=6)
    p.add_argument("--scenario", default="hug", choices=SCENARIOS)
    p.add_argument("--frames", type=int, default=10_000, help="labeled frames after training")
    p.add_argument("--rate", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--capture", help="replay this labeled capture (ping-pong) instead")
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument(
        "--trace-heap", action="store_true", help="tracemalloc heap growth (slows every frame)"
    )
    p.add_argument(
        "--labeled-start",
        choices=("labeler", "model"),
        default="labeler",
        help="model: the window model's start (evaluate's default, --labeled-start auto): the "
        "booting labeler from templates trained on the 50 labeled frames",
    )
    args = p.parse_args(argv)

    t_sim = time.perf_counter()
    cap = _capture(args)
    t_sim = time.perf_counter() - t_sim
    plan, frames = iter_stream(cap, CorruptionSpec(protect_frames=INIT, seed=args.seed))
    lab: FrameLabeler
    if args.labeled_start == "model":
        window = Capture(cap.positions[:INIT], cap.labels, cap.rate)
        lab = make_window_labeler(window_model(window), rate=plan.rate, window_frames=INIT)
        if tuple(lab.marker_names) != tuple(plan.marker_names):  # (the scorer's indices)
            raise SystemExit("the window model orders the markers otherwise than the scene")
    else:
        lab = Labeler(plan.marker_names, plan.rate)
    t0 = time.perf_counter()
    lab.warmup()
    warm_s = time.perf_counter() - t0

    times = np.empty(args.frames)
    cpu = np.empty(args.frames)
    # the scorer of ``evaluate``; it allocates its storage here, before the memory baseline
    scorer = Scorer(plan.marker_names, INIT, INIT + args.frames)
    if args.trace_heap:
        tracemalloc.start()
    heap0 = rss0 = 0.0
    objs0 = 0
    rss_mid = float("nan")
    gc.collect()
    for k, fr in enumerate(frames):
        if k >= INIT + args.frames:
            break
        labels = fr.truth if k < INIT else None
        c1 = time.thread_time_ns()
        t1 = time.perf_counter_ns()
        out = lab.process(fr.points, fr.t, labels)
        dt = time.perf_counter_ns() - t1
        dc = time.thread_time_ns() - c1
        scorer.add(k, fr.truth, out)
        if k < INIT:
            continue
        i = k - INIT
        times[i] = dt / 1e6
        cpu[i] = dc / 1e6
        if i == MARK:
            heap0 = tracemalloc.get_traced_memory()[0] / 1024 if args.trace_heap else np.nan
            rss0 = _rss_kib()
            objs0 = len(gc.get_objects())
        if i == (MARK + args.frames) // 2:
            rss_mid = _rss_kib()
        if sys.stderr.isatty() and i % 1000 == 0:
            print(f"\r{i}/{args.frames}", end="", file=sys.stderr)
    heap1 = tracemalloc.get_traced_memory()[0] / 1024 if args.trace_heap else np.nan
    rss1 = _rss_kib()
    objs1 = len(gc.get_objects())
    tracemalloc.stop()
    n = len(plan.marker_names)
    subjects = len(cap.subjects)
    t = times[WARMUP_FRAMES:]  # the first labeled frames after training are not steady state
    p50 = float(np.median(t))
    result = {
        "labeled_start": args.labeled_start,
        "source": args.capture or f"simulate {args.performers} {args.scenario} seed {args.seed}",
        "frames": int(times.size),
        "subjects": subjects,
        "markers": n,
        "rate_hz": plan.rate,
        "accuracy": round(scorer.result().accuracy, 6),
        "ms_per_frame_p50": round(p50, 4),
        "ms_per_frame_p99": round(float(np.percentile(t, 99)), 4),
        "ms_per_frame_max": round(float(t.max()), 4),
        "ms_per_performer_p50": round(p50 / subjects, 4),
        "cpu_ms_per_frame_p50": round(float(np.median(cpu[WARMUP_FRAMES:])), 4),
        "cpu_ms_per_frame_p99": round(float(np.percentile(cpu[WARMUP_FRAMES:], 99)), 4),
        "load_average_1min": round(_load(), 2),
        "p99_over_p50": round(float(np.percentile(t, 99)) / p50, 3),
        "rss_kib_at_1000": round(rss0, 1),
        "rss_growth_kib": round(rss1 - rss0, 1),
        "rss_growth_second_half_kib": round(rss1 - rss_mid, 1),
        "gc_objects_growth": objs1 - objs0,
        "heap_growth_kib": None if not args.trace_heap else round(heap1 - heap0, 1),
        "warmup_s": round(warm_s, 3),
        "scene_s": round(t_sim, 3),
    }
    if sys.stderr.isatty():
        print(file=sys.stderr)  # end the progress line before the JSON
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
