"""Issue #3 acceptance in one run: scenes (a), (b), (c) x settings, online vs closest point.

Scenes (as in the issue):
  (a) the two CMU takes composed at radius 300 mm (1200 frames, seed 7);
  (b) those plus the 62-marker kneel-to-prone take decimated to 120 Hz (800 frames, seed 7);
  (c) a simulated 6-performer hug (10 s, seed 1).
(a) and (b) need the real captures (MOCAP_DATA_DIR or ../shared/data/real) and are skipped
without them. Settings: plain, --downsample 4, --ghosts 3, --gaps 2 --gap-frames 20. Every
number comes from ``labeler_service.evaluation.scoring.evaluate``, exactly what ``mocap-labeler
evaluate``
prints; the same scene files can be written with ``--write DIR`` to rerun any cell by hand.

    .venv/bin/python benchmarks/acceptance.py --out acceptance.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from labeler_service.capture import Capture, write_capture
from labeler_service.evaluation.scoring import evaluate
from labeler_service.labeling.registry import LABELED_STARTS
from labeler_service.scenes.compose import compose_scene
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.testing.realdata import real_file

SETTINGS: dict[str, dict] = {
    "plain": {},
    "downsample4": {"downsample": 4},
    "ghosts3": {"ghosts": 3.0},
    "gaps2x20": {"gaps": 2, "gap_frames": 20},
}
KEYS = (
    "accuracy",
    "baseline_accuracy",
    "ghost_labeled_rate",
    "recovery_mean_mm",
    "recovery_p95_mm",
    "recovery_mean_ratio",
    "recovery_rate",
    "ms_per_frame_p50",
    "ms_per_frame_p99",
    "frames",
    "subjects",
    "markers",
)


def scenes() -> dict[str, Capture | str]:
    """Scene name -> capture, or the reason it is skipped."""
    out: dict[str, Capture | str] = {}
    a = real_file("cmu_01_01_playground.c3d")
    b = real_file("cmu_02_05_expressions.c3d")
    k = real_file("kneel_to_prone_62markers_240hz.c3d")
    if a and b:
        out["a"] = compose_scene([f"{a}:600", str(b)], radius=300.0, frames=1200, seed=7)
    else:
        out["a"] = "real CMU takes not found"
    if a and b and k:
        out["b"] = compose_scene(
            [f"{a}:600", str(b), str(k)], radius=300.0, frames=800, seed=7, rate=120.0
        )
    else:
        out["b"] = "real takes not found"
    out["c"] = simulate_scene(performers=6, seconds=10.0, scenario="hug", seed=1)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    p.add_argument("--write", type=Path, default=None, help="write the scenes (C3D) here")
    p.add_argument("--only", nargs="+", default=None, help="scene names to run (a b c)")
    p.add_argument(
        "--labeled-start",
        choices=LABELED_STARTS,
        default="auto",
        help="evaluate --labeled-start: auto (default) and model run the online labeler's "
        "labeled start through the model-based labeler; labeler: the labeler trained in place",
    )
    args = p.parse_args()
    results: dict[str, dict] = {}
    for name, cap in scenes().items():
        if args.only and name not in args.only:
            continue
        if isinstance(cap, str):
            results[name] = {"skipped": cap}
            continue
        if args.write:
            write_capture(cap, args.write / f"scene_{name}.c3d")
        results[name] = {}
        for label, opts in SETTINGS.items():
            report, _ = evaluate(cap, seed=0, labeled_start=args.labeled_start, **opts)
            results[name][label] = {k: report.get(k) for k in KEYS}
            print(f"{name} {label}: {json.dumps(results[name][label])}", file=sys.stderr)
    text = json.dumps(results)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
