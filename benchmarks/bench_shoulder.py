"""Benchmark: ``mocap-labeler train shoulder`` on the synthetic dense shoulder.

Simulates the default data set once (215 markers, 4000-frame range of motion + three 800-frame
test motions, ``simulate-shoulder``), then times the full ``train shoulder`` command (a fresh
process each time: imports, C3D reading, k = 3..6 x 1000 restarts, evaluation, MG03, plots and
report) ``--repeats`` times and prints one JSON object: median / min / max wall time and the
median of each stage's time from ``results.json``. The first run may include numba compilation
when the cache is cold; the median is what to quote. The machine is shared: the load average
before and after is recorded.

    python benchmarks/bench_shoulder.py [--repeats 3] [--restarts 1000] [--frames 4000]
        [--no-tests] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--restarts", type=int, default=1000)
    ap.add_argument("--frames", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-tests", action="store_true", help="time the training motion only")
    ap.add_argument("--keep", help="simulate into / write outputs under this folder")
    args = ap.parse_args()

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_shoulder_"))
    cli = [sys.executable, "-m", "labeler_service.cli.main"]
    sim = root / "sim"
    subprocess.run(
        [*cli, "simulate-shoulder", str(sim), "--frames", str(args.frames), "--seed",
         str(args.seed)],
        check=True, capture_output=True,
    )  # fmt: skip
    tests = [] if args.no_tests else [
        x for n in ("jumping_jack", "swimming", "curls") for x in ("--test", str(sim / f"{n}.c3d"))
    ]  # fmt: skip
    load_before = os.getloadavg()
    walls, stages, summary = [], [], {}
    for i in range(args.repeats):
        out = root / f"out{i}"
        cmd = [*cli, "train", "shoulder", str(sim / "rom.c3d"), *tests, "--truth",
               str(sim / "truth.npz"), "--restarts", str(args.restarts), "--seed",
               str(args.seed), "--out", str(out)]  # fmt: skip
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, check=True, capture_output=True, text=True)
        walls.append(time.perf_counter() - t0)
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        stages.append(json.loads((out / "results.json").read_text())["timings_s"])
    load_after = os.getloadavg()
    stage_median = {k: round(statistics.median(s[k] for s in stages), 3) for k in stages[0]}
    print(
        json.dumps(
            {
                "benchmark": "train_shoulder",
                "command": "mocap-labeler train shoulder rom.c3d"
                + ("" if args.no_tests else " --test x3")
                + f" --truth truth.npz --restarts {args.restarts}",
                "markers": summary.get("markers"),
                "train_frames": args.frames,
                "ks": summary.get("ks"),
                "restarts": args.restarts,
                "repeats": args.repeats,
                "wall_s_median": round(statistics.median(walls), 3),
                "wall_s_min": round(min(walls), 3),
                "wall_s_max": round(max(walls), 3),
                "wall_s_all": [round(w, 3) for w in walls],
                "stages_median_s": stage_median,
                "acceptance_passed": summary.get("acceptance_passed"),
                "acceptance_total": summary.get("acceptance_total"),
                "cpu_count": os.cpu_count(),
                "loadavg_before": [round(x, 2) for x in load_before],
                "loadavg_after": [round(x, 2) for x in load_after],
                "outputs": str(root),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
