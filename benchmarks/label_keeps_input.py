"""What ``mocap-labeler label IN.c3d OUT.c3d`` keeps of each real take besides its points:
analog channels (compared sample for sample over the labeled frames), events, the first frame
(header and ``TRIAL:ACTUAL_START_FIELD``), the point units, and the parameter groups; for a
segment ``IN:start`` too. Needs the real takes (``MOCAP_DATA_DIR``, default
``../shared/data/real``); every C3D there with labels is labeled (the raw take, which has
none, and the BTS take, empty in its first frames, are labeled from a segment)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import emit

#: a segment per take that needs one (no labels in the first 50 frames, or none at all)
SEGMENTS = {"gait_bts_yup_22markers_100hz": ":297:600"}
SKIP = {"raw_unlabeled_kneel_to_run_240hz": "no labels: labeled with --model in BENCHMARKS.md"}
UP = {"gait_bts_yup_22markers_100hz": "y"}


def check(take: Path, segment: str, workdir: Path) -> dict:
    import ezc3d

    out = workdir / f"{take.stem}{segment.replace(':', '_')}.c3d"
    cmd = [sys.executable, "-m", "labeler_service.cli.main", "label", f"{take}{segment}",
           str(out), "--json", "--no-progress", "--up", UP.get(take.stem, "z")]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if run.returncode != 0:
        return {"take": take.stem + segment, "error": run.stderr.strip().splitlines()[-1:]}
    summary = json.loads(run.stdout.strip().splitlines()[-1])
    a, b = ezc3d.c3d(str(take)), ezc3d.c3d(str(out))
    start = int(segment.split(":")[1]) if segment else 0
    n = int(b["data"]["points"].shape[2])
    an = a["data"]["analogs"]
    per = an.shape[2] // a["data"]["points"].shape[2] if a["data"]["points"].shape[2] else 0
    same = None  # (no channel to compare)
    if an.shape[1]:
        cut = an[:, :, start * per : (start + n) * per]
        same = bool(np.array_equal(cut, b["data"]["analogs"], equal_nan=True))
    events = lambda c: list(c["parameters"].get("EVENT", {}).get("LABELS", {}).get("value", []))  # noqa: E731
    units = lambda c: list(c["parameters"]["POINT"].get("UNITS", {}).get("value", []))  # noqa: E731
    return {
        "take": take.stem + segment,
        "analog_channels": int(an.shape[1]),
        "analog_same": same,
        "events_same": events(a) == events(b),
        "events": len(events(a)),
        "first_frame": [
            int(a["header"]["points"]["first_frame"]) + 1 + start,
            int(b["header"]["points"]["first_frame"]) + 1,
        ],  # fmt: skip
        "units": [units(a), units(b)],
        "groups_lost": sorted(set(a["parameters"]) - set(b["parameters"])),
        "kept_from_input": summary["kept_from_input"],
        "agreement_with_input_labels": summary["agreement_with_input_labels"],
    }


def main() -> None:
    from labeler_service.testing.realdata import real_data_dir

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    root = real_data_dir()
    if root is None:
        emit({"skipped": "no real takes (MOCAP_DATA_DIR or ../shared/data/real)"}, a.out)
        return
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="label-keeps-") as d:
        for take in sorted(root.glob("*.c3d")):
            if take.stem in SKIP:
                rows.append({"take": take.stem, "skipped": SKIP[take.stem]})
                continue
            segs = [SEGMENTS.get(take.stem, "")]
            if not segs[0]:
                segs.append(":60")  # a segment: its own frames of the analog channels
            for seg in segs:
                rows.append(check(take, seg, Path(d)))
    emit({"takes": rows, "wall_s": round(time.perf_counter() - t0, 1)}, a.out)


if __name__ == "__main__":
    main()
