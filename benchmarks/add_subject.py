"""Cost of installing a booted subject in a running labeler: rebuild vs ``add_subjects``.

A 10-performer walk at 360 Hz; the model is trained on the first half, the second half is
streamed. Nine subjects are labeled; the tenth is installed from the boot window (24 labeled
frames, the ``BootingLabeler`` window at 360 Hz) in two ways, interleaved ``--repeats`` times:

- ``rebuild_ms``: what ``BootingLabeler`` did before ``add_subjects``: ``Labeler.from_model``
  of the ten subjects, the window as labeled first frames, and the first unlabeled frame (the
  warm start runs in it), minus one steady frame (``frame_ms_p50``);
- ``add_ms``: ``Labeler.add_subjects`` of the tenth subject on the running labeler (the nine
  others keep their state); ``drop_ms``: ``Labeler.drop_subject``.

``frame_ms_p50_inactive`` / ``frame_ms_p50_only9``: a steady frame with the tenth subject
built but inactive, and with a labeler of the nine alone (what carrying an inactive subject
costs per frame). Wall times on a shared machine: noisy, compare medians.

    .venv/bin/python benchmarks/add_subject.py [--repeats 7] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import emit

from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.simulate import simulate_scene

RATE = 360.0
W = 24


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out")
    args = ap.parse_args()
    from offline.structure import StructureTrainer

    cap = simulate_scene(10, 3.0, "walk", seed=5, rate=RATE, ghosts=0.0)
    half = cap.n_frames // 2
    model = StructureTrainer().fit([cap.frames(0, half)]).model_
    names = model.marker_names
    perm = [cap.labels.index(n) for n in names]
    pos = cap.positions[half:, perm]
    subjects = [s.name for s in model.subjects]
    nine = LabelerModel(rate=model.rate, subjects=model.subjects[:-1], source=model.source)

    def frame(f: int) -> tuple[np.ndarray, np.ndarray]:
        ok = np.isfinite(pos[f, :, 0])
        return pos[f][ok], np.flatnonzero(ok)

    def window(end: int) -> list[tuple[float, np.ndarray, np.ndarray]]:
        return [(f / RATE, *frame(f)) for f in range(end - W, end)]

    def steady(lab: Labeler, start: int, n: int) -> list[float]:
        ms = []
        for f in range(start, start + n):
            pts, _ = frame(f)
            t0 = time.perf_counter()
            lab.process(pts, f / RATE)
            ms.append((time.perf_counter() - t0) * 1e3)
        return ms

    first = W
    labels9 = np.flatnonzero(~np.char.startswith(np.array(names), f"{subjects[-1]}:"))
    rebuild, add, drop, frames_inactive, frames_only9 = [], [], [], [], []
    for r in range(args.repeats + 1):  # the first round compiles
        end = first + 40 * r + 60
        # the labeler of the new API: nine active, the tenth built inactive
        inc = Labeler.from_model(model, RATE, subjects=subjects[:-1])
        win9 = [(t, p, np.where(np.isin(lab, labels9), lab, -1)) for t, p, lab in window(first)]
        for t, p, lab in win9:
            inc.process(p, t, lab)
        fi = steady(inc, first, end - first)
        only9 = Labeler.from_model(nine, RATE)
        g9 = {n: i for i, n in enumerate(nine.marker_names)}
        for t, p, lab in win9:
            ok = lab >= 0
            l9 = np.full(lab.shape, -1)
            l9[ok] = [g9[names[i]] for i in lab[ok]]
            only9.process(p, t, l9)
        f9 = steady(only9, first, end - first)
        t0 = time.perf_counter()
        inc.add_subjects([subjects[-1]], window(end))
        a = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        inc.drop_subject(subjects[-1])
        d = (time.perf_counter() - t0) * 1e3
        # the old install: a new labeler of the ten from the window
        t0 = time.perf_counter()
        old = Labeler.from_model(model, RATE)
        for t, p, lab in window(end):
            old.process(p, t, lab)
        pts, _ = frame(end)
        old.process(pts, end / RATE)
        b = (time.perf_counter() - t0) * 1e3 - float(np.median(fi[W:]))
        if r:
            rebuild.append(b)
            add.append(a)
            drop.append(d)
            frames_inactive += fi[W:]
            frames_only9 += f9[W:]
    emit(
        {
            "subjects": len(subjects),
            "rate": RATE,
            "window_frames": W,
            "repeats": args.repeats,
            "rebuild_ms_median": float(np.median(rebuild)),
            "add_ms_median": float(np.median(add)),
            "drop_ms_median": float(np.median(drop)),
            "frame_ms_p50_inactive": float(np.median(frames_inactive)),
            "frame_ms_p50_only9": float(np.median(frames_only9)),
        },
        args.out,
    )


if __name__ == "__main__":
    main()
