"""How far ahead can a low frame rate be predicted? (issue 10, class B; docs/algorithm.md).

For every scene of the cross-take matrix (``generalization.py``) at a fraction of its rate,
the true marker tracks (no labeler: a perfect past) are predicted one frame ahead by:

- ``cv``: constant velocity of each marker (``2 p[t-1] - p[t-2]``), what Eq. 3 converges to;
- ``twist``: each rigid body (trained on the 0.4 s init window as the labeler trains it) moved
  again by its last inter-frame rigid motion (constant linear and angular velocity);
- ``cv_subject_median``: ``cv`` minus the subject's median error (an oracle common-mode shift);
- ``cv_body_translation``: ``cv`` minus the body's mean error (an oracle per-body shift);
- ``cv_body_rigid``: ``cv`` after the best rigid motion of each body onto its true points (an
  oracle per-body registration: what is left is the body's own non-rigidity).

Printed: the 50/90/99th percentiles of each error (mm) per group, and the share of ``cv``
errors larger than half the distance to the nearest other marker (where a nearest-point gate
must fail). Accuracy is not involved: this bounds what any motion model can do.

    .venv/bin/python benchmarks/lowrate_prediction.py --downsample 4
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
from _common import emit
from generalization import INIT_S, load, matrix

from labeler_service.capture import split_label, subject_groups
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.geometry import kabsch
from labeler_service.labeling.training import train_subject


def _rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``src`` moved by the least-squares proper rigid motion onto ``dst``."""
    R, t = kabsch(src, dst)
    return src @ R.T + t


def _scene_errors(scene: Any, step: int, out: dict[str, list[np.ndarray]]) -> None:
    rate = scene.rate()
    frames = scene.frames(8.0, 1200)
    cap = scene.compose(frames)
    keep = ~cap.ghost_mask
    names = [n for n, k in zip(cap.labels, keep, strict=True) if k]
    P = cap.positions[::step][:, keep].astype(np.float64)
    init = max(3, round(INIT_S * rate / step))
    bodies: list[list[int]] = []
    c = LabelerConfig()  # bodies as the labeler trains them (Labeler.train_model)
    for subj, cols in subject_groups(names).items():
        markers = [split_label(names[i])[1] for i in cols]
        model = train_subject(
            subj,
            markers,
            P[:init, cols],
            rate / step,
            tolerance_mm=c.body_tolerance_mm,
            distance_weight=c.body_distance_weight,
            min_size=c.body_min_size,
            max_size=c.body_max_size,
            all_seeds=c.body_all_seeds,
        )
        bodies += [[cols[i] for i in b] for b in model.bodies]
    groups = list(subject_groups(names).values())
    F = P.shape[0]
    for t in range(max(2, init), F):
        cv = 2.0 * P[t - 1] - P[t - 2]
        e = P[t] - cv
        ok = np.all(np.isfinite(e), axis=1)
        d = np.linalg.norm(P[t][:, None] - P[t][None], axis=2)
        np.fill_diagonal(d, np.inf)
        nn = np.nanmin(np.where(np.isfinite(d), d, np.inf), axis=1)
        out["cv"].append(np.linalg.norm(e[ok], axis=1))
        out["cv_over_half_nn"].append((np.linalg.norm(e[ok], axis=1) > 0.5 * nn[ok]) * 1.0)
        for g in groups:
            gg = [i for i in g if ok[i]]
            if len(gg) >= 3:
                r = e[gg] - np.median(e[gg], axis=0)
                out["cv_subject_median"].append(np.linalg.norm(r, axis=1))
        for b in bodies:
            A, B, C = P[t - 2, b], P[t - 1, b], P[t, b]
            if not (np.isfinite(A).all() and np.isfinite(B).all() and np.isfinite(C).all()):
                continue
            R, tt = kabsch(A, B)
            out["twist"].append(np.linalg.norm(B @ R.T + tt - C, axis=1))
            eb = C - cv[b]
            out["cv_body_translation"].append(np.linalg.norm(eb - eb.mean(axis=0), axis=1))
            out["cv_body_rigid"].append(np.linalg.norm(_rigid(cv[b], C) - C, axis=1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=4, help="fraction of the scene rate")
    ap.add_argument("--split", choices=("all", "tune", "holdout"), default="all")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args(argv)
    result: dict[str, Any] = {"downsample": args.downsample, "groups": {}}
    keys = ("cv", "twist", "cv_subject_median", "cv_body_translation", "cv_body_rigid")
    for scene in matrix(args.split, quick=False):
        if len(scene.takes) < 2:
            continue
        for t, _ in scene.takes:
            load(t)
        out = result["groups"].setdefault(scene.group, {"scenes": 0, "_e": {}})
        errs = out["_e"]
        for k in (*keys, "cv_over_half_nn"):
            errs.setdefault(k, [])
        _scene_errors(scene, args.downsample, errs)
        out["scenes"] += 1
        print(f"{scene.name}: done", file=sys.stderr)
    for g in result["groups"].values():
        errs = g.pop("_e")
        for k in keys:
            v = np.concatenate(errs[k]) if errs[k] else np.zeros(1)
            g[k + "_p50_p90_p99_mm"] = [round(float(x), 1) for x in np.percentile(v, [50, 90, 99])]
        share = np.concatenate(errs["cv_over_half_nn"])
        g["cv_over_half_nearest_share"] = round(float(share.mean()), 4)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
