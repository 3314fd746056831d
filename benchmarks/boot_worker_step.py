"""Wall time of the service's first boot attempt in its boot worker process, by set-up.

The ``bench latency --start boot`` scene (simulated hug, model trained on the
``--train-seconds`` before the streamed part): a booting labeler driven as the service drives
it runs until its first attempt is due; then, for each set-up in turn (``--repeats`` rounds,
interleaved), a new :class:`~labeler_service.service.boot_worker.BootWorker` is started as the
service starts it and the attempt's step runs in it, timed from the request to the result:

- ``alone``: no helper process, the model sent with the first attempt (the booter is built
  then);
- ``prepared``: no helper, the booter built at start (``BootWorker.prepare``);
- ``helper``: prepared, and the subjects' hypotheses shared with the helper process.

Reports per set-up the first attempt's wall ms (each round), their median, the worker's
start + preparation wall ms, and a digest of the attempt's labels (every set-up must give the
same). Wall time: on a busy machine the worker's share of the cores decides it (note the load).

    .venv/bin/python benchmarks/boot_worker_step.py [--repeats 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import time

import numpy as np
from _common import add_hug_args, emit, hug_scene, until_first_attempt

from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.service.boot_worker import BootWorker

SETUPS = {"alone": (0, False), "prepared": (0, True), "helper": (1, True)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hug_args(ap, seconds=1.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    model, frames = hug_scene(a)
    lab = BootingLabeler(model, a.rate, boot=BootConfig(), inline_boot=False, inline_extend=False)
    snap, first = until_first_attempt(lab, frames)
    remote = snap.remote()
    walls: dict[str, list[float]] = {s: [] for s in a.setups}
    starts: dict[str, list[float]] = {s: [] for s in a.setups}
    digests: dict[str, set[str]] = {s: set() for s in a.setups}
    loads = []
    for _ in range(a.repeats):
        for name in a.setups:
            helpers, prepare = SETUPS[name]
            loads.append(os.getloadavg()[0])
            w = BootWorker(helpers=helpers)
            try:
                t0 = time.perf_counter()
                w.start()
                if prepare:
                    w.prepare(lab)
                starts[name].append((time.perf_counter() - t0) * 1e3)
                t0 = time.perf_counter()
                res, _, _ = w.step(lab.key, (lab.model, lab.boot_config), remote)
                walls[name].append((time.perf_counter() - t0) * 1e3)
            finally:
                w.close()
            digest = hashlib.sha256(np.ascontiguousarray(res.labels, dtype=np.int64).tobytes())
            digests[name].add(digest.hexdigest()[:16])
    emit(
        {
            "subjects": a.subjects, "rate": a.rate, "attempt_frame": first,
            "points": int(snap.points.shape[0]), "load": [round(x, 2) for x in loads],
            **{f"{s}_ms": [round(x, 1) for x in walls[s]] for s in a.setups},
            **{f"{s}_ms_median": round(statistics.median(walls[s]), 1) for s in a.setups},
            **{f"{s}_start_ms": [round(x, 1) for x in starts[s]] for s in a.setups},
            "labels_sha256": {s: sorted(digests[s]) for s in a.setups},
        },
        a.out,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
