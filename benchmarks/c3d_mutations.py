"""Damaged C3D files: real takes with 1-8 bytes overwritten (0x00, 0x7F, 0x80, 0xFF or random)
in the header or the first 0.6-20 KB of the parameter section. Each file is read twice, each
time in a child process so a crash only ends the child: by ezc3d alone (``ezc3d.c3d``) and by
our reader (``read_capture``, which walks the parameter section and forks a probe read first).
Counted per reader: killed by a signal, hung past ``--timeout`` s, a clean error, read.

    MOCAP_DATA_DIR=../shared/data/real .venv/bin/python benchmarks/c3d_mutations.py --files 350
"""

from __future__ import annotations

import argparse
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import emit, real_args

#: the child of each reader: prints "ok" or "error" (a clean exception), or dies
_EZC3D = (
    "import sys, ezc3d\ntry:\n    ezc3d.c3d(sys.argv[1])\nexcept Exception:\n"
    "    print('error')\nelse:\n    print('ok')\n"
)
_OURS = (
    "import sys\nfrom labeler_service.capture.io import read_capture\n"
    "from labeler_service.errors import CaptureError\ntry:\n    read_capture(sys.argv[1])\n"
    "except CaptureError:\n    print('error')\nelse:\n    print('ok')\n"
)


def mutate(data: bytes, rng: random.Random) -> bytes:
    """``data`` with 1-8 bytes overwritten in the header (15 %) or the parameter section."""
    b = bytearray(data)
    start = 512 * (b[0] - 1)
    n = rng.choice([1, 2, 4, 8])
    if rng.random() < 0.15:
        at = rng.randrange(0, 512 - n)
    else:
        span = rng.choice([600, 3000, 20000])
        at = rng.randrange(start, min(len(b) - n, start + span))
    value = rng.choice([0x00, 0x7F, 0x80, 0xFF, None])
    for i in range(n):
        b[at + i] = rng.randrange(256) if value is None else value
    return bytes(b)


def read_in_child(code: str, path: Path, timeout: float) -> str:
    """``killed``, ``hung``, ``error`` or ``ok``: what reading ``path`` with ``code`` did."""
    try:
        run = subprocess.run(
            [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return "hung"
    if run.returncode < 0:
        return "killed"
    out = run.stdout.strip().splitlines()
    return out[-1] if run.returncode == 0 and out and out[-1] in ("ok", "error") else "error"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=100, help="damaged files")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds a read may take")
    a, root = real_args(ap)
    if root is None:
        return
    t0 = time.perf_counter()
    takes = sorted(root.glob("*.c3d"))
    rng = random.Random(a.seed)
    counts = {r: dict.fromkeys(("killed", "hung", "error", "ok"), 0) for r in ("ezc3d", "ours")}
    ours_failed = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(a.files):
            src = rng.choice(takes)
            path = Path(tmp) / f"m{k}.c3d"
            path.write_bytes(mutate(src.read_bytes(), rng))
            for reader, code in (("ezc3d", _EZC3D), ("ours", _OURS)):
                got = read_in_child(code, path, a.timeout)
                counts[reader][got] += 1
                if reader == "ours" and got in ("killed", "hung"):
                    ours_failed.append({"file": k, "take": src.name, "outcome": got})
            path.unlink()
    emit(
        {
            "files": a.files,
            "seed": a.seed,
            "ezc3d": counts["ezc3d"],
            "read_capture": counts["ours"],
            "read_capture_killed_or_hung": ours_failed,
            "wall_s": round(time.perf_counter() - t0, 1),
        },
        a.out,
    )


if __name__ == "__main__":
    main()
