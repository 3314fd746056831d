"""Boot with a model that lacks some of the scene's markers (issue 11, a partial model).

For each ``SCENE:CELL`` the cell is rebuilt as ``generalization.py --start boot`` builds it,
except that the model is trained with the markers ``--drop`` lists hidden (their columns left
out of the training scene, as a ROM take that never showed them); every subject whose local
marker name is listed loses it. Per subject one JSON line: ``boot_s`` (the matrix's criterion:
95 % of every visible marker right), ``boot_s_known`` (``evaluate``'s: the same criterion over
the markers the model knows: the best a labeler without the others can do), wrong labels
(on known and on unknown markers' points) and unlabeled known markers after the first boot.

    .venv/bin/python benchmarks/boot_partial.py tune-alone-clinical_gait_pig_35markers_100hz:alone \
        --drop C7 RSHO LASI RHEE LBAK RBAK
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from generalization import _cells, boot_frames, matrix, training_capture

import labeler_service.evaluation.scoring as scoring
from labeler_service.capture import split_label
from labeler_service.evaluation.scoring import (
    CORRECT,
    NOT_VISIBLE,
    UNLABELED,
    evaluate,
)


def _train_without(scene, plan, drop: set[str]):
    from offline.structure import StructureTrainer

    cap = training_capture(scene, plan)
    keep = [i for i, lab in enumerate(cap.labels) if split_label(lab)[1] not in drop]
    return StructureTrainer().fit([cap.select(keep)]).model_


def run(name: str, cell: str, drop: set[str]) -> list[dict]:
    scene = next(s for s in matrix("all", False) if s.name == name)
    frames = scene.frames(8.0, 1200)
    frames, plan = boot_frames(scene, frames)
    cap = scene.compose(frames)
    model = _train_without(scene, plan, drop)
    opts = {} if len(scene.takes) == 1 else _cells(scene.rate())[cell]
    pairs: dict[tuple[int, int], list[int]] = {}
    made: list = []
    add, make = scoring.Scorer.add, scoring.make_labeler

    def spy_add(self, f, truth, out, **kw):  # every wrong (true, given) pair, frames
        add(self, f, truth, out, **kw)
        if out is None or f < self.init_frames:
            return
        t = np.asarray(truth)
        lab = np.asarray(out.point_labels)
        bad = (t >= 0) & (lab >= 0) & (lab != t)
        for a, b in zip(t[bad].tolist(), lab[bad].tolist(), strict=True):
            pairs.setdefault((a, b), []).append(f)

    def spy_make(*a, **k):
        lab = make(*a, **k)
        made.append(lab)
        return lab

    scoring.Scorer.add, scoring.make_labeler = spy_add, spy_make
    try:
        report, scores = evaluate(
            cap, methods=["online"], init_frames=0, seed=scene.seed, model=model, **opts
        )
    finally:
        scoring.Scorer.add, scoring.make_labeler = add, make
    sc = scores["online"]
    raster, names = sc.raster, list(sc.marker_names)
    known = set(model.marker_names)
    out = []
    for subj, bs in report["boot_s"].items():
        cols = [j for j, n in enumerate(names) if split_label(n)[0] == subj]
        kcols = [j for j in cols if names[j] in known]
        ucols = [j for j in cols if names[j] not in known]
        rk, ru = raster[:, kcols], raster[:, ucols]
        visk = (rk != NOT_VISIBLE).sum(1)
        okk = (rk == CORRECT).sum(1)
        wk = int(((rk != NOT_VISIBLE) & (rk != CORRECT) & (rk != UNLABELED)).sum())
        wu = int(((ru != NOT_VISIBLE) & (ru != CORRECT) & (ru != UNLABELED)).sum())
        out.append(
            {
                "cell": f"{name}:{cell}",
                "subject": subj,
                "dropped": sorted(split_label(names[j])[1] for j in ucols),
                "boot_s": bs,
                "boot_s_known": report["boot_s_known"].get(subj, bs),
                "wrong_known": wk,
                "wrong_on_unknown": wu,
                "unlabeled_known": int((rk == UNLABELED).sum()),
                "visible_known": int(visk.sum()),
                "accuracy_known": round(float(okk.sum() / max(1, visk.sum())), 4),
                "events": [(round(float(t), 2), e) for t, e, n in made[0].events if n == subj][:8],
                "wrong_pairs": sorted(
                    (
                        [
                            split_label(names[a])[1],
                            split_label(names[b])[1],
                            len(fs),
                            fs[0],
                            fs[-1],
                            names[a] in known,
                        ]
                        for (a, b), fs in pairs.items()
                        if a in cols
                    ),
                    key=lambda x: -x[2],
                )[:12],
            }
        )
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cells", nargs="+", help="SCENE:CELL")
    ap.add_argument("--drop", nargs="*", default=[], help="local marker names the model lacks")
    a = ap.parse_args(argv)
    for arg in a.cells:
        name, cell = arg.rsplit(":", 1)
        for row in run(name, cell, set(a.drop)):
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
