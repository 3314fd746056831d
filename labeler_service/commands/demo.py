"""``mocap-labeler demo``: compose a multi-person scene and score the labelers on it.

Interim demo of the foundation: the streaming pipeline (replay -> service -> subscriber) replaces
the in-process scoring once the service exists. The scene is composed from the real CMU takes when
they are present (``MOCAP_DATA_DIR`` or ``../shared/data/real``), else simulated.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from labeler_service.data import real_file


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("reports/demo"), help="report folder")
    p.add_argument("--seed", type=int, default=7, help="scene and corruption seed")
    p.add_argument("--frames", type=int, default=1200, help="scene length (frames)")


def _scene(seed: int, frames: int):
    a = real_file("cmu_01_01_playground.c3d")
    b = real_file("cmu_02_05_expressions.c3d")
    if a is not None and b is not None:
        from labeler_service.scenes.compose import compose_scene

        cap = compose_scene([f"{a}:600", str(b)], radius=300.0, frames=frames, seed=seed)
        return cap, "two real CMU takes composed at radius 300 mm"
    try:
        from labeler_service.scenes.simulate import simulate_scene
    except ImportError as exc:
        from labeler_service.errors import MocapError

        raise MocapError(
            "no real captures found (set MOCAP_DATA_DIR) and the simulator is not available"
        ) from exc
    cap = simulate_scene(performers=4, seconds=frames / 120.0, scenario="hug", seed=seed)
    return cap, "simulated 4-performer hug (no real captures found)"


def run(args: argparse.Namespace) -> int:
    from labeler_service.capture import write_capture
    from labeler_service.commands.evaluate import plot_accuracy_vs_downsampling
    from labeler_service.evaluate import evaluate

    cap, what = _scene(args.seed, args.frames)
    args.out.mkdir(parents=True, exist_ok=True)
    write_capture(cap, args.out / "scene.c3d")
    print(
        f"scene: {what}: {len(cap.subjects)} subjects, {cap.n_markers} markers, "
        f"{cap.n_frames} frames at {cap.rate:g} Hz -> {args.out / 'scene.c3d'}"
    )
    reports = {}
    curves: dict[str, list[tuple[int, float]]] = {}
    for factor in (1, 4):
        rep, _ = evaluate(
            cap,
            downsample=factor,
            gaps=2,
            gap_frames=20,
            ghosts=1.0,
            seed=args.seed,
            show_progress=sys.stderr.isatty(),
        )
        reports[f"downsample_{factor}"] = rep
        for name, s in rep["methods"].items():
            curves.setdefault(name, []).append((factor, s["accuracy"]))
            rec = s["recovery_mean_mm"]
            print(
                f"  {cap.rate / factor:5.0f} Hz  {name:14s} accuracy {100 * s['accuracy']:6.2f} %"
                f"  ghosts labeled {100 * (s['ghost_labeled_rate'] or 0):5.2f} %"
                f"  recovery {'-' if rec is None else f'{rec:.1f} mm':>8s}"
                f"  {s['ms_per_frame_p50']:.3f} ms/frame (p50)"
            )
        for note in rep["notes"]:
            print(f"  note: {note}")
    plot = plot_accuracy_vs_downsampling(curves, args.out / "accuracy_vs_downsampling.png")
    (args.out / "report.json").write_text(json.dumps({"scene": what, **reports}, indent=2))
    print(f"report: {args.out / 'report.json'}, {plot}")
    return 0
