"""A jump of the whole scene (``BootConfig.jump_fraction``; docs/algorithm.md, "A jump of the
whole scene"): how far normal frames are from one, and what the rule does at one.

``real``: every scene and cell of the cross-take matrix (``generalization.py``: composed as it
composes them, corrupted as ``evaluate`` corrupts each cell) run through the anonymous point
tracker alone; per cell the largest, over frames, of the smaller of the share of the last
frame's marker points whose tracks ended and the share of the frame's points on new tracks
(the rule's statistic, ``booting.jumped_subjects``, with every marker labeled right). The rule
fires at ``jump_fraction``. Also the plain labeler's watch (``booting.JumpWatch``) over the
same streams: the largest share of its sample that found no point, and the frames it fired.

``sim``: the simulated walk and hug at 120 Hz (model of the first half, stream of the second,
as the boot tests build them) with ``--skips`` frames lost after frame 60, ``t`` continuous,
labeled by the booting labeler with the rule off and on: accuracy and wrong labels from 40
frames after the jump, seconds from the jump until a frame is 95 % right again.

``service``: a service stream with a labeled start on the plain labeler (three hugging
performers, 30 labeled frames), the same frames lost after frame 300, the rule off and on:
markers published on wrong points from 40 frames after the jump.

    MOCAP_DATA_DIR=../shared/data/real .venv/bin/python benchmarks/scene_jump.py --json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from _common import emit
from rich.progress import track

from labeler_service.labeling.boot import PointTracker
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt

SIM_RATE = 120.0
SIM_JUMP = 60  # the frame after which frames are lost
SIM_SCORED_AFTER = 40  # frames after the jump before scoring starts


def switched_shares(
    points: list[np.ndarray], truth: list[np.ndarray], rate: float, config: BootConfig
) -> np.ndarray:
    """Per frame the rule's share: the smaller of the share of the previous frame's marker
    points (``truth`` >= 0, as a labeler that labels every marker right sees them) whose
    tracks ended and the share of this frame's points on new tracks (0 where fewer than
    ``jump_min_markers`` either way)."""
    tracker = PointTracker(rate, config)
    prev_ids = np.zeros(0, dtype=np.int64)
    prev_lab = np.zeros(0, dtype=bool)
    out = np.zeros(len(points))
    for k, (pts, tr) in enumerate(zip(points, truth, strict=True)):
        ids = tracker.update(pts, k / rate)
        if ids.size == 0 and prev_ids.size:  # (an empty frame held over keeps the tracks)
            continue
        gone = int(np.count_nonzero(prev_lab & ~np.isin(prev_ids, ids)))
        if prev_lab.any() and min(gone, tracker.born) >= config.jump_min_markers:
            out[k] = min(gone / np.count_nonzero(prev_lab), tracker.born / ids.size)
        prev_ids, prev_lab = ids, np.asarray(tr) >= 0
    return out


def watch_shares(stream, rate: float, config: BootConfig) -> tuple[np.ndarray, int]:
    """The plain labeler's watch (``booting.JumpWatch``) over a stream labeled right: per frame
    the smaller of its two shares (the sample's markers that found no point, this frame's points
    that continue no marker), and the frames it named a subject in."""
    from labeler_service.labeling.booting import JumpWatch

    names = stream.marker_names
    subjects = {
        n.split(":")[0]: k for k, n in enumerate(dict.fromkeys(n.split(":")[0] for n in names))
    }
    subject_of = np.array([subjects[n.split(":")[0]] for n in names], dtype=np.int64)
    watch = JumpWatch(rate, config, subject_of)
    # (a twin that always reaches the second share: its ``share`` is the smaller of the two)
    probe = JumpWatch(rate, config.model_copy(update={"jump_fraction": 1e-6}), subject_of)
    out = np.zeros(stream.n_frames)
    fired = 0
    for k in range(stream.n_frames):
        fired += int(watch.update(stream.points[k], k / rate, stream.truth[k]).size > 0)
        probe.update(stream.points[k], k / rate, stream.truth[k])
        out[k] = probe.share
    return out, fired


def real(seconds: float, max_frames: int) -> dict:
    sys.path.insert(0, str(Path(__file__).parent))
    from generalization import INIT_S, _cells, matrix

    config = BootConfig()
    cells = []
    scenes = matrix("all", quick=False)
    for scene in track(scenes, description="matrix scenes", transient=True):
        rate = scene.rate()
        cap = scene.compose(scene.frames(seconds, max_frames))
        chosen = {"alone": {}} if len(scene.takes) == 1 else _cells(rate)
        for cell, opts in chosen.items():
            step = opts.get("downsample", 1)
            init = max(1, round(INIT_S * rate / step))
            stream = corrupt(cap, CorruptionSpec(**opts, protect_frames=init, seed=scene.seed))
            share = switched_shares(stream.points, stream.truth, rate / step, config)
            watch, fired = watch_shares(stream, rate / step, config)
            cells.append({
                "scene": scene.name, "cell": cell, "rate_hz": rate / step,
                "frames": len(share), "max_share": round(float(share.max(initial=0.0)), 3),
                "frames_at_or_above": int(np.count_nonzero(share >= config.jump_fraction)),
                "watch_max_share": round(float(watch.max(initial=0.0)), 3),
                "watch_fired": fired,
            })  # fmt: skip
    worst = max(cells, key=lambda c: c["max_share"])
    worst_watch = max(cells, key=lambda c: c["watch_max_share"])
    return {
        "jump_fraction": config.jump_fraction,
        "cells": len(cells),
        "max_share": worst["max_share"],
        "max_share_cell": f"{worst['scene']} {worst['cell']} ({worst['rate_hz']:g} Hz)",
        "frames_at_or_above": sum(c["frames_at_or_above"] for c in cells),
        "watch_max_share": worst_watch["watch_max_share"],
        "watch_max_share_cell": f"{worst_watch['scene']} {worst_watch['cell']} "
        f"({worst_watch['rate_hz']:g} Hz)",
        "watch_fired": sum(c["watch_fired"] for c in cells),
        "watch_by_rate": {
            f"{r:g}": max(c["watch_max_share"] for c in cells if c["rate_hz"] == r)
            for r in sorted({c["rate_hz"] for c in cells})
        },
        "by_rate": {
            f"{r:g}": max(c["max_share"] for c in cells if c["rate_hz"] == r)
            for r in sorted({c["rate_hz"] for c in cells})
        },
        "per_cell": cells,
    }


def _sim_scene(kind: str):
    sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
    from labeling.walks import absent_walk, train

    from labeler_service.scenes.simulate import simulate_scene

    if kind == "walk":
        return absent_walk(SIM_RATE)
    cap = simulate_scene(3, 4.0, kind, seed=5, rate=SIM_RATE)
    half = cap.n_frames // 2
    return train(cap.frames(0, half)), cap.frames(half, cap.n_frames)


def sim_run(model, cap, skip: int, fraction: float) -> dict:
    from labeler_service.labeling.booting import BootingLabeler
    from labeler_service.testing.frames import ModelFrames

    frames = ModelFrames(cap, model.marker_names, seed=3)
    lab = BootingLabeler(model, SIM_RATE, boot=BootConfig(jump_fraction=fraction))
    right = wrong = visible = 0
    back = None
    for k in range(cap.n_frames - skip):
        pts, truth = frames.frame(k if k < SIM_JUMP else k + skip)
        pl = lab.process(pts, k / SIM_RATE).point_labels
        ok = int(np.count_nonzero((pl == truth) & (truth >= 0)))
        n_vis = int(np.count_nonzero(truth >= 0))
        if k > SIM_JUMP and back is None and ok >= 0.95 * n_vis:
            back = round((k - SIM_JUMP) / SIM_RATE, 4)
        if k >= SIM_JUMP + SIM_SCORED_AFTER:
            right += ok
            wrong += int(np.count_nonzero((pl >= 0) & (pl != truth)))
            visible += n_vis
    return {
        "accuracy_after": round(right / max(1, visible), 4),
        "wrong_after": wrong,
        "back_to_95_s": back,
        "jump_events": sum(1 for e in lab.events if e[1] == "jump"),
    }


def sim(skips: list[int]) -> list[dict]:
    rows = []
    for kind in ("walk", "hug"):
        model, cap = _sim_scene(kind)
        for skip in skips:
            row = {"scene": kind, "lost_s": round(skip / SIM_RATE, 4)}
            for name, fraction in (("off", 0.0), ("on", BootConfig().jump_fraction)):
                row[name] = sim_run(model, cap, skip, fraction)
            rows.append(row)
    return rows


def service_run(skip: int, fraction: float, init: int = 30, jump: int = 300) -> dict:
    """A service stream with a labeled start (``init`` labeled frames, the plain labeler
    trained in place; its recovery model is the one trained from them), three simulated
    hugging performers at 120 Hz, ``skip`` frames lost after frame ``jump`` with ``seq`` and
    ``t`` continuous: markers published on wrong points from 40 frames after the jump, at
    their true points, visible; recoveries, the worst markers."""
    from collections import Counter

    from labeler_service.labeling.frame import MarkerState
    from labeler_service.scenes.simulate import simulate_scene
    from labeler_service.service.continuity import ACCEPT
    from labeler_service.service.protocol import FrameMsg, decode
    from labeler_service.service.settings import load_settings
    from labeler_service.service.stream import StreamState

    cap = simulate_scene(3, 8.0, "hug", seed=7, rate=SIM_RATE)
    frames = corrupt(cap, CorruptionSpec(protect_frames=init, seed=11))
    settings = load_settings(
        labeler="online", metrics_port=None, queue_size=4096, warmup=False,
        streams=[{"name": "vol", "labeled_start": "auto"}],
        boot_config={"jump_fraction": fraction},
    )  # fmt: skip
    st = StreamState("vol", settings, settings.streams[0])
    names = frames.marker_names

    def msg(k: int, f: int, labeled: bool) -> FrameMsg:
        labels = (
            tuple(names[m] if m >= 0 else None for m in frames.truth[f].tolist())
            if labeled
            else None
        )
        return FrameMsg("vol", k, float(frames.times[k]), frames.points[f], labels)

    for f in range(init):
        st.buffer_init(msg(f, f, True))
    lab, rate, out, ns, h = st.train_staged(st.take_init(), msg(init, init, False))
    st.install_trained(lab, rate, msg(init, init, False), out, 0, ns, h)
    source = [*range(jump), *range(jump + skip, frames.n_frames)]
    index = {m: st.names.index(nm) for m, nm in enumerate(names)}
    wrong = right = visible = 0
    worst: Counter = Counter()
    for k in range(init + 1, len(source)):
        f = source[k]
        published = st.process(msg(k, f, False), 0, ACCEPT)
        assert published is not None
        st.update_health(published)
        if st.boot_due():
            req = st.boot_request()
            assert req is not None
            st.boot_done(req, StreamState.boot_job(req))
        if k < jump + SIM_SCORED_AFTER:
            continue
        out_f = decode(published.payload)
        at = {index[m]: frames.points[f][i] for i, m in enumerate(frames.truth[f]) if m >= 0}
        visible += len(at)
        for i in np.flatnonzero(out_f.state == MarkerState.OBSERVED):
            if i in at and np.allclose(out_f.positions[i], at[i], atol=1e-3):
                right += 1
            else:
                wrong += 1
                worst[st.names[i]] += 1
    return {
        "wrong_after": wrong, "right_after": round(right / max(1, visible), 4),
        "recoveries": st.recoveries, "worst_markers": worst.most_common(6),
    }  # fmt: skip


def service(skips: list[int]) -> list[dict]:
    rows = []
    for skip in skips:
        row: dict = {"lost_s": round(skip / SIM_RATE, 4)}
        for name, fraction in (("off", 0.0), ("on", BootConfig().jump_fraction)):
            row[name] = service_run(skip, fraction)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--parts", nargs="+", choices=("real", "sim", "service"), default=["real", "sim", "service"]
    )
    ap.add_argument("--skips", type=int, nargs="+", default=[8, 16, 30, 45, 60, 90])
    ap.add_argument("--seconds", type=float, default=8.0, help="longest matrix scene (s)")
    ap.add_argument("--max-frames", type=int, default=1200)
    ap.add_argument("--json", action="store_true", help="(the output is JSON either way)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out: dict = {}
    if "real" in a.parts:
        from labeler_service.testing.realdata import real_data_dir

        if real_data_dir() is None:
            out["real"] = {"skipped": "no real captures (set MOCAP_DATA_DIR)"}
        else:
            out["real"] = real(a.seconds, a.max_frames)
    if "sim" in a.parts:
        out["sim"] = sim(a.skips)
    if "service" in a.parts:
        out["service"] = service(a.skips)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
