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

With ``--boot`` no label is given at all: a model (``--model FILE``, or trained here on
``--train TAKE``, default the labeled 62-marker ``kneel_to_prone_62markers_240hz.c3d``: the same
marker set, another take) boots the subject from the anonymous points, as ``mocap-labeler label
RAW OUT --model M`` does. Reported on the raw tracks (a track is a run of consecutive frames of
one file column): the fraction of points in tracks longer than ``--long-s`` (0.5 s) that get a
label, and the label changes along a track per 1,000 track-frames: a track whose label goes
from A to B (unlabeled frames in between included) is an error unless A is on another point of
that frame (the raw data had joined two markers' trajectories). ``--plot FILE.png`` draws the
label of every long track over time.

    .venv/bin/python benchmarks/raw_unlabeled.py --boot --plot raw_boot.png --out raw_boot.json

The raw take has no ground truth; two runs can be compared on its tracks: ``--labels-out
FILE.npy`` keeps a run's labels (frame x file column, -1 unlabeled) and ``--against FILE.npy``
scores this run's labels against another's (:func:`track_agreement`: per track the other run's
most frequent label; a labeled sample on such a track agrees or not). An earlier boot is
checked against a later one this way: where they disagree on a track that runs from the
kneeling start into the run, at least one of them read it wrong.

    .venv/bin/python benchmarks/raw_unlabeled.py --boot --labels-out late.npy
    .venv/bin/python benchmarks/raw_unlabeled.py --boot --against late.npy  # another build
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _common import emit

from labeler_service.capture import Capture, read_capture
from labeler_service.errors import LabelerError, MocapError
from labeler_service.evaluation.scoring import WARMUP_FRAMES
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import make_labeler
from labeler_service.labeling.templates import LabelerModel, load_model
from labeler_service.testing.realdata import real_file

DEFAULT = "raw_unlabeled_kneel_to_run_240hz.c3d"
TRAIN = "kneel_to_prone_62markers_240hz.c3d"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture", nargs="?", help=f"raw capture (default: {DEFAULT} in real data)")
    p.add_argument("--init-frames", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument("--boot", action="store_true", help="no labels: boot from a subject model")
    p.add_argument("--model", help="with --boot: the model (train structure output)")
    p.add_argument("--train", help=f"with --boot and no --model: labeled take (default {TRAIN})")
    p.add_argument("--long-s", type=float, default=0.5, help="tracks at least this long count")
    p.add_argument("--plot", help="with --boot: PNG of every long track's label over time")
    p.add_argument("--labels-out", help="with --boot: save the labels (frames x columns, .npy)")
    p.add_argument("--against", help="with --boot: score the labels against another run's .npy")
    args = p.parse_args(argv)
    path = args.capture or real_file(DEFAULT)
    if path is None:
        print(f"error: {DEFAULT} not found (set MOCAP_DATA_DIR)", file=sys.stderr)
        return 2
    try:
        cap = read_capture(path)
        if args.boot:
            result = _boot(cap, str(path), args)
            emit(result, args.out)
            return 0
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


def _model(args: argparse.Namespace) -> LabelerModel:
    if args.model:
        return load_model(args.model)
    from offline.structure import StructureTrainer

    train = args.train or real_file(TRAIN)
    if train is None:
        raise LabelerError(f"{TRAIN} not found (set MOCAP_DATA_DIR, or give --model/--train)")
    return StructureTrainer().fit([read_capture(train)]).model_


def _runs(visible: np.ndarray) -> np.ndarray:
    """Track id of every (frame, column) sample, -1 where the column is empty: a track is a run
    of consecutive visible frames of one column."""
    starts = visible & ~np.vstack([np.zeros((1, visible.shape[1]), bool), visible[:-1]])
    ids = np.cumsum(starts.T.ravel()).reshape(visible.shape[1], -1).T - 1
    return np.where(visible, ids, -1)


def track_scores(
    label: np.ndarray, visible: np.ndarray, long_frames: float
) -> tuple[dict[str, object], np.ndarray, np.ndarray]:
    """Scores of the labels (``label[f, column]``, -1 unlabeled) on the raw tracks: the labeled
    fraction overall and in tracks of at least ``long_frames``, and the label changes along a
    track, an error unless the old label is on another point of that frame. Also returns the
    track ids (:func:`_runs`) and the long-track mask."""
    track = _runs(visible)
    n_tracks = int(track.max()) + 1
    length = np.bincount(track[visible], minlength=n_tracks)
    long = visible & (length[np.maximum(track, 0)] >= long_frames)
    changes = errors = 0
    for c in range(visible.shape[1]):
        last, last_track = -1, -1
        for f in np.flatnonzero(visible[:, c]):
            t, lb = track[f, c], label[f, c]
            if t != last_track:
                last, last_track = -1, t
            if lb < 0:
                continue
            if last >= 0 and lb != last:
                changes += 1
                errors += int(not np.any(label[f][visible[f]] == last))
            last = lb
    points = int(visible.sum())
    scores: dict[str, object] = {
        "tracks": n_tracks,
        "points": points,
        "points_in_long_tracks": int(long.sum()),
        "labeled_fraction": round(float((label[visible] >= 0).mean()), 4),
        "labeled_fraction_long_tracks": round(float((label[long] >= 0).mean()), 4),
        "label_changes": changes,
        "label_change_errors": errors,
        "label_change_errors_per_1000_track_frames": round(1000 * errors / max(1, points), 3),
        "distinct_labels_used": int(np.unique(label[visible & (label >= 0)]).size),
    }
    return scores, track, long


def track_agreement(
    label: np.ndarray, ref: np.ndarray, visible: np.ndarray, rate: float
) -> dict[str, object]:
    """``label`` against another run's labels ``ref`` (both ``[frame, column]``, -1
    unlabeled) on the raw tracks: per track the reference label is ``ref``'s most frequent
    label on it; each labeled sample of ``label`` on a track with a reference label agrees or
    disagrees (also counted before ``ref``'s first label: what an earlier boot adds), and the
    most frequent ``(reference, label)`` pairs of the disagreements (label indices)."""
    track = _runs(visible)
    n = int(track.max()) + 1
    on = visible & (ref >= 0)
    keys = track[on].astype(np.int64) * (int(ref.max()) + 1) + ref[on]
    counts = np.bincount(keys, minlength=n * (int(ref.max()) + 1)).reshape(n, -1)
    ref_label = np.where(counts.max(axis=1) > 0, counts.argmax(axis=1), -1)
    r = np.where(visible, ref_label[np.maximum(track, 0)], -1)
    both = visible & (label >= 0) & (r >= 0)
    bad = both & (label != r)
    ref_first = np.flatnonzero(on.any(axis=1))
    before = np.zeros(visible.shape[0], dtype=bool)
    before[: int(ref_first[0]) if ref_first.size else visible.shape[0]] = True
    pairs: dict[tuple[int, int], int] = {}
    for a, b in zip(r[bad].tolist(), label[bad].tolist(), strict=True):
        pairs[(a, b)] = pairs.get((a, b), 0) + 1
    worst = sorted(pairs.items(), key=lambda kv: -kv[1])[:10]
    return {
        "reference_first_label_s": round(float(ref_first[0]) / rate, 3) if ref_first.size else None,
        "samples_on_reference_tracks": int(both.sum()),
        "agree": int((both & ~bad).sum()),
        "disagree": int(bad.sum()),
        "disagree_before_reference_boot": int((bad & before[:, None]).sum()),
        "agree_before_reference_boot": int((both & ~bad & before[:, None]).sum()),
        "worst_pairs": [[a, b, c] for (a, b), c in worst],
    }


def _boot(cap: Capture, path: str, args: argparse.Namespace) -> dict[str, object]:
    """The raw take booted from a model with no label at all; scored on the raw tracks."""
    model = _model(args)
    lab = make_labeler("online", rate=cap.rate, model=model, boot=True)
    lab.warmup()
    vis = cap.visible
    label = np.full(vis.shape, -1, dtype=np.int32)  # label index per (frame, column)
    rng = np.random.default_rng(args.seed)
    times = []
    for f in range(cap.n_frames):
        cols = np.flatnonzero(vis[f])
        cols = cols[rng.permutation(cols.size)]
        t0 = time.perf_counter_ns()
        out = lab.process(cap.positions[f, cols], f / cap.rate, None)
        times.append((time.perf_counter_ns() - t0) / 1e6)
        label[f, cols] = out.point_labels
    scores, track, long = track_scores(label, vis, args.long_s * cap.rate)
    first = np.flatnonzero((label >= 0).any(axis=1))
    if args.labels_out:
        np.save(args.labels_out, label)
    if args.against:
        other = np.load(args.against)
        if other.shape != label.shape:
            raise LabelerError(f"{args.against}: labels {other.shape}, this take {label.shape}")
        agreement = track_agreement(label, other, vis, cap.rate)
        names = lab.marker_names
        agreement["worst_pairs"] = [[names[a], names[b], c] for a, b, c in agreement["worst_pairs"]]
        scores["against"] = {"file": args.against, **agreement}
    t = np.asarray(times[WARMUP_FRAMES:])
    if args.plot:
        _plot(args.plot, label, track, long, cap.rate, lab.marker_names)
    return {
        "capture": path,
        "mode": "boot",
        "model_subjects": [s.name for s in model.subjects],
        "model_markers": len(lab.marker_names),
        "frames": cap.n_frames,
        "rate_hz": cap.rate,
        "long_s": args.long_s,
        **scores,
        "first_label_s": round(float(first[0]) / cap.rate, 3) if first.size else None,
        "ms_per_frame_p50": round(float(np.median(t)), 4),
        "ms_per_frame_p99": round(float(np.percentile(t, 99)), 4),
    }


def _plot(
    out: str, label: np.ndarray, track: np.ndarray, long: np.ndarray, rate: float,
    names: tuple[str, ...],
) -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ids = np.unique(track[long])
    row = np.full(int(track.max()) + 1, -1)
    row[ids] = np.arange(ids.size)
    img = np.full((ids.size, label.shape[0]), np.nan)
    f, c = np.nonzero(long)
    img[row[track[f, c]], f] = np.where(label[f, c] >= 0, label[f, c], -1)
    fig, ax = plt.subplots(figsize=(12, 7))
    cmap = plt.get_cmap("nipy_spectral").with_extremes(under="black", bad="white")
    ax.imshow(
        img, aspect="auto", interpolation="nearest", cmap=cmap, vmin=0, vmax=max(1, len(names)),
        extent=(0, label.shape[0] / rate, ids.size, 0),
    )  # fmt: skip
    ax.set_xlabel("time (s)")
    ax.set_ylabel("raw track (long tracks only)")
    ax.set_title("label per raw track: colour = model marker, black = unlabeled, white = no point")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
