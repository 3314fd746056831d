"""The online labeler on a raw, unlabeled capture (prints one JSON object).

Default input: ``raw_unlabeled_kneel_to_run_240hz.c3d`` from the real-data directory: 75
unlabeled tracks (``*N``) that break and restart under new numbers. The tracks visible in the
first frame become the marker set (pseudo labels ``raw:T<col>``); during the first
``--init-frames`` frames each point is labeled by the track it comes from (a track that is not
in the marker set gives no label). Afterwards every frame's points are given anonymously.

Reported: how many markers stay labeled (per frame and in the last frame) and how often a
marker's label moves to another track: ``jumps_live`` when the track it left is still visible
in that frame (the label left a live track: a labeling error), ``jumps_after_end`` when the old
track had ended (the raw data restarted the same physical marker under a new number, or the
marker was re-acquired after an occlusion: the expected case).

    .venv/bin/python benchmarks/raw_unlabeled.py --out raw.json
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _common import emit

from labeler_service.capture import read_capture
from labeler_service.errors import MocapError
from labeler_service.evaluation.scoring import WARMUP_FRAMES
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.labeler import Labeler
from labeler_service.testing.realdata import real_file

DEFAULT = "raw_unlabeled_kneel_to_run_240hz.c3d"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture", nargs="?", help=f"raw capture (default: {DEFAULT} in real data)")
    p.add_argument("--init-frames", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="also write the JSON here")
    args = p.parse_args(argv)
    path = args.capture or real_file(DEFAULT)
    if path is None:
        print(f"error: {DEFAULT} not found (set MOCAP_DATA_DIR)", file=sys.stderr)
        return 2
    try:
        cap = read_capture(path)
    except MocapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    vis = cap.visible
    tracks = np.flatnonzero(vis[0])
    names = tuple(f"raw:T{c}" for c in tracks)
    col_to_marker = np.full(cap.n_markers, -1, dtype=np.int32)
    col_to_marker[tracks] = np.arange(tracks.size, dtype=np.int32)
    lab = Labeler(names, cap.rate)
    lab.warmup()
    rng = np.random.default_rng(args.seed)
    last_track = np.full(tracks.size, -1)
    labeled, times = [], []
    recovered = 0
    jumps_live = jumps_after_end = 0
    init = args.init_frames
    final_state = None
    for f in range(cap.n_frames):
        cols = np.flatnonzero(vis[f])
        cols = cols[rng.permutation(cols.size)]
        pts = cap.positions[f, cols]
        t0 = time.perf_counter_ns()
        out = lab.process(pts, f / cap.rate, col_to_marker[cols] if f < init else None)
        times.append((time.perf_counter_ns() - t0) / 1e6)
        for j in np.flatnonzero(out.point_labels >= 0):
            m = out.point_labels[j]
            src = cols[j]
            if f >= init and last_track[m] >= 0 and last_track[m] != src:
                if vis[f, last_track[m]]:
                    jumps_live += 1
                else:
                    jumps_after_end += 1
            last_track[m] = src
        if f >= init:
            labeled.append(out.n_observed)
            recovered += out.n_recovered
        final_state = out.state
    frames = cap.n_frames - init
    t = np.asarray(times[init + WARMUP_FRAMES :])
    result = {
        "capture": str(path),
        "frames": frames,
        "rate_hz": cap.rate,
        "tracks_in_file": cap.n_markers,
        "markers": len(names),
        "labeled_per_frame_mean": round(float(np.mean(labeled)), 3),
        "labeled_fraction_mean": round(float(np.mean(labeled)) / len(names), 4),
        "labeled_in_last_frame": int(np.count_nonzero(final_state == MarkerState.OBSERVED)),
        "visible_points_in_last_frame": int(vis[-1].sum()),
        "recovered_per_frame_mean": round(recovered / frames, 3),
        "jumps_live": jumps_live,
        "jumps_after_end": jumps_after_end,
        "jumps_live_per_1000_marker_frames": round(1000 * jumps_live / max(1, sum(labeled)), 3),
        "ms_per_frame_p50": round(float(np.median(t)), 4),
        "ms_per_frame_p99": round(float(np.percentile(t, 99)), 4),
    }
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
