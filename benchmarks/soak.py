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

    .venv/bin/python benchmarks/soak.py --minutes 10 --subjects 10 --rate 360
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
from pathlib import Path

import numpy as np

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
    args = p.parse_args()

    frames = simulated_frames(args.subjects, args.sim_seconds, args.rate, args.seed)
    n_total = int(args.minutes * 60 * frames.rate)
    with tempfile.TemporaryDirectory(prefix="mocap-soak-") as d:
        work = Path(d)
        model = train_model_file(frames, 50, work / "model.json")
        stream = {"name": "soak", "model": str(model), "rate": frames.rate}
        res = asyncio.run(run_pipeline(
            frames, service_settings(args.transport, stream, 30.0), work,
            transport=args.transport, stream="soak", init_frames=5, speed=1.0,
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
