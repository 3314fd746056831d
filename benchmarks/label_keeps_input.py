"""What ``mocap-labeler label IN.c3d OUT.c3d`` keeps of each real take besides its points:
analog channels (compared sample for sample over the labeled frames), events, the first frame
(header and ``TRIAL:ACTUAL_START_FIELD``), the point units, and the parameter groups; for a
segment ``IN:start`` too, whose events must be those within its frames. And the hidden markers'
estimates OUT holds (residual 0, C3D's calculated point): how many, how many where IN has that
marker visible (the labeler lost a point it had), and how far those lie from IN's point.
Needs the real takes (``MOCAP_DATA_DIR``, default ``../shared/data/real``); every C3D there
with labels is labeled (the raw take, which has none, and the BTS take, empty in its first
frames, are labeled from a segment)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import emit, real_args

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
    # IN's events within OUT's frames (times on the take's time base: frame k at k / rate s)
    rate = float(a["parameters"]["POINT"]["RATE"]["value"][0])
    f0 = int(a["header"]["points"]["first_frame"]) + start
    ev = a["parameters"].get("EVENT", {})
    want = events(a)
    if want and "TIMES" in ev:
        t = np.asarray(ev["TIMES"]["value"], dtype=np.float64)
        t = 60.0 * t[0] + t[1]
        inside = (t >= (f0 - 0.5) / rate) & (t <= (f0 + n - 0.5) / rate)
        want = [x for x, k in zip(want, inside, strict=True) if k]
    # the estimates written, against IN's point where IN has the marker
    la = list(a["parameters"]["POINT"]["LABELS"]["value"])
    lb = list(b["parameters"]["POINT"]["LABELS"]["value"])
    res = np.asarray(b["data"]["meta_points"]["residuals"])[0]  # (M, F)
    scale = 1000.0 if units(b) and units(b)[0].strip().lower() in ("m", "meter", "metre") else 1.0
    n_calc, errs = int((res == 0.0).sum()), []
    for i, name in enumerate(lb):
        if name.startswith("*") or name not in la:
            continue
        calc = np.flatnonzero(res[i] == 0.0)
        if calc.size:
            j = la.index(name)
            pa = a["data"]["points"][:3, j, start + calc]
            pb = b["data"]["points"][:3, i, calc]
            ra = np.asarray(a["data"]["meta_points"]["residuals"])[0, j, start + calc]
            seen = (ra >= 0) & np.any(pa != 0.0, axis=0)  # (IN's gaps: residual < 0 or 0,0,0)
            e = np.linalg.norm(pa - pb, axis=0)[seen] * scale
            errs += e[np.isfinite(e)].tolist()
    err = np.asarray(errs)
    return {
        "take": take.stem + segment,
        "analog_channels": int(an.shape[1]),
        "analog_same": same,
        "events_same": want == events(b),
        "events": [len(events(a)), len(events(b))],
        "estimates": n_calc,
        "estimates_where_in_has_the_point": int(err.size),
        "their_error_mm_p50_max": [round(float(np.median(err)), 1), round(float(err.max()), 1)]
        if err.size
        else None,
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
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a, root = real_args(ap)
    if root is None:
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
