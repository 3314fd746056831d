"""``mocap-labeler evaluate TRUTH``: score labelers on a labeled capture (DESIGN.md contract).

With ``--json`` the last line of stdout is one JSON object. ``--plot FILE.png`` also runs
down-sampling factors 1, 2 and 4 and draws accuracy against the factor per method (seed 003
Fig. 6 analogue), and writes ``FILE_errors.png``: the per-marker error raster of the first
method at the requested setting.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from pathlib import Path

from labeler_service.capture import check_writable, join_label, read_segment, split_label
from labeler_service.cli.args import (
    check_init_window,
    init_frames,
    seed,
    without_absent_subjects,
)
from labeler_service.errors import CaptureError
from labeler_service.evaluation.plots import errors_path, plot_error_raster
from labeler_service.evaluation.scoring import check_init_frames, evaluate, resolve_methods
from labeler_service.labeling.registry import LABELED_STARTS
from labeler_service.labeling.templates import load_model
from labeler_service.wording import plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "truth",
        help="labeled capture (.c3d/.trc/.npz), TRUTH[:start[:stop]] (frames); *N columns "
        "are ghosts",
    )
    p.add_argument(
        "--method",
        nargs="+",
        default=None,
        metavar="NAME",
        help="labeler(s) to score: online, closest-point (comma or space separated; "
        "default: every available one)",
    )
    p.add_argument("--downsample", type=int, default=1, help="keep every N-th frame")
    p.add_argument(
        "--init-frames",
        type=int,
        default=None,
        help="labeled training frames (default 50; with --model default 0: boot from the "
        "model, no labels at all, as label does)",
    )
    p.add_argument(
        "--model",
        default=None,
        metavar="MODEL",
        help="subject model (train structure, subjects named as in TRUTH) to start from",
    )
    p.add_argument(
        "--leave", type=int, default=0, help="subjects that vanish once and return displaced"
    )
    p.add_argument(
        "--leave-seconds", type=float, default=1.0, help="how long each --leave subject is gone"
    )
    p.add_argument("--gaps", type=int, default=0, help="markers removed per subject per event")
    p.add_argument("--gap-frames", type=int, default=20, help="length of each gap (frames)")
    p.add_argument(
        "--occlude", type=int, default=0, help="body-part occlusions per subject (120 mm)"
    )
    p.add_argument("--occlude-frames", type=int, default=15, help="frames each part is hidden")
    p.add_argument("--ghosts", type=float, default=0.0, help="mean ghost points per frame")
    p.add_argument("--seed", type=seed, default=0, help="seed of every random choice")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the file")
    p.add_argument(
        "--labeled-start",
        choices=LABELED_STARTS,
        default="auto",
        help="with --init-frames N and no --model: 'model' trains subject templates on the "
        "init window and runs the online method through the model-based (booting) labeler "
        "from them (its extension re-finds lost markers; docs/algorithm.md); 'labeler' trains "
        "the labeler in place; 'auto' (default): 'model' where it applies (online method, "
        "--init-frames >= 3), else 'labeler'",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON (last line)")
    p.add_argument("--plot", type=Path, default=None, help="PNG: accuracy vs down-sampling")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _methods(arg: list[str] | None) -> list[str] | None:
    if not arg:
        return None
    return [m.strip() for a in arg for m in a.split(",") if m.strip()]


def run(args: argparse.Namespace) -> int:
    if args.plot is not None:  # before the run, not after it
        _check_plot_format(args.plot)
        check_writable(args.plot, suffixes=None)
        check_writable(errors_path(args.plot), suffixes=None)
    args.init_frames = init_frames(args.init_frames, args.model)
    cap = without_absent_subjects(read_segment(args.truth, up=args.up), args.truth)
    step = max(args.downsample, 1)
    check_init_window(cap, args.truth, args.init_frames, step, subjects=args.model is None)
    from labeler_service.evaluation.scoring import check_scored_frames

    check_scored_frames(cap.positions[::step], args.init_frames, args.truth)
    methods = _methods(args.method)
    # before the kernels compile (a minute on a cold cache), not after
    online = methods is None or "online" in methods
    check_init_frames(args.init_frames, args.model is not None, online=online)
    show = not args.no_progress and sys.stderr.isatty()
    # (the online method runs through a booting labeler, the window start's too: its kernels)
    _warm_up(cap.rate, boot=methods is None or "online" in methods)
    common = dict(
        methods=methods,
        init_frames=args.init_frames,
        gaps=args.gaps,
        gap_frames=args.gap_frames,
        ghosts=args.ghosts,
        occlude=args.occlude,
        occlude_frames=args.occlude_frames,
        seed=args.seed,
        show_progress=show,
        model=args.model,
        leave=args.leave,
        leave_seconds=args.leave_seconds,
        labeled_start=args.labeled_start,
    )
    report, scores = evaluate(cap, downsample=args.downsample, **common)
    # what was scored, as given: the file and its frame range, and the model file (the
    # report's settings.model is what the model was trained on)
    report["truth"] = str(args.truth)
    report["settings"]["model_file"] = None if args.model is None else str(args.model)
    for note in report["notes"]:
        print(f"note: {note}", file=sys.stderr)
    if args.plot is not None:
        curves: dict = {}
        for factor in (1, 2, 4):
            kept = -(-cap.n_frames // factor)  # frames left at this factor
            if factor == args.downsample:
                rep = report
            elif kept <= args.init_frames:
                # too short at this factor for the init window: the asked report still stands
                report["notes"].append(
                    f"plot: --downsample {factor} left out ({kept} frames, not more than the "
                    f"{args.init_frames}-frame init window)"
                )
                print(f"note: {report['notes'][-1]}", file=sys.stderr)
                continue
            else:
                rep = evaluate(cap, downsample=factor, **common)[0]
            for name, s in rep["methods"].items():
                curves.setdefault(name, []).append((factor, s["accuracy"]))
        try:
            plot_accuracy_vs_downsampling(curves, args.plot, title=Path(args.truth).name)
            report["plot"] = str(args.plot)
            raster = plot_error_raster(
                scores[report["method"]],
                errors_path(args.plot),
                rate=report["rate_hz"],
                init_frames=args.init_frames,
                title=f"{Path(args.truth).name} ({report['method']})",
            )
        except OSError as exc:
            raise CaptureError(f"{args.plot}: cannot write the plot: {exc}") from exc
        report["errors_plot"] = str(raster)
        print(f"wrote {args.plot} and {raster}", file=sys.stderr)  # (said nowhere before)
    if args.json:
        print(json.dumps(report))
    else:
        # (the model's markers in no body: a subject they keep from booting is told why)
        no_body = (
            set()
            if args.model is None
            else {join_label(t.name, m) for t in load_model(args.model).subjects for m in t.no_body}
        )
        _print_table(report, no_body)
    return 0


def _print_table(report: dict, no_body: set[str] | frozenset[str] = frozenset()) -> None:
    """The report for a reader: one row per measure, one column per method (so no header is
    cut at any terminal width), then the error anatomy, the boot of each subject by name (a
    subject that never booted with the markers that kept it under 95 %, ``no_body`` the labels
    its model cannot give) and who left and came back."""
    from rich.console import Console
    from rich.table import Table

    t = Table()
    cols = [
        "accuracy",
        "ghost_labeled_rate",
        "recovery_mean_mm",
        "recovery_mean_ratio",
        "ms_per_frame_p50",
        "ms_per_frame_p99",
    ]
    t.add_column("measure", no_wrap=True)
    for name in report["methods"]:
        t.add_column(name, justify="right", no_wrap=True)
    shares = {"accuracy", "ghost_labeled_rate"}  # (0.999968 read "1" at 4 digits)
    for c in cols:
        vals = [s.get(c) for s in report["methods"].values()]
        shown = [
            "-" if v is None else f"{100 * v:.3f} %" if c in shares else f"{v:.4g}" for v in vals
        ]
        t.add_row(c, *shown)
    console = Console()
    console.print(
        f"{plural(report['frames'], 'frame')}, {plural(report['subjects'], 'subject')}, "
        f"{plural(report['markers'], 'marker')} at {report['rate_hz']:g} Hz"
        + (
            "; online: labeled start through the init window's model"
            if (report.get("settings") or {}).get("labeled_start") == "model"
            else ""
        )
    )
    console.print(t)
    e = report["errors"]
    settings = report.get("settings") or {}
    init = settings.get("init_frames", 0)
    # (from a model the field counts markers the model lacks: the model, not the init frames,
    # is what the labeler learned)
    from_model = bool(settings.get("model_file"))
    learned = "the model lacks" if from_model else "unseen in the init window"
    hint = "" if from_model else "; a --model trained on frames that show them can label them"
    unseen = (
        f"; {report['unseen_at_init']} samples of markers {learned} (accuracy without them "
        f"{100 * report['accuracy_seen']:.3f} %{hint})"
        if init and report["unseen_at_init"]
        else ""
    )
    console.print(
        f"{report['method']}: {report['visible']} visible samples scored; errors: "
        f"{e['same_subject']} same-subject, {e['cross_subject']} cross-subject, "
        f"{e['unlabeled']} unlabeled; {plural(e['ghost_taken'], 'ghost point')} labeled{unseen}"
    )
    swap = report["max_swap"]
    if swap:
        console.print(
            f"longest swap: {plural(report['max_swap_frames'], 'frame')} ({swap['marker']}, frames "
            f"{swap['first_frame']}-{swap['last_frame']})"
        )

    def sec(x: float | None) -> str:
        return "never" if x is None else f"{x:.3f} s"

    boot_s = report.get("boot_s") or {}
    if boot_s:
        each = ", ".join(f"{name} {sec(v)}" for name, v in boot_s.items())
        never = [name for name, v in boot_s.items() if v is None]
        console.print(
            f"boot (seconds until >= 95 % of a subject's visible markers are right for 10 "
            f"frames): {each}; slowest {sec(report['boot_s_max'])}"
        )
        known = report.get("boot_s_known") or {}
        if known:
            console.print(
                f"counting only the markers the labeler can name (not those {learned}): "
                + ", ".join(f"{name} {sec(v)}" for name, v in known.items())
            )
        if never:
            console.print(
                f"never booted: {', '.join(never)} (its samples count in accuracy, not in "
                "accuracy after boot)"
            )
            other = _labeled_as_others(report["errors"])
            if other:
                console.print(f"  {other}")
            for name in never:
                stuck = _boot_blockers(report["worst_markers"], name, no_body)
                if stuck:
                    console.print(f"  {name} stayed under 95 % with {stuck}")
    n_ret = len(report["reid_s"])
    reid = f"re-identification p95 {sec(report['reid_s_p95'])} over {plural(n_ret, 'return')}"
    left = ", ".join(
        f"{d['subject']} (frames {d['first_frame']}-{d['back_frame']})"
        for d in report.get("departures") or []
    )
    after = report["accuracy_after_boot"]
    after_text = "- (no subject booted)" if after is None else f"{100.0 * after:.3f} %"
    console.print(
        f"accuracy after boot {after_text}; "
        f"{reid if n_ret else 'no returns'}{f' (left: {left})' if left else ''}; "
        f"{plural(report['absent_labeled'], 'point')} given labels of absent subjects; "
        f"{plural(report['identity_swaps'], 'identity swap')}"
    )
    worst = ", ".join(f"{w['marker']} {w['errors']}" for w in report["worst_markers"])
    if worst:
        console.print(f"worst markers: {worst}")


def _labeled_as_others(errors: dict) -> str:
    """For the summary of a run where a subject never booted: the samples that carried another
    subject's labels, when they are at least a tenth of the errors ("" otherwise). A subject
    booted onto another performer (one person's copy: the same template) read only "never
    booted", as if nothing had been labeled."""
    cross = int(errors.get("cross_subject", 0))
    total = cross + int(errors.get("same_subject", 0)) + int(errors.get("unlabeled", 0))
    if cross == 0 or 10 * cross < total:
        return ""
    return (
        f"{cross} samples carried another subject's labels: a subject was booted onto another "
        "performer's points (a model cannot tell two performers of one template apart)"
    )


def _boot_blockers(worst: list[dict], subject: str, no_body: set[str] | frozenset[str]) -> str:
    """The markers of ``subject`` among ``worst`` (the report's ``worst_markers``) wrong in at
    least half of the frames they were visible in, for the text summary ("" if none): one
    marker in 20 always wrong keeps a subject under the boot's 95 % for good."""
    parts = []
    for w in worst:
        who, marker = split_label(w["marker"])
        if (who or "") != subject or not 0 < w["visible"] <= 2 * w["errors"]:
            continue
        why = (
            " (in no body of the model: never labeled)"
            if w["marker"] in no_body
            else " (not learned at the start: never labeled)"
            if not w.get("seen_at_init", True)
            else ""
        )
        parts.append(f"{marker} wrong in {w['errors']} of its {w['visible']} visible frames{why}")
    return "; ".join(parts)


def _check_plot_format(path: Path) -> None:
    """A ``--plot`` suffix matplotlib cannot write is refused before the run (no suffix:
    PNG); it was matplotlib's ValueError traceback after the three evaluations."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    suffix = path.suffix.lower().lstrip(".")
    formats = Figure().canvas.get_supported_filetypes()
    if suffix and suffix not in formats:
        raise CaptureError(
            f"{path}: cannot write a plot as .{suffix} (use .png, or one of "
            f"{', '.join(sorted(formats))})"
        )


def plot_accuracy_vs_downsampling(
    curves: dict[str, list[tuple[int, float]]], out: Path, title: str = ""
) -> Path:
    """Accuracy (%) against down-sampling factor, one line per method (seed 003 Fig. 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=120)
    for name, pts in curves.items():
        xs = [p[0] for p in pts]
        ys = [100 * p[1] for p in pts]
        ax.plot(xs, ys, marker="o", label=name)
    ax.set_xscale("log", base=2)
    ax.set_xticks([1, 2, 4], labels=["1", "2", "4"])
    ax.set_xlabel("down-sampling factor")
    ax.set_ylabel("labels correct (%)")
    # the take's name on its own lines: a long name and frame range ran past the right edge
    lines = ["accuracy vs down-sampling", *textwrap.wrap(title, 48, break_on_hyphens=False)]
    ax.set_title("\n".join(lines), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


__all__ = ["add_arguments", "plot_accuracy_vs_downsampling", "resolve_methods", "run"]


def _warm_up(rate: float, boot: bool) -> None:
    """Compiles (or loads from numba's cache) the kernels before the run, saying so on stderr
    when that takes long: the first run after an install compiles for a minute or more, which
    ``--no-progress`` (or output to a file) left silent (as ``label`` says it,
    :func:`~labeler_service.cli.label.notice_if_slow`)."""
    from labeler_service.cli.label import notice_if_slow
    from labeler_service.labeling.booting import warmup_booting
    from labeler_service.labeling.config import LabelerConfig
    from labeler_service.labeling.labeler import Labeler

    with notice_if_slow(
        "compiling the labeling kernels (numba; the first run after an install takes a minute "
        "or more, later runs load them from the cache)..."
    ):
        if boot:
            warmup_booting(rate, LabelerConfig())
        else:
            Labeler(["w:a", "w:b", "w:c"], rate).warmup()
