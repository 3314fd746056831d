"""A dropout: frames with no point at all in a real take, labeled from its first labeled
frames through the window model (``label``'s default start). Per dropout length,
``BootConfig.blackout_hold_s`` and ``blackout_reboot_s`` (``--reboot``): the frames after the
return until half and all of the take's visible markers are labeled right, the wrong labels
over the 40 frames after it, and the labeler's drop and boot events.

    MOCAP_DATA_DIR=../shared/data/real .venv/bin/python benchmarks/blackout.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import emit, real_args


def run(take: str, at: int, n_empty: int, hold: float, init: int, reboot: float) -> dict:
    from labeler_service.capture import Capture
    from labeler_service.capture.io import read_segment
    from labeler_service.labeling.boot_config import BootConfig
    from labeler_service.labeling.registry import make_window_labeler
    from labeler_service.labeling.structure import window_model

    cap = read_segment(take)
    pos = np.asarray(cap.positions, dtype=np.float64)
    names = list(cap.labels)
    win = window_model(Capture(cap.positions[:init], tuple(names), cap.rate))
    lab = make_window_labeler(win, rate=cap.rate, window_frames=init)
    update = {"blackout_hold_s": hold, "blackout_reboot_s": reboot}
    lab.boot_config = lab.boot_config.model_copy(update=update)
    assert isinstance(lab.boot_config, BootConfig)
    idx = {n: i for i, n in enumerate(lab.marker_names)}
    rng = np.random.default_rng(0)
    back = at + n_empty
    half = full = None
    wrong = 0
    for f in range(min(pos.shape[0], back + 200)):
        vis = np.flatnonzero(np.isfinite(pos[f, :, 0]))
        if at <= f < back:
            vis = vis[:0]
        vis = vis[rng.permutation(vis.size)]
        truth = np.array([idx[names[i]] for i in vis], dtype=np.int64)
        out = lab.process(pos[f, vis], f / cap.rate, truth if f < init else None)
        if f < back:
            continue
        pl = np.asarray(out.point_labels)
        right = int(np.count_nonzero(pl == truth))
        if f < back + 40:
            wrong += int(np.count_nonzero((pl >= 0) & (pl != truth)))
        if half is None and right >= 0.5 * vis.size:
            half = f - back
        if full is None and right == vis.size:
            full = f - back
    t0 = at / cap.rate
    return {
        "empty_frames": n_empty,
        "blackout_hold_s": hold,
        "blackout_reboot_s": reboot,
        "frames_to_half_right": half,
        "frames_to_all_right": full,
        "wrong_in_40_frames_after": wrong,
        "events": [(round(t - t0, 3), k) for t, k, _ in lab.events if t >= t0],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--take", default="tennis_serve_pig_39markers_50hz.c3d:0:400")
    ap.add_argument("--at", type=int, default=200, help="the first empty frame")
    ap.add_argument("--frames", type=int, nargs="+", default=[2, 5, 10, 25])
    ap.add_argument("--hold", type=float, nargs="+", default=[0.0, 0.5])
    ap.add_argument("--init-frames", type=int, default=50)
    ap.add_argument("--reboot", type=float, nargs="+", default=[0.25], help="blackout_reboot_s")
    a, root = real_args(ap)
    if root is None:
        return
    t0 = time.perf_counter()
    take = str(root / a.take)
    rows = [
        run(take, a.at, n, h, a.init_frames, r) for n in a.frames for h in a.hold for r in a.reboot
    ]
    emit({"take": a.take, "runs": rows, "wall_s": round(time.perf_counter() - t0, 1)}, a.out)


if __name__ == "__main__":
    main()
