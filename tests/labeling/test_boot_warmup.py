"""The boot worker's warm-up covers every kernel a first attempt runs.

The service's boot worker warms its kernels at start (``warmup_kernels`` and
``warmup_labeler``, :mod:`labeler_service.service.boot_worker`); a kernel left out compiles
inside the first attempt instead. In a fresh checkout that is seconds: the two anchor-triangle
kernels added without a warm-up made ``make demo``'s first run boot in 1.9 s instead of
0.17 s (80.9 % instead of 98.4 % over the stream). Here a fresh interpreter warms up as the
worker does, then boots a walk as the service drives it (the attempt, frames labeled
meanwhile, the catch-up, the install, frames after): no kernel may gain a compiled signature
after the warm-up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CODE = r"""
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from labeling.test_boot import RATE, Stream
from labeling.walks import split_walk
from labeler_service.labeling.boot import warmup_kernels
from labeler_service.labeling.booting import BootingLabeler, warmup_labeler

model, cap = split_walk(3, 4.0, seed=11, rate=RATE, ghosts=1.0)
stream = Stream(cap, model, seed=2)
frames = [stream.frame(f)[0] for f in range(cap.n_frames)]
lab = BootingLabeler(model, RATE, inline_boot=False, inline_extend=False)
warmup_kernels()
warmup_labeler(RATE, lab.config)


def counts():
    out = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("labeler_service"):
            continue
        for v in list(vars(mod).values()):
            if isinstance(v, CPUDispatcher):
                out[v.py_func.__module__ + "." + v.py_func.__name__] = len(v.signatures)
    return out


before = counts()
snap = result = None
late = 0
for f, pts in enumerate(frames):
    lab.process(pts, f / RATE)
    if snap is None and lab.needs_boot():
        snap = lab.boot_snapshot()
        result = lab.boot_step(snap)
        late = 80  # frames the attempt takes in the worker (a catch-up from 0.5 s)
    elif snap is not None and late > 0:
        late -= 1
        if late == 0:
            caught = lab.catch_up(snap, result)
            lab.install_boot(snap, result)
after = counts()
grown = sorted(k for k, n in after.items() if n > before.get(k, 0))
print(json.dumps({"grown": grown, "caught": bool(caught), "booted": list(lab.active_subjects),
                  "kernels": len(after)}))
"""


def test_no_kernel_compiles_after_the_boot_workers_warm_up():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])}
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", CODE], cwd=ROOT, env=env, check=True,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    res = json.loads(out.stdout.strip().splitlines()[-1])
    # the run did what the worker does: an attempt that booted, and its catch-up
    assert res["caught"] and len(res["booted"]) == 3 and res["kernels"] > 50
    assert res["grown"] == []
