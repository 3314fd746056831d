"""Per-frame cost of a booting stream in the frame thread, with and without re-verification.

The service drives a :class:`~labeler_service.labeling.booting.BootingLabeler` with
``inline_boot=False, inline_extend=False``: ``process`` runs per frame in the stream's thread,
the boot and extension attempts (``boot_step``) run in a worker, and ``boot_snapshot`` /
``install_boot`` run in the frame thread between frames. This script does the same in one
process on the ``bench latency --start boot`` scene (simulated hug, a model trained on the
``--train-seconds`` before the streamed part) and times ``process`` and ``install_boot``
separately, from ``--skip-s`` on, and the largest ``boot_snapshot`` (frame thread too).
``boot_step`` is off the frame path: its CPU time is reported apart (``first_attempt_cpu_ms``:
the first boot attempt, 10 performers at once; ``extend_cpu_ms_p50``: the extensions of booted
subjects to markers not placed yet, which also run twice in each catch-up). Each
``--verify`` value is one run, in order, so ``--verify off on off on`` interleaves them.

With ``--labeled-s S`` the first S seconds are sent with their labels (a client that does
send them) and each run also reports ``first_unlabeled_ms``: the frame that ends the labeled
run, in which the inner labeler is rebuilt from the labeled frames
(``booting.LABELED_KEPT_S`` of them at most).

    .venv/bin/python benchmarks/boot_frame_cost.py --verify off on off on [--out FILE]
    .venv/bin/python benchmarks/boot_frame_cost.py --verify on on --labeled-s 1.0 --skip-s 1.1
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import add_hug_args, emit, hug_scene

from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import BootingLabeler


def run(frames, model, rate: float, verify: bool, skip: int, labeled: int = 0) -> dict:
    lab = BootingLabeler(
        model, rate, boot=BootConfig(verify=verify), inline_boot=False, inline_extend=False
    )
    lab.warmup()
    index = {n: i for i, n in enumerate(model.marker_names)}
    to_model = np.array([index.get(n, -1) for n in frames.marker_names], dtype=np.int64)
    proc, inst, snaps, attempts, extends = [], [], [], [], []
    first_unlabeled = None
    for f in range(frames.n_frames):
        labels = None
        if f < labeled:
            tr = frames.truth[f]
            labels = np.where(tr >= 0, to_model[np.maximum(tr, 0)], -1).astype(np.int32)
        t0 = time.perf_counter()
        lab.process(frames.points[f], float(frames.times[f]), labels)
        t1 = time.perf_counter()
        if labeled and f == labeled:
            first_unlabeled = round((t1 - t0) * 1e3, 3)
        if f >= skip:
            proc.append((t1 - t0) * 1e3)
        if lab.needs_boot():
            ts = time.perf_counter()
            snap = lab.boot_snapshot()
            t1 = time.perf_counter()
            c1 = time.process_time()
            res = lab.boot_step(snap)
            c2 = time.process_time()
            t2 = time.perf_counter()
            lab.install_boot(snap, res)
            snaps.append((t1 - ts) * 1e3)
            # the step's CPU time (off the frame path; CPU, not wall: the machine is shared)
            if snap.subjects:
                attempts.append((c2 - c1) * 1e3)
            elif snap.labels is not None:
                extends.append((c2 - c1) * 1e3)
            if f >= skip:
                inst.append((time.perf_counter() - t2) * 1e3)
    p = np.array(proc)
    q50, q99, q999 = np.percentile(p, [50, 99, 99.9])
    return {
        "verify": verify,
        "frames_timed": int(p.size),
        "process_ms_p50": round(float(q50), 3),
        "process_ms_p99": round(float(q99), 3),
        "process_ms_p99_9": round(float(q999), 3),
        "install_ms_max": round(max(inst), 3) if inst else None,
        "snapshot_ms_max": round(max(snaps), 3) if snaps else None,
        "first_attempt_cpu_ms": round(attempts[0], 1) if attempts else None,
        "attempts": len(attempts),
        "extend_cpu_ms_p50": round(float(np.median(extends)), 1) if extends else None,
        "extends": len(extends),
        "installs": len(inst),
        "active_subjects": len(lab.active_subjects),
        "withdrawals": sum(1 for e in lab.events if e[1] == "withdraw"),
        "first_unlabeled_ms": first_unlabeled,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hug_args(ap, seconds=3.0)
    ap.add_argument("--skip-s", type=float, default=0.5, help="seconds not timed at the start")
    ap.add_argument("--verify", nargs="+", choices=["on", "off"], default=["off", "on"])
    ap.add_argument("--labeled-s", type=float, default=0.0, help="seconds sent with labels")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    labeled = int(round(a.labeled_s * a.rate))
    model, frames = hug_scene(a, protect_frames=labeled)
    skip = int(round(a.skip_s * a.rate))
    runs = [run(frames, model, a.rate, v == "on", skip, labeled) for v in a.verify]
    emit(
        {"subjects": a.subjects, "rate": a.rate, "seconds": a.seconds, "labeled_s": a.labeled_s,
         "runs": runs},
        a.out,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
