"""Accuracy of a capture replayed through the service, per labeled start, against ``evaluate``.

The capture is corrupted as ``evaluate`` corrupts it (shuffled, NaN dropped, the first
``--init-frames`` frames labeled; the same seed gives the same frames), replayed over loopback
UDP at its rate to ``mocap-labeler serve`` (a subprocess, ``testing.harness.run_pipeline``)
with the stream's ``labeled_start`` set to each of ``--starts``, and the labeled frames the
subscriber received are scored with ``evaluate``'s scorer (a lost frame counts as unlabeled).
``evaluate`` runs in this process on the same capture for each start (``evaluate_<start>``).
Runs are interleaved (``--repeats``); the JSON lists every run and the median per start.

    .venv/bin/python benchmarks/service_start.py TAKE.c3d [--init-frames 50]
        [--starts labeler auto] [--repeats 3] [--speed 1.0] [--out FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
from pathlib import Path

from _common import emit

from labeler_service.capture import read_capture
from labeler_service.cli.demo import score
from labeler_service.evaluation.scoring import evaluate
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.testing.harness import run_pipeline, service_settings


async def _through_service(frames, start: str, init: int, speed: float, workdir: Path) -> dict:
    stream = {"name": "bench", "rate": frames.rate, "labeled_start": start}
    settings = service_settings("udp", stream, 5.0)
    res = await run_pipeline(frames, settings, workdir, stream="bench", init_frames=init,
                             speed=speed)  # fmt: skip
    summary = score(frames, res.received, init).summary()
    return {
        "start": start,
        "accuracy": summary["accuracy"],
        "frames_received": len(res.received),
        "drops": res.sent - init - len(res.received),
        "service_drops": res.drops_service,
        "service_exit_code": res.service_returncode,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--init-frames", type=int, default=50)
    ap.add_argument("--starts", nargs="+", default=["labeler", "auto"])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out")
    args = ap.parse_args()
    cap = read_capture(args.capture)
    frames = corrupt(cap, CorruptionSpec(protect_frames=args.init_frames, seed=args.seed))
    out: dict = {
        "capture": args.capture.name,
        "init_frames": args.init_frames,
        "frames": frames.n_frames,
        "rate": frames.rate,
        "runs": [],
    }
    for start in args.starts:
        report, _ = evaluate(cap, init_frames=args.init_frames, seed=args.seed,
                             labeled_start=start, methods=["online"])  # fmt: skip
        out[f"evaluate_{start}"] = report["accuracy"]
    with tempfile.TemporaryDirectory(prefix="mocap-start-") as d:
        for k in range(args.repeats):
            for start in args.starts:  # interleaved
                work = Path(d) / f"{start}{k}"
                work.mkdir()
                run = asyncio.run(_through_service(frames, start, args.init_frames,
                                                   args.speed, work))  # fmt: skip
                out["runs"].append(run)
    for start in args.starts:
        runs = [r for r in out["runs"] if r["start"] == start]
        out[f"service_{start}_accuracy_p50"] = statistics.median(r["accuracy"] for r in runs)
        out[f"service_{start}_drops_p50"] = statistics.median(r["drops"] for r in runs)
    emit(out, args.out)


if __name__ == "__main__":
    main()
