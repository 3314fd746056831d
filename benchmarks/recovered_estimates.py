"""How far the hidden markers' published estimates lie from the real points, on a real take.

The take is labeled from its first ``--init-frames`` labeled frames (the labeler trained in
place, as ``label`` does) with points shuffled; every frame after them, every marker the
labeler reports recovered while the take has its point (the labeler lost that point: its
estimate is all a user gets) is compared with that point. ``--min-neighbours`` sets
``LabelerConfig.recovered_min_neighbours`` (1: every estimate published, as before
2026-12-04; 3: the default).

    .venv/bin/python benchmarks/recovered_estimates.py --min-neighbours 1 3
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import emit, real_args


def run(take: str, init: int, min_neighbours: int, far_mm: float) -> dict:
    from labeler_service.capture.io import read_segment
    from labeler_service.labeling.config import LabelerConfig
    from labeler_service.labeling.frame import MarkerState
    from labeler_service.labeling.registry import make_labeler

    cap = read_segment(take)
    pos = np.asarray(cap.positions, dtype=np.float64)
    names = list(cap.labels)
    config = LabelerConfig(recovered_min_neighbours=min_neighbours)
    lab = make_labeler("online", rate=cap.rate, marker_names=names, config=config)
    index = {n: i for i, n in enumerate(lab.marker_names)}
    col = np.array([names.index(n) for n in lab.marker_names])
    rng = np.random.default_rng(0)
    errs: list[float] = []
    recovered = 0
    for f in range(cap.n_frames):
        vis = np.flatnonzero(np.isfinite(pos[f, :, 0]))
        vis = vis[rng.permutation(vis.size)]
        truth = np.array([index[names[i]] for i in vis], dtype=np.int64)
        out = lab.process(pos[f, vis], f / cap.rate, truth if f < init else None)
        if f < init:
            continue
        rec = np.flatnonzero(out.state == MarkerState.RECOVERED)
        recovered += rec.size
        real = pos[f, col[rec]]
        seen = np.isfinite(real[:, 0])
        errs += np.linalg.norm(out.positions[rec[seen]] - real[seen], axis=1).tolist()
    e = np.asarray(errs)
    return {
        "take": take,
        "min_neighbours": min_neighbours,
        "recovered": recovered,
        "where_the_take_has_the_point": int(e.size),
        f"farther_than_{far_mm:g}_mm": int((e > far_mm).sum()),
        "error_mm_p50_max": [round(float(np.median(e)), 1), round(float(e.max()), 1)]
        if e.size
        else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--take", default="tennis_serve_pig_39markers_50hz.c3d:0:400")
    ap.add_argument("--init-frames", type=int, default=50)
    ap.add_argument("--min-neighbours", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--far-mm", type=float, default=100.0)
    a, root = real_args(ap)
    if root is None:
        return
    t0 = time.perf_counter()
    take = str(root / a.take)
    rows = [run(take, a.init_frames, k, a.far_mm) for k in a.min_neighbours]
    emit({"runs": rows, "wall_s": round(time.perf_counter() - t0, 1)}, a.out)


if __name__ == "__main__":
    main()
