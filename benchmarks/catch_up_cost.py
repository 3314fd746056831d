"""CPU of a first boot through the service's path, in process: the attempt, then its catch-up.

The service's first boot of a crowd is the attempt (``BootingLabeler.boot_step``, in the boot
worker) and then its catch-up (``BootingLabeler.catch_up``: the shadow installs the result,
extends the booted subjects, labels the frames recorded since the snapshot, extends again);
only then is anyone labeled. This script does the same in one process on the ``bench latency
--start boot`` scene (simulated hug, a model trained on the ``--train-seconds`` before the
streamed part): the booting labeler runs as the service drives it (``inline_boot=False,
inline_extend=False``) until the first attempt is due, the attempt runs, ``--late-s`` of
frames pass (the attempt's wall time in the service), then the catch-up runs and the result is
installed. It reports the CPU time of the attempt and of the catch-up, by stage
(``extend_ms``: the extension right after the install and the one at the end), and a digest
of the labels (the attempt's, and every point label and position of the ``--after-s`` frames
after the install): two codes with the same digest labeled the stream the same.

    .venv/bin/python benchmarks/catch_up_cost.py [--late-s 1.5] [--out FILE]
"""

from __future__ import annotations

import argparse
import hashlib
import time

import numpy as np
from _common import add_hug_args, emit, hug_scene, until_first_attempt

from labeler_service.labeling import booting
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import BootingLabeler


def _timed(stages: dict[str, list[float]], name: str) -> None:
    """Wraps ``BootingLabeler.<name>`` to append each call's CPU ms to ``stages[name]``."""
    orig = getattr(BootingLabeler, name)

    def run(self, *args, **kwargs):
        c0 = time.process_time()
        try:
            return orig(self, *args, **kwargs)
        finally:
            stages.setdefault(name, []).append((time.process_time() - c0) * 1e3)

    setattr(booting.BootingLabeler, name, run)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hug_args(ap, seconds=5.0)
    ap.add_argument("--late-s", type=float, default=1.5, help="stream seconds the result is late")
    ap.add_argument("--after-s", type=float, default=1.0, help="seconds labeled after install")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    model, frames = hug_scene(a)
    lab = BootingLabeler(model, a.rate, boot=BootConfig(), inline_boot=False, inline_extend=False)
    lab.warmup()
    snap, first = until_first_attempt(lab, frames)
    f = first + 1
    c0 = time.process_time()
    res = lab.boot_step(snap)
    attempt_ms = (time.process_time() - c0) * 1e3
    for _ in range(int(round(a.late_s * a.rate))):  # the frames the attempt took
        lab.process(frames.points[f], float(frames.times[f]))
        f += 1
    stages: dict[str, list[float]] = {}
    for name in ("_begin_catch_up", "_catch_up_frames", "_extend"):
        _timed(stages, name)
    c0 = time.process_time()
    caught = lab.catch_up(snap, res)
    catch_ms = (time.process_time() - c0) * 1e3
    booted = lab.install_boot(snap, res)
    digest = hashlib.sha256(np.ascontiguousarray(res.labels, dtype=np.int64).tobytes())
    for _ in range(int(round(a.after_s * a.rate))):
        out = lab.process(frames.points[f], float(frames.times[f]))
        f += 1
        digest.update(np.ascontiguousarray(out.point_labels, dtype=np.int64).tobytes())
        digest.update(np.ascontiguousarray(out.positions, dtype=np.float32).tobytes())
    emit(
        {
            "subjects": a.subjects, "rate": a.rate, "late_s": a.late_s,
            "attempt_frame": first,
            "attempt_cpu_ms": round(attempt_ms, 1),
            "caught_up": caught,
            "catch_up_cpu_ms": round(catch_ms, 1),
            "extend_ms": [round(x, 1) for x in stages.get("_extend", [])],
            "catch_up_frames_ms": round(sum(stages.get("_catch_up_frames", [])), 1),
            "subjects_booted": len(res.subjects),
            "installed": len(booted),
            "labels_sha256": digest.hexdigest()[:16],
        },
        a.out,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
