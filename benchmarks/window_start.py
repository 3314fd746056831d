"""Cost of a service stream's labeled start through a window model (``labeled_start = "model"``).

What the stream's training job does on top of the plain start, off the event loop and inside
``train_budget_s``: train subject templates on the labeled init window
(``labeling.structure.window_model``: ``train structure``'s trainer) and build the booting
labeler from them with its boot kernels compiled (``make_window_labeler(...).warmup()``). For
comparison, ``plain_s``: the plain start's labeler trained in place on the same window (built,
fed the window's frames, then one unlabeled frame, which trains it). Simulated walks of
``--people`` performers at 120 Hz, a 0.4 s window (48 frames), ``--repeats`` runs each,
median and max. Wall times on a shared machine:
noisy, compare medians.

    .venv/bin/python benchmarks/window_start.py [--people 2 10] [--repeats 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import emit

from labeler_service.capture import Capture
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import make_window_labeler
from labeler_service.labeling.structure import window_model
from labeler_service.scenes.simulate import simulate_scene

RATE = 120.0
WINDOW = 48  # 0.4 s, the init window of the cross-take matrix


def _plain(window: Capture) -> None:
    lab = Labeler(window.labels, window.rate)
    idx = np.arange(window.n_markers, dtype=np.int32)
    for f in range(window.n_frames):
        seen = ~np.isnan(window.positions[f]).any(axis=1)
        lab.process(window.positions[f][seen], f / window.rate, idx[seen])
    lab.process(window.positions[-1][seen], window.n_frames / window.rate, None)  # trains it


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--people", type=int, nargs="+", default=[2, 10])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out")
    args = ap.parse_args()
    out: dict = {"rate_hz": RATE, "window_frames": WINDOW, "repeats": args.repeats, "cases": []}
    for n in args.people:
        cap = simulate_scene(n, 1.0, "walk", seed=7, rate=RATE)
        keep = np.flatnonzero(~cap.ghost_mask)  # the labeled markers (no ghost tracks)
        labels = tuple(cap.labels[i] for i in keep)
        window = Capture(cap.positions[:WINDOW, keep], labels, cap.rate)
        train, build, plain = [], [], []
        for _ in range(args.repeats):  # interleaved
            t0 = time.perf_counter()
            model = window_model(window)
            t1 = time.perf_counter()
            make_window_labeler(model, rate=RATE, window_frames=WINDOW).warmup()
            t2 = time.perf_counter()
            _plain(window)
            t3 = time.perf_counter()
            train.append(t1 - t0)
            build.append(t2 - t1)
            plain.append(t3 - t2)
        out["cases"].append(
            {
                "people": n,
                "markers": window.n_markers,
                "train_s_p50": round(float(np.median(train)), 3),
                "train_s_max": round(max(train), 3),
                "build_warmup_s_p50": round(float(np.median(build)), 3),
                "plain_s_p50": round(float(np.median(plain)), 3),
            }
        )
    emit(out, args.out)


if __name__ == "__main__":
    main()
