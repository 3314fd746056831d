"""The labeled start from a model trained elsewhere, on the cross-take matrix.

``evaluate SCENE --model M --init-frames N`` on the scenes of ``generalization.py --start boot``:
M is trained (``train structure``) on that mode's training scene (other segments of the same
takes), N is the matrix's 0.4 s init window, and the labeled frames give the subjects' first
labels (no boot). Where ``--start boot`` asks how well a stream starts with no label at all,
this asks how well a model start holds up after a few labeled frames: a marker those frames
never showed must be labeled from its template. Cells that do not fit a scene cut for room
are left out (as there).

``--labeler plain`` runs the plain labeler of the model instead (``Labeler.from_model``: the
service's ``boot = false`` start from labeled frames); ``--set NAME=VALUE`` overrides a
``LabelerConfig`` field of the online labeler (e.g. ``--set acquire_unseen=false``).

Reported: one line per cell on stderr, then one JSON object: every cell (``accuracy``,
``accuracy_seen``, ``errors``, ``max_swap_frames``, ``ghost_labeled_rate``) and per group
and cell the worst and mean ``accuracy_seen``, the longest swap and the largest ghost rate.

    .venv/bin/python benchmarks/model_start.py --jobs 2 --out FILE
    .venv/bin/python benchmarks/model_start.py --cells rate quarter --split tune
    .venv/bin/python benchmarks/model_start.py --labeler plain --cells rate quarter gaps2 --jobs 2
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import generalization as gen
from _common import emit, warm_kernels

from labeler_service.errors import MocapError
from labeler_service.evaluation import scoring
from labeler_service.evaluation.scoring import evaluate
from labeler_service.labeling import registry
from labeler_service.labeling.config import LabelerConfig

CELLS = ("rate", "half", "quarter", "gaps2", "ghosts3", "occlude2")


def run_cell(job: tuple[Any, str, float, int]) -> dict | None:
    """One scene and cell; None when the scene has no training segment or the cell does not
    fit the (cut) scene."""
    scene, cell, seconds, max_frames = job
    frames, plan = gen.boot_frames(scene, scene.frames(seconds, max_frames))
    if plan is None:
        return None
    cap = scene.compose(frames)
    model = gen._train(scene, plan)
    opts = {} if cell == "alone" else gen._cells(scene.rate())[cell]
    init = max(1, round(gen.INIT_S * scene.rate() / opts.get("downsample", 1)))
    t0 = time.perf_counter()
    try:
        rep, _ = evaluate(
            cap, methods=["online"], init_frames=init, seed=scene.seed, model=model, **opts
        )
    except MocapError:
        return None
    keys = ("accuracy", "accuracy_seen", "errors", "max_swap_frames", "ghost_labeled_rate")
    return (
        {"scene": scene.name, "group": scene.group, "cell": cell, "init_frames": init}
        | {k: rep[k] for k in keys}
        | {"seconds": round(time.perf_counter() - t0, 2)}
    )


def use_labeler(kind: str, settings: dict[str, Any]) -> None:
    """Makes ``evaluate``'s online labeler of a model the ``plain`` one (``boot=False``) or
    keeps the ``booting`` one, with ``settings`` over the default ``LabelerConfig`` (in this
    process and the workers it forks)."""
    make = registry.make_labeler

    def made(name: str, **kw: Any) -> Any:
        if kw.get("model") is not None and name == "online":
            kw["boot"] = kw["boot"] and kind == "booting"
            kw["config"] = LabelerConfig(**settings)
        return make(name, **kw)

    scoring.make_labeler = made  # type: ignore[assignment]


def _setting(text: str) -> tuple[str, Any]:
    name, _, value = text.partition("=")
    if name not in LabelerConfig.model_fields or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: not NAME=VALUE of a LabelerConfig field")
    return name, value


def summarize(rows: list[dict]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for r in rows:
        out.setdefault(r["group"], {}).setdefault(r["cell"], []).append(r)
    return {
        g: {
            c: {
                "scenes": len(rs),
                "worst_accuracy_seen": min(r["accuracy_seen"] for r in rs),
                "worst_scene": min(rs, key=lambda r: r["accuracy_seen"])["scene"],
                "mean_accuracy_seen": round(statistics.mean(r["accuracy_seen"] for r in rs), 6),
                "max_swap_frames": max(r["max_swap_frames"] for r in rs),
                "ghost_labeled_rate_max": max((r["ghost_labeled_rate"] or 0.0) for r in rs),
            }
            for c, rs in cells.items()
        }
        for g, cells in out.items()
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", choices=("all", *gen.GROUPS), default="all")
    p.add_argument("--cells", nargs="+", choices=CELLS, default=list(CELLS))
    p.add_argument("--seconds", type=float, default=8.0, help="longest scene (s)")
    p.add_argument("--max-frames", type=int, default=1200, help="longest scene (frames)")
    p.add_argument("--labeler", choices=("booting", "plain"), default="booting")
    p.add_argument("--set", type=_setting, action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    if a.labeler != "booting" or a.set:
        use_labeler(a.labeler, dict(a.set))
    scenes = gen.matrix(a.split, False)
    jobs = [
        (s, c, a.seconds, a.max_frames)
        for s in scenes
        for c in (a.cells if len(s.takes) > 1 else ["alone"])
    ]
    rows = []
    warm_kernels()  # (in the parent: the workers inherit them, none compiles)
    with ProcessPoolExecutor(max(1, a.jobs)) as ex:
        for r in ex.map(run_cell, jobs):
            if r is not None:
                rows.append(r)
                print(
                    f"{r['scene']:>10} {r['cell']:<8} {100 * r['accuracy_seen']:7.3f} "
                    f"swap {r['max_swap_frames']}",
                    file=sys.stderr,
                    flush=True,
                )
    settings = {"labeler": a.labeler, "set": dict(a.set)}
    emit({"settings": settings, "cells": rows, "summary": summarize(rows)}, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
