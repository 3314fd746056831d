"""Soak test: the service under sustained load, watching resident memory and errors.

Streams a simulated scene (``--subjects`` performers at ``--rate`` Hz, played forward and
backward) for ``--minutes`` through ``mocap-labeler serve`` (a subprocess) over loopback UDP
(or MQTT with a local Mosquitto), sampling the service's resident memory every 5 s. Prints one
JSON object (last line):

- ``rss_mb_start``: median RSS over the second minute (after warm-up and the first frames);
- ``rss_mb_end``: median RSS over the last minute; ``rss_growth_pct`` their relative change
  (acceptance: within 5 %);
- ``errors``: service drops that mean a fault (``labeler_error``, ``internal``, ``send_error``,
  protocol rejects) - acceptance 0; ``queue_full`` and ``rx_overflow`` (falling behind) are
  reported separately;
- frames sent/received and latency percentiles.

With ``--start boot`` the production path: a model trained on ``--train-seconds`` of other
simulated frames of the same performers, ``boot = true``, no label ever sent (the boot, its
worker process, the re-verification and the extensions run all along).

    .venv/bin/python benchmarks/soak.py --minutes 10 --subjects 10 --rate 360
    .venv/bin/python benchmarks/soak.py --minutes 10 --subjects 10 --rate 360 --start boot
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
from pathlib import Path

import numpy as np

from labeler_service.cli.bench_latency import boot_scene
from labeler_service.testing.harness import (
    run_pipeline,
    service_settings,
    simulated_frames,
    train_model_file,
)
from labeler_service.tools.replay import loops_to_cover
from labeler_service.tools.subscribe import percentiles

#: Service drop reasons that are not faults (falling behind, sender-side seq trouble); every
#: other reason counts in ``errors``.
NOT_FAULTS = ("queue_full", "rx_overflow", "duplicate", "late")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--subjects", type=int, default=10)
    p.add_argument("--rate", type=float, default=360.0)
    p.add_argument("--sim-seconds", type=float, default=5.0)
    p.add_argument("--transport", choices=["udp", "mqtt"], default="udp")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start", choices=["model", "boot"], default="model",
                   help="model: a model of the streamed performers and 5 labeled frames; boot: "
                        "the production path (a model trained on other frames, boot = true, "
                        "no label sent)")  # fmt: skip
    p.add_argument("--train-seconds", type=float, default=3.0, help="--start boot: model's")
    args = p.parse_args()
    args.scenario, args.seconds = "hug", args.sim_seconds  # (what boot_scene reads)

    with tempfile.TemporaryDirectory(prefix="mocap-soak-") as d:
        work = Path(d)
        if args.start == "boot":
            frames, model = boot_scene(args, work / "model.json")
            init = 0
        else:
            frames = simulated_frames(args.subjects, args.sim_seconds, args.rate, args.seed)
            model = train_model_file(frames, 50, work / "model.json")
            init = 5
        n_total = int(args.minutes * 60 * frames.rate)
        stream = {"name": "soak", "model": str(model), "rate": frames.rate}
        settings = service_settings(args.transport, stream, 30.0, boot=args.start == "boot")
        res = asyncio.run(run_pipeline(
            frames, settings, work,
            transport=args.transport, stream="soak", init_frames=init, speed=1.0,
            loops=loops_to_cover(frames.n_frames, n_total), max_frames=n_total,
            keep_frames=False, rss_every_s=5.0,
        ))  # fmt: skip
        log_tail = (work / "service.log").read_text()[-1500:]
    t = np.array([x[0] for x in res.rss])
    rss = np.array([x[1] for x in res.rss], dtype=np.float64) / 2**20
    start = rss[(t >= 60) & (t < 120)] if (t >= 120).any() else rss[: max(1, len(rss) // 4)]
    end = rss[t >= t.max() - 60] if t.size else rss
    stats = res.stats
    lat = percentiles(stats.latencies_ms)
    errors = {k: v for k, v in res.drops_service.items() if k not in NOT_FAULTS}
    out = {
        "start": args.start,
        "minutes": args.minutes,
        "transport": args.transport,
        "subjects": args.subjects,
        "rate": frames.rate,
        "frames_sent": res.sent,
        "frames_received": stats.frames,
        "missing_seq": stats.missing_seq,
        "service_drops": res.drops_service,
        "errors": int(sum(errors.values())),
        "rss_mb_start": float(np.median(start)),
        "rss_mb_end": float(np.median(end)),
        "rss_mb_max": float(rss.max()),
        "rss_growth_pct": float(100 * (np.median(end) / np.median(start) - 1)),
        "latency_ms_p50": lat["p50"],
        "latency_ms_p99": lat["p99"],
        "latency_ms_p99_9": lat["p99.9"],
        "service_exit_code": res.service_returncode,
    }
    print(log_tail.strip().splitlines()[-1] if log_tail.strip() else "", flush=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
