"""The ``train shoulder`` run: load, fit k = 3..6, evaluate, write files and the report."""

from __future__ import annotations

import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from labeler_service.capture import Capture
from labeler_service.capture.io import read_segment
from labeler_service.errors import CaptureFormatError, ModelError
from offline.shoulder.evaluation import (
    Truth,
    acceptance,
    adjusted_rand_index,
    joint_errors,
    read_truth,
)
from offline.shoulder.model import MG03Baseline, ShoulderSkeleton, prepare_surface
from offline.shoulder.report import (
    error_table,
    mg03_table,
    plot_error_vs_k,
    plot_segmentation,
    skeleton_dict,
    write_json,
)
from offline.shoulder.triangles import read_faces, write_faces


@dataclass
class TrainConfig:
    train: Path
    out: Path
    tests: list[tuple[str, Path]] = field(default_factory=list)
    ks: tuple[int, ...] = (3, 4, 5, 6)
    restarts: int = 1000
    seed: int = 0
    faces: Path | None = None
    truth: Path | None = None
    subject: str | None = None
    up: str = "z"
    max_strain: float = 2.0
    structure: str = "auto"
    plots: bool = True
    argv: str = ""
    progress: bool | None = None  # None: when stderr is a terminal


def load_training(path: Path, subject: str | None, up: str) -> tuple[Capture, list[str]]:
    """The training capture (``FILE[:start[:stop]]``, frames) restricted to one subject; notes
    say what was excluded."""
    cap = read_segment(path, up=up)
    notes = list(cap.notes)
    subjects = cap.subjects
    if not subjects:
        raise CaptureFormatError(f"{path}: no labeled markers")
    if subject is None:
        subject = max(subjects, key=lambda s: (cap.subject_columns(s).size, s))
    elif subject not in subjects:
        raise CaptureFormatError(
            f"{path}: no subject {subject!r} (subjects: {', '.join(subjects)})"
        )
    others = [s for s in subjects if s != subject]
    ghosts = int(cap.ghost_mask.sum())
    sel = cap.select(cap.subject_columns(subject))
    if others:
        notes.append(f"excluded subjects: {', '.join(others)}")
    if ghosts:
        notes.append(f"excluded {ghosts} unlabeled tracks")
    sel = sel.without_empty()
    notes += [n for n in sel.notes if n not in notes]
    if sel.n_markers < 6:
        raise CaptureFormatError(f"{path}: subject {subject!r} has only {sel.n_markers} markers")
    return sel, notes


def load_test(path: Path, labels: tuple[str, ...], up: str) -> tuple[np.ndarray, list[str]]:
    """Positions ``(F, M, 3)`` of a test capture (``FILE[:start[:stop]]``) in the training
    marker order."""
    cap = read_segment(path, up=up)
    index = {x: i for i, x in enumerate(cap.labels)}
    pos = np.full((cap.n_frames, len(labels), 3), np.nan)
    missing = []
    for j, label in enumerate(labels):
        if label in index:
            pos[:, j] = cap.positions[:, index[label]]
        else:
            missing.append(label)
    if len(missing) == len(labels):
        raise CaptureFormatError(f"{path}: none of the training markers are in this capture")
    if not np.isfinite(pos[..., 0]).any():
        raise CaptureFormatError(
            f"{path}: no training marker is visible in any of its {cap.n_frames} frames: "
            "nothing to measure the synthesis error on"
        )
    notes = [f"{len(missing)} training markers absent: counted as missing"] if missing else []
    return pos, notes


def _progress(enabled: bool | None):  # -> rich.progress.Progress (a context manager)
    """rich progress bars on stderr (shown only when stderr is a terminal unless forced)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    enabled = sys.stderr.isatty() if enabled is None else enabled
    return Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        disable=not enabled,
    )


def _output_folder(out: Path) -> None:
    """Creates ``out`` (a folder) or says why it cannot be one."""
    if out.exists() and not out.is_dir():
        raise ModelError(f"--out {out}: exists and is not a folder (the study writes files in it)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ModelError(f"--out {out}: cannot create the folder: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK):
        raise ModelError(f"--out {out}: the folder is not writable")


#: Files a run writes in its folder: ``<k>`` and the test plots vary with ``--k``, ``--test``
#: and ``--no-plots``; those of an earlier run that this one does not write are removed
#: (:func:`_remove_stale`), so a reader never takes ``skeleton_k6.json`` of another run for
#: this one's. ``faces.txt``, ``results.json`` and ``report.md`` are written every run.
OWNED = re.compile(
    r"^(?:skeleton_k\d+\.json|segments_k\d+\.png|error_train\.png|error_test_(?:full|reduced)\.png)$"
)


def _remove_stale(out: Path, written: set[str]) -> list[str]:
    """Removes the files of :data:`OWNED` in ``out`` that this run did not write; returns their
    names. Nothing else in the folder is touched."""
    stale = sorted(p.name for p in out.iterdir() if OWNED.match(p.name) and p.name not in written)
    for name in stale:
        (out / name).unlink(missing_ok=True)
    return stale


def train(cfg: TrainConfig) -> dict:
    """Runs the study; returns the JSON summary (also in ``results.json``)."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    _output_folder(cfg.out)  # before the input is read: a bad --out fails at once
    cap, notes = load_training(cfg.train, cfg.subject, cfg.up)
    labels = cap.labels
    pos = cap.positions.astype(np.float64)
    motions: dict[str, np.ndarray] = {cfg.train.stem: pos}
    for name, path in cfg.tests:
        if name in motions:
            raise ModelError(f"test name {name!r} clashes with the training motion")
        motions[name], n = load_test(path, labels, cfg.up)
        notes += [f"{name}: {x}" for x in n]
    truth: Truth | None = read_truth(cfg.truth).aligned(labels) if cfg.truth else None
    for name, true_joints in (truth.joints if truth is not None else {}).items():
        if name in motions and true_joints.shape[0] != motions[name].shape[0]:
            raise ModelError(
                f"{cfg.truth}: its {name!r} joints cover {true_joints.shape[0]} frames, the "
                f"capture {motions[name].shape[0]}: give the truth file of the "
                "simulate-shoulder run that wrote the captures"
            )
    if any(k < 2 for k in cfg.ks):
        raise ModelError(f"every k must be >= 2, got {list(cfg.ks)}")
    most = pos.shape[1] // 3  # a segment's pose needs 3 markers (k = 216 of 215 ran for minutes)
    if max(cfg.ks) > most:
        raise ModelError(
            f"every k must be <= {most} (3 markers per segment, {pos.shape[1]} markers), got "
            f"{list(cfg.ks)}"
        )
    if cfg.restarts < 1:
        raise ModelError(f"--restarts must be >= 1, got {cfg.restarts}")
    out = cfg.out
    timings["load_s"] = time.perf_counter() - t_start

    t = time.perf_counter()
    faces = read_faces(cfg.faces, labels) if cfg.faces else None
    surface = prepare_surface(pos, faces=faces, max_strain=cfg.max_strain)
    if max(cfg.ks) > len(surface.faces):
        raise ModelError(
            f"every k must be <= {len(surface.faces)}, the near-rigid triangles segmented, got "
            f"{list(cfg.ks)}"
        )
    write_faces(out / "faces.txt", surface.faces, labels)
    timings["surface_s"] = time.perf_counter() - t

    models: dict[int, ShoulderSkeleton] = {}
    errors: dict[str, dict[str, dict[str, dict]]] = {
        m: {"full": {}, "reduced": {}} for m in motions
    }
    joints: dict[str, dict] = {}
    seg_info: dict[str, dict] = {}
    k3_poses: dict[str, dict] = {}  # motion -> marker set -> k=3 pose, reused by MG03
    rng = np.random.default_rng(cfg.seed)
    with _progress(cfg.progress) as bar:
        for k in cfg.ks:
            task = bar.add_task(f"k={k} k-means", total=cfg.restarts)
            t = time.perf_counter()
            model = ShoulderSkeleton(
                n_segments=k,
                n_restarts=cfg.restarts,
                structure=cfg.structure,
                random_state=np.random.default_rng(rng.integers(2**63)),
            ).fit(pos, surface, progress=lambda n, task=task: bar.update(task, completed=n))  # type: ignore[misc]
            timings[f"fit_k{k}_s"] = time.perf_counter() - t
            models[k] = model
            t = time.perf_counter()
            ev = bar.add_task(f"k={k} synthesis", total=len(motions))
            for name, p in motions.items():
                poses = {mset: model.pose(p, mset) for mset in ("full", "reduced")}
                for mset, (R, tt) in poses.items():
                    errors[name][mset][str(k)] = model.score_pose(p, R, tt).as_dict()
                if k == 3:
                    k3_poses[name] = poses
                if truth is not None:
                    R, tt = poses["full"]
                    je = joint_errors(
                        truth, model.labels_, model.parent_, model.joint_trajectories(R, tt), name
                    )
                    if je:
                        joints.setdefault(str(k), {})[name] = je
                bar.advance(ev)
            timings[f"evaluate_k{k}_s"] = time.perf_counter() - t
            seg_info[str(k)] = {
                "n_segments": model.n_segments_,
                "merged": model.merged_,
                "structure": "chain" if model.is_chain_ else "tree",
                "order": model.chain_,
                "parent": model.parent_.tolist(),
                "joint_rms_mm": [None if not np.isfinite(x) else round(float(x), 2)
                                 for x in model.joint_rms_],
                "inertia": model.inertia_,
                "segments": [[labels[i] for i in np.flatnonzero(model.labels_ == s)]
                             for s in range(model.n_segments_)],
                "reduced": [[labels[i] for i in r] for r in model.reduced_],
            }  # fmt: skip
            if truth is not None:
                seg_info[str(k)]["ari_vs_truth"] = adjusted_rand_index(truth.segment, model.labels_)
            write_json(out / f"skeleton_k{k}.json", skeleton_dict(model, labels))

    mg03: dict[str, dict] = {}
    if 3 in models and models[3].n_segments_ >= 2:
        t = time.perf_counter()
        base = MG03Baseline(models[3]).fit(pos, k3_poses[cfg.train.stem]["full"])
        for name, p in motions.items():
            mg03[name] = {
                s: base.score(p, s, k3_poses[name][s]).as_dict() for s in ("reduced", "full")
            }
        timings["mg03_s"] = time.perf_counter() - t
    checks = acceptance(errors, mg03)

    plots: list[str] = []
    if cfg.plots:
        t = time.perf_counter()
        train_name = cfg.train.stem
        test_names = [n for n in motions if n != train_name]
        train_plot = plot_error_vs_k(
            out / "error_train.png", errors, [train_name], None, "Training set (Fig. 5 analogue)"
        )
        plots.append(train_plot.name)
        if test_names:
            for mset, fig in (("full", 6), ("reduced", 7)):
                test_plot = plot_error_vs_k(
                    out / f"error_test_{mset}.png", errors, test_names, mset,
                    f"Test motions, {mset} set (Fig. {fig} analogue)",
                )  # fmt: skip
                plots.append(test_plot.name)
        for k, model in models.items():
            title = f"k={k}: segments, reduced markers (o), joints (x)"
            plots.append(plot_segmentation(out / f"segments_k{k}.png", model, title).name)
        timings["plots_s"] = time.perf_counter() - t
    written = {f"skeleton_k{k}.json" for k in cfg.ks} | set(plots)
    stale = _remove_stale(out, written)
    if stale:
        msg = (
            f"removed {', '.join(stale)}: an earlier run's files in {out} that this run "
            f"(k = {', '.join(map(str, cfg.ks))}{', no plots' if not cfg.plots else ''}) "
            "does not write"
        )
        notes.append(msg)
        print(f"note: {msg}", file=sys.stderr)
    timings["total_s"] = time.perf_counter() - t_start

    results = {
        "train": str(cfg.train),
        "tests": {n: str(p) for n, p in cfg.tests},
        "markers": len(labels),
        "frames": {n: int(p.shape[0]) for n, p in motions.items()},
        "rate_hz": cap.rate,
        "missing_fraction": round(float(np.isnan(pos[..., 0]).mean()), 4),
        "faces": int(len(surface.faces)),
        "clustered_faces": int(len(surface.kept)),
        "rest_frame": surface.rest_frame,
        "ks": list(cfg.ks),
        "restarts": cfg.restarts,
        "seed": cfg.seed,
        "errors": errors,
        "mg03": mg03,
        "segmentation": seg_info,
        "joints_vs_truth": joints,
        "acceptance": checks,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "notes": notes,
    }
    write_json(out / "results.json", results)
    write_report(out / "report.md", cfg, results, plots, labels)
    return {
        "out": str(out),
        "report": str(out / "report.md"),
        "markers": len(labels),
        "ks": list(cfg.ks),
        "avg_error_mm": {
            n: {s: {k: round(v["avg"], 3) for k, v in d.items()} for s, d in e.items()}
            for n, e in errors.items()
        },
        "acceptance_passed": sum(bool(v["pass"]) for v in checks.values()),
        "acceptance_total": len(checks),
        "total_s": round(timings["total_s"], 2),
    }


def write_report(path: Path, cfg: TrainConfig, r: dict, plots: list[str], labels: tuple) -> None:
    """The Markdown report tying tables, plots and checks together."""
    ks = r["ks"]
    L: list[str] = ["# Data-driven shoulder skeleton (Hong, Park and Hodgins 2009)", ""]
    if cfg.argv:
        L += ["Command:", "", f"    {cfg.argv}", ""]
    frames = ", ".join(f"{n} {f}" for n, f in r["frames"].items())
    L += [
        f"- training capture: `{r['train']}` ({r['markers']} markers, {r['rate_hz']:g} Hz, "
        f"{100 * r['missing_fraction']:.2f} % samples missing); frames: {frames}",
        f"- marker surface: {r['faces']} triangles "
        f"({'from ' + str(cfg.faces) if cfg.faces else 'automatic, Delaunay + kNN + sliver filter'}"
        f"), {r['clustered_faces']} clustered (near-rigid: edge strain <= {cfg.max_strain}, "
        "no fold, complete in >= 80 % of frames)",
        f"- k-means: k = {', '.join(map(str, ks))}, {r['restarts']} random restarts each, "
        f"seed {r['seed']}; rest pose = frame {r['rest_frame']}",
    ]
    L += [f"- note: {n}" for n in r["notes"]]
    L += ["", "## Segmentation", ""]
    L += ["| k | segments | merged | structure | markers per segment | joint fit RMS (mm) |"]
    L += ["|---|---|---|---|---|---|"]
    for k in ks:
        s = r["segmentation"][str(k)]
        counts = ", ".join(str(len(x)) for x in s["segments"])
        rms = ", ".join("-" if x is None else f"{x:.1f}" for x in s["joint_rms_mm"])
        L.append(f"| {k} | {s['n_segments']} | {s['merged']} | {s['structure']} "
                 f"({'>'.join(map(str, s['order']))}) | {counts} | {rms} |")  # fmt: skip
    if any("ari_vs_truth" in r["segmentation"][str(k)] for k in ks):
        ari = ", ".join(f"k={k}: {r['segmentation'][str(k)]['ari_vs_truth']:.3f}" for k in ks)
        L += ["", f"Agreement with the true segments (adjusted Rand index): {ari}."]
    if len(labels) <= 80:  # name the markers of each segment (real, sparse marker sets)
        L += ["", "Which markers group together:", ""]
        for k in ks:
            s = r["segmentation"][str(k)]
            L.append(f"- **k={k}**")
            for i, seg in enumerate(s["segments"]):
                names = ", ".join(x.split(":", 1)[-1] for x in seg)
                red = ", ".join(x.split(":", 1)[-1] for x in s["reduced"][i])
                L.append(f"  - S{i} ({len(seg)}): {names} — reduced: {red}")
    L += ["", "## Synthesis error (Table 2 analogue, mm)", ""]
    L += ["Linear-blend skinning of the whole marker surface from joint angles estimated with "
          "the full marker set (each segment's rigid core) or the reduced set (4 per segment); "
          "error over every visible sample.", ""]  # fmt: skip
    L += error_table(r["errors"], ks)
    for p in plots:
        if p.startswith("error_"):
            L += ["", f"![{p}]({p})"]
    if r["mg03"]:
        L += ["", "## Against MG03 (Table 3 analogue, mm)", ""]
        L += ["MG03: our k=3 skeleton plus an extra shoulder bone taking half the shoulder "
              "rotation, weights fitted by NNLS on the training motion.", ""]  # fmt: skip
        L += mg03_table(r["errors"], r["mg03"])
    if r["joints_vs_truth"]:
        L += ["", "## Joint centres against ground truth (mm, full-set pose)", ""]
        L += ["| k | motion | joint: mean / p95 |"]
        L += ["|---|---|---|"]
        for k, by_motion in r["joints_vs_truth"].items():
            for motion, js in by_motion.items():
                cells = "; ".join(
                    f"{n}: {v['mean_mm']:.1f} / {v['p95_mm']:.1f}{'' if v['matched'] else ' (?)'}"
                    for n, v in js.items()
                )
                L.append(f"| {k} | {motion} | {cells} |")
        L += [
            "",
            "(?) = no estimated joint joins the matching pair of true segments; the nearest "
            "estimated joint is reported.",
        ]
    if r["acceptance"]:
        L += [
            "",
            "## Acceptance checks",
            "",
            "The rules of the synthetic study (issue #5); on real data they are informative only.",
            "",
            "| rule | value | limit | pass |",
            "|---|---|---|---|",
        ]
        for name, v in r["acceptance"].items():
            L.append(
                f"| {name} | {v['value']:.3f} | {v['limit']} | {'yes' if v['pass'] else 'NO'} |"
            )
    for p in plots:
        if p.startswith("segments_"):
            L += ["", f"![{p}]({p})"]
    L += ["", "## Timings (s)", ""]
    L += [", ".join(f"{k} {v:.2f}" for k, v in r["timings_s"].items())]
    L += [
        "",
        "Files: `results.json` (all numbers), `skeleton_k<k>.json` (skeleton, joints, reduced "
        "markers, skin weights; format in docs/shoulder.md), `faces.txt` (surface).",
        "",
    ]
    path.write_text("\n".join(L), encoding="utf-8")
