"""Boot from a model with no labeled frame: boot time and accuracy after boot.

Every case streams a labeled scene to a :class:`~labeler_service.labeling.booting.BootingLabeler`
frame by frame (points shuffled, labels hidden, a seeded ``--hide`` fraction of each subject's
markers hidden for the whole stream, the scene's ghost points kept), with a model trained on
*other* frames of the same performers (``StructureTrainer``, like ``train structure``). The
model lists ``--absent`` extra subjects who are never in the stream.

Per subject (as ``evaluate``'s ``boot_s_max`` defines it): *present* from the first frame with
>= 60 % of its template markers visible; *booted* at the first frame that starts 10 frames in a
row with >= 95 % of its visible markers correctly labeled; ``boot_s`` the difference in stream
seconds (null when never booted). ``accuracy_after_boot``: correct / visible markers over each
subject's frames from its boot on. ``absent_labeled``: points given a label of a subject not in
the stream. ``accuracy_up_to_identity``: the same as ``accuracy_all`` once subjects are
matched one to one (whole-person identity swaps between same-template performers forgiven: the
two-player copy has two identical templates). Timing (``boot_ms_*``: wall time of one boot
attempt; ``ms_per_frame_*``) is noisy on a shared machine.

Cases: simulated scenes (``walk``/``hug``/``pile``, 3-10 performers, 60-240 Hz; model trained
on the first half, stream = second half), a leave-and-return case (one performer vanishes for
0.5 s and comes back 1 m away), and real-take composites (``compose_scene`` of CMU and Vicon
takes, model trained on a composite of other segments of the same takes; the two-player copy
for two subjects with one template).

``labeled_start_accuracy``: the same stream labeled from the same model and its first 12
frames' labels (``evaluate --model M --init-frames 12``: the booting labeler given them),
scored from frame 12 on.

    .venv/bin/python benchmarks/boot.py [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _common import emit
from scipy.optimize import linear_sum_assignment

from labeler_service.capture import Capture
from labeler_service.labeling.boot import BootConfig
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.compose import compose_scene
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.testing.realdata import real_file

PRESENT = 0.6
GOOD = 0.95
RUN = 10
REF_INIT = 12  # labeled frames of the labeled-window start compared with


def train(capture: Capture) -> LabelerModel:
    from offline.structure import StructureTrainer

    return StructureTrainer().fit([capture]).model_


def run_case(
    truth: Capture,
    model: LabelerModel,
    *,
    hide: float,
    seed: int,
    leave: tuple[str, int, int, float] | None = None,
    boot: BootConfig | None = None,
) -> dict:
    """Streams ``truth`` to a BootingLabeler built from ``model`` and scores it.

    ``leave = (subject, first, stop, shift_mm)``: the subject's markers vanish in frames
    ``first..stop-1`` and come back shifted by ``shift_mm`` along x."""
    rng = np.random.default_rng(seed)
    names = model.marker_names
    col = {lab: i for i, lab in enumerate(truth.labels)}
    in_scene = np.array([n in col for n in names])
    gidx = np.array([col.get(n, -1) for n in names])
    subj_of = np.array([n.split(":")[0] for n in names])
    subjects = [s.name for s in model.subjects]
    present_subjects = [s for s in subjects if np.any(in_scene[subj_of == s])]
    hidden = rng.random(len(names)) < hide
    ghosts = np.flatnonzero(truth.ghost_mask)
    pos = truth.positions.astype(np.float64).copy()
    if leave is not None:
        s, a, b, shift = leave
        cols = gidx[(subj_of == s) & in_scene]
        pos[a:b, cols] = np.nan
        pos[b:, cols, 0] += shift
    lab = BootingLabeler(model, truth.rate, boot=boot)
    # the labeled start on the same stream: the model plus the first frames' labels, as
    # ``evaluate --model M --init-frames N`` runs it (the booting labeler given those labels)
    ref = BootingLabeler(model, truth.rate, boot=boot)
    ref_ok = ref_vis = 0
    f_total = truth.n_frames
    ok = np.zeros((f_total, len(subjects)))
    vis = np.zeros((f_total, len(subjects)))
    absent_labeled = ghost_labeled = ghost_total = wrong = 0
    ms = []
    mk_name = np.array([n.split(":", 1)[1] for n in names])
    conf = np.zeros((len(subjects), len(subjects)))  # true subject x label subject, same marker
    sidx = {x: i for i, x in enumerate(subjects)}
    subj_i = np.array([sidx[x] for x in subj_of])
    for f in range(f_total):
        mk = np.where(in_scene[:, None], pos[f, np.maximum(gidx, 0)], np.nan)
        v = np.isfinite(mk[:, 0]) & ~hidden
        g = pos[f, ghosts]
        g = g[np.isfinite(g[:, 0])]
        pts = np.concatenate([mk[v], g]).astype(np.float32)
        tr = np.concatenate([np.flatnonzero(v), np.full(len(g), -1)])
        order = rng.permutation(len(pts))
        pts, tr = pts[order], tr[order]
        t0 = time.perf_counter()
        out = lab.process(pts, f / truth.rate)
        ms.append((time.perf_counter() - t0) * 1e3)
        pl = out.point_labels.astype(np.int64)
        m = tr >= 0
        rl = ref.process(pts, f / truth.rate, tr if f < REF_INIT else None).point_labels
        if f >= REF_INIT:
            ref_ok += int((rl[m] == tr[m]).sum())
            ref_vis += int(m.sum())
        ghost_total += int((~m).sum())
        ghost_labeled += int((pl[~m] >= 0).sum())
        wrong += int(((pl[m] >= 0) & (pl[m] != tr[m])).sum())
        same = m & (pl >= 0)
        same[same] = mk_name[pl[same]] == mk_name[tr[same]]
        np.add.at(conf, (subj_i[tr[same]], subj_i[pl[same]]), 1)
        lab_subj = np.where(pl >= 0, subj_of[np.maximum(pl, 0)], "")
        absent_labeled += int(sum(1 for x in lab_subj if x and x not in present_subjects))
        for k, s in enumerate(subjects):
            sel = m & (subj_of[np.maximum(tr, 0)] == s)
            vis[f, k] = sel.sum()
            ok[f, k] = (pl[sel] == tr[sel]).sum()
    n_tpl = np.array([np.sum(subj_of == s) for s in subjects])
    per = {}
    boot_s, acc_ok, acc_vis = [], 0.0, 0.0
    for k, s in enumerate(subjects):
        if s not in present_subjects:
            continue
        present = vis[:, k] >= PRESENT * n_tpl[k]
        good = (vis[:, k] > 0) & (ok[:, k] >= GOOD * vis[:, k])
        first = int(np.argmax(present)) if present.any() else None
        booted = None
        if first is not None:
            for f in range(first, f_total - RUN + 1):
                if good[f : f + RUN].all():
                    booted = f
                    break
        bs = None if booted is None or first is None else (booted - first) / truth.rate
        boot_s.append(bs)
        if booted is not None:
            acc_ok += ok[booted:, k].sum()
            acc_vis += vis[booted:, k].sum()
        per[s] = {"boot_s": bs}
    ms_a = np.array(ms[1:])
    return {
        "frames": f_total,
        "rate": truth.rate,
        "subjects": len(present_subjects),
        "model_subjects": len(subjects),
        "booted": int(sum(b is not None for b in boot_s)),
        "boot_s_max": None if any(b is None for b in boot_s) else max(boot_s, default=0.0),
        "boot_s_each": [None if b is None else round(b, 3) for b in boot_s],
        "accuracy_after_boot": round(acc_ok / acc_vis, 4) if acc_vis else None,
        "accuracy_all": round(ok.sum() / max(1, vis.sum()), 4),
        "accuracy_up_to_identity": round(
            float(conf[linear_sum_assignment(-conf)].sum()) / max(1, vis.sum()), 4
        ),
        "labeled_start_accuracy": round(ref_ok / max(1, ref_vis), 4),
        "wrong_rate": round(wrong / max(1, vis.sum()), 4),
        "absent_labeled": absent_labeled,
        "ghost_labeled_rate": round(ghost_labeled / max(1, ghost_total), 4),
        "boot_ms_p50": round(float(np.median(lab.boot_ms)), 1) if lab.boot_ms else None,
        "boot_ms_max": round(float(np.max(lab.boot_ms)), 1) if lab.boot_ms else None,
        "ms_per_frame_p50": round(float(np.median(ms_a)), 3),
        "ms_per_frame_p99": round(float(np.percentile(ms_a, 99)), 3),
        "events": [(round(t, 3), e, s) for t, e, s in lab.events[:40]],
    }


def sim_case(scenario: str, n: int, rate: float, absent: int, hide: float, seed: int) -> dict:
    """Scene of n + absent performers; the model sees all of them on the first half, the
    stream carries the first n on the second half."""
    absent = min(absent, 10 - n)  # the simulator makes at most 10 performers
    cap = simulate_scene(n + absent, 8.0, scenario, seed=seed, rate=rate, ghosts=2.0)
    half = cap.n_frames // 2
    model = train(cap.frames(0, half))
    keep = [
        i
        for i, lab in enumerate(cap.labels)
        if lab.startswith("*") or int(lab.split(":")[0][1:]) <= n
    ]
    stream = cap.select(keep).frames(half, cap.n_frames)
    return run_case(stream, model, hide=hide, seed=seed)


def leave_case(hide: float, seed: int) -> dict:
    cap = simulate_scene(4, 8.0, "walk", seed=seed, rate=120.0, ghosts=2.0)
    half = cap.n_frames // 2
    model = train(cap.frames(0, half))
    stream = cap.frames(half, cap.n_frames)
    return run_case(stream, model, hide=hide, seed=seed, leave=("P2", 120, 180, 1000.0))


def composite_case(
    takes: list[tuple[str, int, int]], rate: float, frames: int, seed: int, hide: float
) -> dict | None:
    """Model from a composite of the takes at their ``train`` start, stream from one at their
    ``test`` start (same takes, same names)."""
    paths = [real_file(name) for name, _, _ in takes]
    if any(p is None for p in paths):
        return None
    tr = [f"{p}:{a}" for p, (_, a, _) in zip(paths, takes, strict=True)]
    te = [f"{p}:{b}" for p, (_, _, b) in zip(paths, takes, strict=True)]
    model = train(compose_scene(tr, 600.0, frames, seed, rate=rate))
    stream = compose_scene(te, 600.0, frames, seed + 1, rate=rate)
    return run_case(stream, model, hide=hide, seed=seed)


def copy_case(hide: float, seed: int) -> dict | None:
    from labeler_service.capture import read_capture

    p = real_file("two_players_shifted_copy_50hz.c3d")
    if p is None:
        return None
    cap = read_capture(p)
    model = train(cap.frames(0, 250))
    return run_case(cap.frames(300, cap.n_frames), model, hide=hide, seed=seed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a few cases only")
    ap.add_argument("--hide", type=float, default=0.15, help="fraction of markers hidden")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    cases: dict[str, dict | None] = {}
    sims = [("walk", 3, 120.0), ("hug", 5, 120.0), ("pile", 5, 120.0), ("walk", 10, 120.0)]
    if not a.quick:
        sims += [("walk", 3, 60.0), ("walk", 3, 240.0), ("hug", 10, 120.0)]
    for scen, n, rate in sims:
        name = f"sim_{scen}_{n}_{rate:g}hz"
        print(name, file=sys.stderr)
        cases[name] = sim_case(scen, n, rate, 2, a.hide, a.seed)
    cases["sim_leave_4_120hz"] = leave_case(a.hide, a.seed)
    cases["real_cmu_cmu_kneel_120hz"] = composite_case(
        [
            ("cmu_01_01_playground.c3d", 0, 1200),
            ("cmu_02_05_expressions.c3d", 0, 900),
            ("kneel_to_prone_62markers_240hz.c3d", 840, 0),
        ],
        120.0,
        360,
        a.seed,
        a.hide,
    )
    cases["real_two_players_copy_50hz"] = copy_case(a.hide, a.seed)
    result = {"hide": a.hide, "seed": a.seed, "cases": cases}
    emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
