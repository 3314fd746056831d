"""``mocap-labeler bench latency``: end-to-end latency through a real transport.

A simulated scene (``--subjects`` performers at ``--rate`` Hz; ``--sim-seconds`` simulated and
played forward/backward until ``--seconds`` are covered) is replayed unlabeled to
``mocap-labeler serve`` running as a subprocess, over loopback UDP or a local Mosquitto
(started on a free port unless ``--broker URL`` is given); a subscriber in this process
receives the labeled frames. Latency = subscriber receipt - sender stamp (same clock). Prints
one JSON object on the last line with ``--json``.

``--start model`` (default) starts the stream from a subject model trained offline on the
scene's labeled init window (the production set-up: no training stall); ``--start init`` trains
in the service from the labeled init frames in the stream (one-time stall, reported separately
as ``training_stall_frames``); ``--start boot`` simulates ``--train-seconds`` more of the scene,
trains the subject model on them (``StructureTrainer``, as ``train structure``: other frames
than the ones streamed), and streams with **no labels at all**: the service boots every
subject off the event loop (``--boot false``: with the service's ``boot = false``, the default
setting, the stream boots as a recovery instead: its first unlabeled frame starts one). Boot
adds to the JSON: ``boot_s`` per subject and ``boot_s_max``
(the ``evaluate`` definition: from the subject's first frame with >= 60 % of its markers
visible until its visible markers are >= 95 % correct for 10 frames in a row),
``accuracy_after_boot``, ``boot_done_s`` (the last subject's boot), ``labeling_ms_p99_9_boot``
and ``labeling_ms_max_boot`` (labeling time of the frames up to ``boot_done_s``, boot installs
included), ``boot_attempts``/``boot_failed`` and the mean attempt time from the service's
metrics, and the results (boots and extensions) installed between frames rather than in a
frame's labeling (``boot_installs_between_frames``, their mean wall time
``boot_install_ms_mean``: a frame that arrives meanwhile waits, which its latency shows).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
from pathlib import Path

from labeler_service.cli.args import add_labeler_argument, rate, seed, usable_folder
from labeler_service.errors import MocapError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subjects", type=int, default=10, help="performers (1-10)")
    p.add_argument("--rate", type=rate, default=360.0, help="capture rate (Hz, at most 2000)")
    p.add_argument("--seconds", type=float, default=20.0, help="streamed duration (s)")
    p.add_argument("--transport", choices=["udp", "mqtt"], default="udp",
                   help="udp: the embedded loopback path; mqtt: a Mosquitto broker")  # fmt: skip
    p.add_argument("--broker", default=None, metavar="URL", help="mqtt://host:port (else a "
                   "local mosquitto is started)")  # fmt: skip
    p.add_argument("--scenario", default="hug", help="simulated scenario (walk, hug, pile)")
    p.add_argument("--sim-seconds", type=float, default=5.0, help="simulated scene length (s)")
    p.add_argument("--start", choices=["model", "init", "boot"], default="model",
                   help="stream start-up: offline model (+ a few labeled frames), in-stream "
                        "training window, or boot from a model with no labels")  # fmt: skip
    p.add_argument("--boot", choices=["true", "false"], default="true",
                   help="--start boot: the service's boot setting (false: the stream boots as "
                        "a recovery)")  # fmt: skip
    p.add_argument(
        "--train-seconds",
        type=float,
        default=3.0,
        help="--start boot: simulated seconds the model is trained on (not streamed)",
    )
    p.add_argument("--init-frames", type=int, default=None,
                   help="labeled frames first (default: 5 with model, 50 with init)")  # fmt: skip
    add_labeler_argument(p)
    p.add_argument("--labeled-start", choices=["auto", "labeler", "model"], default=None,
                   help="--start init: the stream's labeled_start (else the default)")  # fmt: skip
    p.add_argument("--seed", type=seed, default=0, help="scene seed (default 0)")
    p.add_argument("--workdir", type=Path, default=None, help="keep service log/config here")
    p.add_argument("--json", action="store_true", help="print the result as JSON (last line)")


async def bench(args, workdir: Path) -> dict:
    import numpy as np

    from labeler_service.testing.harness import (
        run_pipeline,
        service_settings,
        simulated_frames,
        train_model_file,
    )
    from labeler_service.tools.replay import loops_to_cover
    from labeler_service.tools.subscribe import percentiles

    default_init = {"model": 5, "init": 50, "boot": 0}[args.start]
    init = args.init_frames if args.init_frames is not None else default_init
    stream = "bench"
    if args.boot == "false" and args.start != "boot":
        raise MocapError("--boot false is for --start boot (the other starts do not boot)")
    if args.start == "boot":
        if args.labeler != "online":
            raise MocapError("--start boot needs --labeler online (only it boots from a model)")
        if init:
            raise MocapError("--start boot sends no labels: leave --init-frames at 0")
        frames, model_path = boot_scene(args, workdir / "model.json")
    else:
        frames = simulated_frames(args.subjects, min(args.sim_seconds, args.seconds), args.rate,
                                  args.seed, args.scenario)  # fmt: skip
    n_total = int(round(args.seconds * frames.rate))
    stream_cfg: dict = {"name": stream, "rate": frames.rate}
    if args.labeled_start is not None and args.start == "init":
        stream_cfg["labeled_start"] = args.labeled_start
    if args.start == "model":
        stream_cfg["model"] = str(train_model_file(frames, 50, workdir / "model.json"))
    elif args.start == "boot":
        stream_cfg["model"] = str(model_path)
    settings = service_settings(
        args.transport, stream_cfg, 5.0, labeler=args.labeler,
        boot=args.start == "boot" and args.boot == "true",
    )  # fmt: skip
    res = await run_pipeline(frames, settings, workdir, transport=args.transport, stream=stream,
                             init_frames=init, speed=1.0,
                             loops=loops_to_cover(frames.n_frames, n_total), max_frames=n_total,
                             broker_url=args.broker)  # fmt: skip
    expected = res.sent - (init if args.start == "init" else 0)
    received = res.received
    lat = np.array([r.latency_ms for r in received if r.latency_ms is not None])
    proc_ms = np.array([r.msg.proc_us / 1e3 for r in received])
    seqs = np.array([r.msg.seq for r in received])
    # frames after the start-up (first unlabeled frame + 1 s): steady state
    first_unlabeled = init
    steady = seqs >= first_unlabeled + int(frames.rate)
    lat_all = percentiles(lat)
    lat_steady = percentiles(lat[steady])
    src = np.array([r.msg.src for r in received], dtype=np.int64)
    recv = np.array([r.msg.recv for r in received], dtype=np.int64)
    sent = np.array([r.msg.sent for r in received], dtype=np.int64)
    got = np.array([r.recv_ns for r in received], dtype=np.int64)
    legs = {
        "to_service": (recv - src) / 1e6,
        "in_service": (sent - recv) / 1e6,
        "to_subscriber": (got - sent) / 1e6,
    }
    leg_q = {k: percentiles(v[steady]) for k, v in legs.items()}
    proc_q = percentiles(proc_ms)
    stall = int(np.count_nonzero(lat[seqs >= first_unlabeled] > 1000.0 / frames.rate))
    out = {
        "transport": args.transport,
        "labeler": args.labeler,
        "start": args.start,
        "boot": settings.get("boot", False),
        "labeled_start": stream_cfg.get("labeled_start"),
        "subjects": args.subjects,
        "markers": len(frames.marker_names),
        "rate": frames.rate,
        "seconds": args.seconds,
        "points_per_frame_mean": float(np.mean([len(p) for p in frames.points])),
        "frames_sent": res.sent,
        "frames_received": len(received),
        "drops": int(expected - len(received)),
        "service_drops": res.drops_service,
        "latency_ms_p50": lat_all["p50"],
        "latency_ms_p99": lat_all["p99"],
        "latency_ms_p99_9": lat_all["p99.9"],
        "latency_ms_max": float(lat.max()) if lat.size else float("nan"),
        "steady_latency_ms_p50": lat_steady["p50"],
        "steady_latency_ms_p99": lat_steady["p99"],
        "steady_latency_ms_p99_9": lat_steady["p99.9"],
        "frames_over_one_period": stall,
        "labeling_ms_p50": proc_q["p50"],
        "labeling_ms_p99": proc_q["p99"],
        "labeled_bytes_max": res.max_payload,
        **{f"{k}_ms_p50": q["p50"] for k, q in leg_q.items()},
        **{f"{k}_ms_p99": q["p99"] for k, q in leg_q.items()},
        "service_exit_code": res.service_returncode,
    }
    if args.start == "init":
        out.update(init_report(frames, received, loops_to_cover(frames.n_frames, n_total),
                               n_total, init))  # fmt: skip
    if args.start == "boot":
        out.update(boot_report(frames, received, loops_to_cover(frames.n_frames, n_total),
                               n_total, res.service))  # fmt: skip
    return out


def init_report(frames, received, loops: int, n_total: int, init: int) -> dict:
    """``--start init``: accuracy (``evaluate``'s, a lost frame scored unlabeled) over the
    frames after the labeled ones, and over the last 2 s (what the start left running)."""
    from labeler_service.cli.demo import score
    from labeler_service.tools.replay import frame_order

    seq_frames = looped(frames, frame_order(frames.n_frames, loops)[:n_total])
    tail = max(init, n_total - int(round(2.0 * frames.rate)))
    return {
        "accuracy": score(seq_frames, received, init).summary()["accuracy"],
        "accuracy_last_2s": score(seq_frames, received, tail).summary()["accuracy"],
    }


def boot_scene(args, path: Path):
    """``--start boot``: the streamed frames (no labels; shuffled) and a model trained on
    ``--train-seconds`` simulated before them (same performers, other frames)."""
    from labeler_service.labeling.templates import save_model
    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.scenes.simulate import simulate_scene
    from offline.structure import StructureTrainer

    streamed = min(args.sim_seconds, args.seconds)
    cap = simulate_scene(performers=args.subjects, seconds=args.train_seconds + streamed,
                         scenario=args.scenario, seed=args.seed, rate=args.rate)  # fmt: skip
    split = int(round(args.train_seconds * cap.rate))
    model = StructureTrainer().fit([cap.frames(0, split)]).model_
    save_model(model, path)
    frames = corrupt(cap.frames(split, cap.n_frames), CorruptionSpec(protect_frames=0,
                                                                      seed=args.seed))  # fmt: skip
    return frames, path


def looped(frames, order):
    """``frames`` in replay order (``seq`` k is frame ``order[k]``), times continuing."""
    import dataclasses

    import numpy as np

    idx = np.asarray(order, dtype=np.int64)
    return dataclasses.replace(
        frames,
        times=np.arange(idx.size, dtype=np.float64) / frames.rate,
        points=[frames.points[i] for i in idx],
        truth=[frames.truth[i] for i in idx],
        positions=frames.positions[idx],
        removed=frames.removed[idx],
        occlusions=[],
        departures=[],
    )


def boot_report(frames, received, loops: int, n_total: int, service: dict) -> dict:
    """The boot fields of the JSON (module docstring), from the received frames (scored as
    ``evaluate`` scores) and the service's metrics."""
    import numpy as np

    from labeler_service.cli.demo import score
    from labeler_service.tools.replay import frame_order
    from labeler_service.tools.subscribe import percentiles

    seq_frames = looped(frames, frame_order(frames.n_frames, loops)[:n_total])
    s = score(seq_frames, received, 0, rate=frames.rate).summary()
    boot_s = s["boot_s"]
    done = s["boot_s_max"]
    if done is None:  # a subject never booted: the whole run counts as "during boot"
        done_seq = n_total
    else:  # the last subject's boot: its first present frame + its boot delay
        done_seq = int(np.ceil(max(_first_present(seq_frames, name) + v * frames.rate
                                   for name, v in boot_s.items())))  # fmt: skip
    proc = np.array([r.msg.proc_us / 1e3 for r in received if r.msg.seq <= done_seq])
    q = percentiles(proc)
    attempts = sum(v for k, v in service.items() if k.startswith("mocap_boot_attempts_total"))
    failed = sum(v for k, v in service.items() if k.startswith("mocap_boot_failed_total"))
    b_sum = sum(v for k, v in service.items() if k.startswith("mocap_boot_seconds_sum"))
    b_n = sum(v for k, v in service.items() if k.startswith("mocap_boot_seconds_count"))
    i_sum = sum(v for k, v in service.items() if k.startswith("mocap_boot_install_seconds_sum"))
    i_n = sum(v for k, v in service.items() if k.startswith("mocap_boot_install_seconds_count"))
    return {
        "boot_s": boot_s,
        "boot_s_max": done,
        "boot_done_s": done_seq / frames.rate,
        "subjects_booted": sum(v is not None for v in boot_s.values()),
        "accuracy_after_boot": s["accuracy_after_boot"],
        "accuracy": s["accuracy"],
        "ghost_labeled_rate": s["ghost_labeled_rate"],
        "labeling_ms_p99_9_boot": q["p99.9"],
        "labeling_ms_max_boot": float(proc.max()) if proc.size else float("nan"),
        "frame_period_ms": 1000.0 / frames.rate,
        "boot_attempts": int(attempts),
        "boot_failed": int(failed),
        "boot_attempt_s_mean": b_sum / b_n if b_n else None,
        "boot_installs_between_frames": int(i_n),
        "boot_install_ms_mean": 1e3 * i_sum / i_n if i_n else None,
    }


def _first_present(frames, subject: str) -> int:
    """First frame with >= 60 % of ``subject``'s markers visible (the scorer's *present*)."""
    import numpy as np

    from labeler_service.evaluation.scoring import PRESENT

    cols = np.array([i for i, n in enumerate(frames.marker_names)
                     if n.split(":", 1)[0] == subject])  # fmt: skip
    for f, truth in enumerate(frames.truth):
        if np.isin(truth, cols).sum() >= PRESENT * cols.size:
            return f
    return len(frames.truth)


def run(args: argparse.Namespace) -> int:
    from labeler_service.scenes.simulate import MAX_PERFORMERS

    if not 1 <= args.subjects <= MAX_PERFORMERS:  # (the simulator's message names its own flag)
        raise MocapError(f"--subjects must be 1..{MAX_PERFORMERS}, got {args.subjects}")
    for flag, value in (("--seconds", args.seconds), ("--sim-seconds", args.sim_seconds)):
        if not (math.isfinite(value) and value > 0):  # (the simulator's message says --seconds)
            raise MocapError(f"{flag} must be a positive number, got {value:g}")
    _check_init_frames(args)
    from labeler_service.tools.subscribe import no_nan

    if args.workdir is not None:
        out = asyncio.run(bench(args, usable_folder(args.workdir, "--workdir")))
    else:
        with tempfile.TemporaryDirectory(prefix="mocap-bench-") as d:
            out = asyncio.run(bench(args, Path(d)))
    out = no_nan(out)
    if args.json:
        print(json.dumps(out, allow_nan=False))
    else:
        for k, v in out.items():
            print(f"{k:>26}: {v}")
    ok = out["drops"] == 0 and out["service_exit_code"] == 0
    if not ok:
        print("bench: frames were lost or the service did not exit cleanly", file=sys.stderr)
    return 0 if ok else 1


def _check_init_frames(args: argparse.Namespace) -> None:
    """``--init-frames`` against the start and the frames the run sends: a labeled window as
    long as the run left no frame to measure (0 received, drops negative, exit 0)."""
    n = args.init_frames
    if n is None:
        return
    if n < 0:
        raise MocapError(f"--init-frames must be >= 0, got {n}")
    from labeler_service.labeling.labeler import MIN_TRAIN_FRAMES

    if args.start == "init" and n < MIN_TRAIN_FRAMES:
        raise MocapError(f"--start init trains the stream on its labeled frames: --init-frames "
                         f"must be >= {MIN_TRAIN_FRAMES}, got {n}")  # fmt: skip
    sent = int(round(args.seconds * args.rate))
    if args.start != "boot" and n >= sent:
        raise MocapError(
            f"--init-frames {n} leaves no unlabeled frame to measure: the run sends {sent} "
            f"frames (--seconds {args.seconds:g} at {args.rate:g} Hz)"
        )
