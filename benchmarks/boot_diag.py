"""Per subject-cell boot diagnosis of the ``--start boot`` matrix (issue 11).

For each given ``SCENE:CELL`` the cell is rebuilt exactly as ``generalization.py --start boot``
builds it (scene, training segment, model, corruption), booted with no labeled frame, and each
subject's labels over its active frames are summarised: when the boot first activated it, the
fraction of its visible markers right, wrong and unlabeled at 0.5 s and over the scene, and the
markers that hold it below the 95 % criterion (wrong or unlabeled in most frames after the
subject was first activated, each with whether the model knows it). One JSON line per
subject-cell on stdout.

    .venv/bin/python benchmarks/boot_diag.py tune03:half tune21:rate
"""

from __future__ import annotations

import json
import sys

import numpy as np
from generalization import _cells, _train, boot_frames, matrix

import labeler_service.evaluation.scoring as scoring
from labeler_service.capture import split_label
from labeler_service.evaluation.scoring import (
    CORRECT,
    CROSS_SUBJECT,
    NOT_VISIBLE,
    UNLABELED,
    evaluate,
)

_BUILT: dict = {}


def diagnose(name: str, cell: str) -> list[dict]:
    if name not in _BUILT:
        scene = next(s for s in matrix("all", False) if s.name == name or s.name.endswith(name))
        frames = scene.frames(8.0, 1200)
        frames, plan = boot_frames(scene, frames)
        _BUILT.clear()
        _BUILT[name] = (scene, scene.compose(frames), _train(scene, plan))
    scene, cap, model = _BUILT[name]
    opts = {} if len(scene.takes) == 1 else _cells(scene.rate())[cell]
    made = []
    real = scoring.make_labeler

    def spy(*a, **k):
        lab = real(*a, **k)
        made.append(lab)
        return lab

    scoring.make_labeler = spy
    try:
        report, scores = evaluate(
            cap, methods=["online"], init_frames=0, seed=scene.seed, model=model, **opts
        )
    finally:
        scoring.make_labeler = real
    sc = scores["online"]
    raster = sc.raster
    names = list(sc.marker_names)
    rate = report["rate_hz"]
    lab = made[0]
    events = list(lab.events)
    known = set(model.marker_names)
    out = []
    for subj, bs in report["boot_s"].items():
        cols = [j for j, n in enumerate(names) if split_label(n)[0] == subj]
        r = raster[:, cols]
        vis = r != NOT_VISIBLE
        nvis = vis.sum(1)
        ok = (r == CORRECT).sum(1)
        unl = (r == UNLABELED).sum(1)
        wrong = nvis - ok - unl
        boots = [round(float(t), 3) for t, e, n in events if n == subj and e == "boot"]
        # frames counted from the stream start (init 0)
        ts = np.arange(len(r)) / rate
        first_act = boots[0] if boots else None
        span = ts >= (first_act if first_act is not None else 1e9)
        per_marker = []
        for j, c in enumerate(cols):
            v = vis[span, j]
            if v.sum() == 0:
                continue
            bad_w = int(((r[span, j] != CORRECT) & (r[span, j] != UNLABELED) & v).sum())
            cross = int(((r[span, j] == CROSS_SUBJECT) & v).sum())
            bad_u = int(((r[span, j] == UNLABELED) & v).sum())
            frac = (bad_w + bad_u) / v.sum()
            if frac > 0.3:
                per_marker.append(
                    {
                        "m": split_label(names[c])[1],
                        "wrong": round(bad_w / v.sum(), 2),
                        "unl": round(bad_u / v.sum(), 2),
                        "cross": round(cross / v.sum(), 2),
                        "in_model": names[c] in known,
                    }
                )
        good = np.where(nvis > 0, ok / np.maximum(nvis, 1), np.nan)
        half = min(len(r) - 1, int(0.5 * rate))
        late = []  # markers not right at 0.5 s: (name, code then, first right after, in model)
        for j, c in enumerate(cols):
            if r[half, j] in (NOT_VISIBLE, CORRECT):
                continue
            hit = np.flatnonzero(r[half:, j] == CORRECT)
            late.append(
                [
                    split_label(names[c])[1],
                    int(r[half, j]),
                    None if not hit.size else round(float((half + hit[0]) / rate), 2),
                ]
            )
        tail = span & (nvis > 0)
        out.append(
            {
                "cell": f"{name}:{cell}",
                "subject": subj,
                "boot_s": bs,
                "first_boot_event": first_act,
                "events": [(round(float(t), 2), e) for t, e, n in events if n == subj][:12],
                "n_markers": len(cols),
                "model_missing": [n for n in (names[c] for c in cols) if n not in known],
                "at_0.5s": None
                if nvis[half] == 0
                else [int(ok[half]), int(wrong[half]), int(unl[half]), int(nvis[half])],
                "after_act_ok": None if not tail.any() else round(float(np.nanmean(good[tail])), 3),
                "after_act_wrong": None
                if not tail.any()
                else round(float((wrong[tail] / nvis[tail]).mean()), 3),
                "after_act_unl": None
                if not tail.any()
                else round(float((unl[tail] / nvis[tail]).mean()), 3),
                "frac95": None if not tail.any() else round(float((good[tail] >= 0.95).mean()), 3),
                "bad_markers": per_marker,
                "late_at_0.5s": late,
                "frames": len(r),
                "rate": rate,
            }
        )
    return out


def main(argv: list[str]) -> int:
    for arg in argv:
        name, cell = arg.split(":")
        try:
            rows = diagnose(name, cell)
        except Exception as exc:  # noqa: BLE001 - a diagnosis goes on with the next cell
            print(json.dumps({"cell": arg, "error": repr(exc)}), flush=True)
            continue
        for row in rows:
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
