"""``mocap-labeler label IN OUT [--model MODEL]``: batch-label a capture with the online labeler.

The capture is replayed frame by frame through the same
:class:`~labeler_service.labeling.labeler.Labeler`
the service runs: every frame's visible points (labeled columns and unlabeled ``*N`` tracks
alike) are given anonymously, in a shuffled order.

- Without ``--model`` the first ``--init-frames`` frames carry the capture's own labels and are
  the training window (Yu, Li and Deng 2007); the marker set is the capture's labeled columns.
  By default (``--labeled-start auto``, as ``evaluate``) subject templates are trained on that
  window and the capture is labeled through the model-based labeler
  (:func:`~labeler_service.labeling.registry.make_window_labeler`); ``--labeled-start labeler``
  trains the labeler in place instead, as ``auto`` does for a capture with a label without
  ``subject:`` (the window model would rename it); either needs 3 or more init frames. The
  summary's ``labeled_start`` says which start ran, ``labeled_start_note`` why
  ``auto`` fell back.
- With ``--model`` the marker set is the model's and, by default (``--init-frames 0``), IN needs
  no labels at all: the labeler boots the model's subjects from the anonymous points
  (:class:`~labeler_service.labeling.booting.BootingLabeler`, ``make_labeler(..., boot=True)``),
  drops a subject that leaves and boots it again when it returns. ``--init-frames N`` >= 1
  instead labels the first N frames from IN's columns with the model's names: the subjects
  they label (3 or more points) start from those labels, through the same booting labeler,
  which boots the others when they are there and labels a marker the N frames never showed
  from its template when it appears.

OUT is in IN's axes (a take read with ``--up y`` is rotated back) and holds
one column per marker (observed and, unless ``--drop-recovered``, recovered
positions) plus the points that stayed unlabeled as ``*N`` columns: ``*N`` is the point's
column N of IN, so an unlabeled raw track stays one trajectory. A C3D OUT of a C3D IN keeps
everything of IN but its points (``write_capture(..., like=IN)``): analog channels (force
plates, EMG) and events of the same frames, every parameter group, the time base (first frame)
and the point units; any other C3D or TRC OUT keeps IN's time base (the number and time of its
first frame); the summary's ``kept_from_input`` says what was kept. Those outputs are in
millimetres and hold the points only. If the input carries labels
after the init window, the summary also says how often the labeler agreed with them.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from labeler_service.cli.args import (
    check_init_window,
    init_frames,
    seed,
    without_absent_subjects,
)
from labeler_service.labeling.registry import LABELED_STARTS
from labeler_service.wording import and_list, first_of, plural

#: seconds of warm-up after which ``label`` says the kernels are being compiled
NOTICE_AFTER_S = 3.0


@contextlib.contextmanager
def notice_if_slow(message: str, after: float | None = None) -> Iterator[None]:
    """Prints ``message`` on stderr if the block is still running after ``after`` seconds
    (default :data:`NOTICE_AFTER_S`): a first run compiles for a minute, silently otherwise."""
    timer = threading.Timer(
        NOTICE_AFTER_S if after is None else after,
        lambda: print(message, file=sys.stderr, flush=True),
    )
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "input", metavar="IN", help="capture to label (.c3d/.trc/.npz), IN[:start[:stop]] (frames)"
    )
    p.add_argument("output", metavar="OUT", help="labeled capture to write")
    p.add_argument("--model", help="subject template (train structure); else train on IN")
    p.add_argument(
        "--init-frames",
        type=int,
        default=None,
        help="labeled frames at the start (default 50; with --model default 0: boot, no labels)",
    )
    p.add_argument(
        "--labeled-start",
        choices=LABELED_STARTS,
        default="auto",
        help="without --model: 'model' trains subject templates on the init frames and labels "
        "through the model-based labeler; 'labeler' trains the labeler in place; 'auto' "
        "(default): 'model' with 3 or more init frames (as evaluate)",
    )
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of IN")
    p.add_argument("--seed", type=seed, default=0, help="seed of the per-frame shuffle")
    p.add_argument("--drop-recovered", action="store_true", help="write only observed samples")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from labeler_service.capture import (
        Capture,
        c3d_frames_fit,
        check_writable,
        read_segment,
        write_capture,
    )
    from labeler_service.capture.io import split_segment
    from labeler_service.errors import LabelerError
    from labeler_service.labeling.frame import MarkerState
    from labeler_service.labeling.labeler import MIN_TRAIN_FRAMES
    from labeler_service.labeling.registry import (
        low_rate_note,
        make_labeler,
        make_window_labeler,
        resolve_labeled_start,
        thin_subjects,
    )
    from labeler_service.labeling.structure import WINDOW_MIN_FRAMES, window_model
    from labeler_service.labeling.templates import load_model

    check_writable(args.output, inputs=(args.input,))  # before minutes of labeling
    cap = without_absent_subjects(read_segment(args.input, up=args.up), args.input)
    if cap.n_frames == 0:
        raise LabelerError(f"{args.input}: no frames (nothing to label)")
    c3d_frames_fit(args.output, cap.n_frames)  # before minutes of labeling too
    model = load_model(args.model) if args.model else None
    init = init_frames(args.init_frames, model)
    if init < 0 or (model is None and init < MIN_TRAIN_FRAMES):  # before the labeler's own
        raise LabelerError(
            f"--init-frames must be >= {MIN_TRAIN_FRAMES} without --model (the labeler trains "
            f"on them), or 0 with --model (boot), got {init}"
        )
    if cap.n_frames <= init:
        raise LabelerError(
            f"{args.input}: {plural(cap.n_frames, 'frame')}, not more than "
            f"{plural(init, 'init frame')}: give fewer --init-frames (at least "
            f"{MIN_TRAIN_FRAMES} without --model), or a longer segment"
        )
    names = tuple(cap.labels[i] for i in np.flatnonzero(~cap.ghost_mask))
    if model is None and not names:
        raise LabelerError(
            f"{args.input} has no labeled markers: give --model, or label its first frames"
        )
    check_init_window(cap, args.input, init, subjects=model is None)
    for note in thin_subjects(names) if init > 0 else ():
        print(f"note: {args.input}: {note}", file=sys.stderr)
    slow = low_rate_note(cap.rate)
    if slow is not None:
        print(f"note: {args.input}: {slow}", file=sys.stderr)
    # a label without ``subject:`` would come back renamed from the window model
    start, why = resolve_labeled_start(
        args.labeled_start,
        online=True,
        init_frames=init,
        model_given=model is not None,
        labels=names,
        source=args.input,
    )
    if start == "model" and (model is not None or init < WINDOW_MIN_FRAMES):
        raise LabelerError(
            "--labeled-start model trains its model on the init frames: it needs "
            f"--init-frames >= {WINDOW_MIN_FRAMES} and no --model"
        )
    if start == "model":
        cols = np.flatnonzero(~cap.ghost_mask)
        window = Capture(cap.positions[:init][:, cols], names, cap.rate, source=args.input)
        lab = make_window_labeler(window_model(window), rate=cap.rate, window_frames=init)
    else:
        lab = make_labeler(
            "online",
            marker_names=names,
            rate=cap.rate,
            model=model,
            boot=model is not None,
        )
    index = {n: i for i, n in enumerate(lab.marker_names)}
    col_label = np.array([index.get(n, -1) for n in cap.labels], dtype=np.int32)
    if init > 0 and not (col_label >= 0).any():
        raise LabelerError(f"{args.input}: none of its labels is a marker of the model")
    with notice_if_slow(
        "compiling the labeling kernels (numba; the first run after an install takes about a "
        "minute, later runs load them from the cache)..."
    ):
        lab.warmup()

    m = len(lab.marker_names)
    out = np.full((cap.n_frames, m, 3), np.nan, dtype=np.float32)
    # points left unlabeled stay in a column of their input column (a raw track stays a track)
    loose_all = np.full(cap.positions.shape, np.nan, dtype=np.float32)
    seen = np.zeros((cap.n_frames, m), dtype=bool)  # observed (labeled) per frame and marker
    rng = np.random.default_rng(args.seed)
    agree = compared = observed = recovered = 0
    vis = cap.visible
    show = not args.no_progress and sys.stderr.isatty()
    bar = None
    if show:
        from rich.console import Console
        from rich.progress import Progress

        bar = Progress(console=Console(stderr=True), transient=True)
        bar.start()
        task = bar.add_task("labeling", total=cap.n_frames)
    try:
        for f in range(cap.n_frames):
            cols = np.flatnonzero(vis[f])
            cols = cols[rng.permutation(cols.size)]
            pts = cap.positions[f, cols]
            truth = col_label[cols]
            res = lab.process(pts, f / cap.rate, truth if f < init else None)
            keep = res.state == MarkerState.OBSERVED
            seen[f] = keep
            if not args.drop_recovered:
                keep |= res.state == MarkerState.RECOVERED
            out[f, keep] = res.positions[keep]
            free = res.point_labels < 0
            loose_all[f, cols[free]] = pts[free]
            if f >= init:
                observed += res.n_observed
                recovered += 0 if args.drop_recovered else res.n_recovered
                known = truth >= 0
                compared += int(np.count_nonzero(known))
                agree += int(np.count_nonzero(res.point_labels[known] == truth[known]))
            if bar is not None and f % 25 == 0:
                bar.update(task, completed=f + 1)
    finally:
        if bar is not None:
            bar.stop()
    loose_in = np.flatnonzero(np.isfinite(loose_all[..., 0]).any(axis=0))
    positions = np.concatenate([out, loose_all[:, loose_in]], axis=1)
    if args.up == "y":  # back to IN's axes (read rotated to Z up): OUT overlays IN
        positions = np.stack([positions[..., 0], positions[..., 2], -positions[..., 1]], axis=-1)
    out_names = lab.marker_names
    bare = cap.default_subject if model is None else None
    if bare is not None:  # IN's labels named no subject: OUT's name none either
        out_names = tuple(n.removeprefix(f"{bare}:") for n in out_names)
    # the recovered samples written: a C3D marks them calculated (residual 0)
    calculated = np.zeros(positions.shape[:2], dtype=bool)
    calculated[:, :m] = np.isfinite(out[..., 0]) & ~seen
    result = Capture(
        positions,
        out_names + tuple(f"*{j}" for j in loose_in.tolist()),
        cap.rate,
        source=args.output,
        notes=(f"labeled by mocap-labeler label from {args.input}",),
    )
    frames = cap.n_frames - init
    failed = observed == 0 and frames > 0  # (a run that labeled nothing is no success)
    unseen: list[str] = []
    if init > 0 and model is None:
        # markers never visible in the init window: the labeled start cannot learn them, so
        # they stay unlabeled to the end (evaluate counts them as unseen_at_init)
        in_window = np.zeros(m, dtype=bool)
        early = vis[:init].any(axis=0) & (col_label >= 0)  # input columns the window showed
        in_window[col_label[early]] = True
        unseen = [lab.marker_names[i] for i in np.flatnonzero(~in_window)]
    # such a run writes OUT for inspection, but never over an earlier OUT (a good one)
    kept = failed and Path(args.output).exists()
    carried: list[str] = []  # what OUT keeps of a C3D IN besides the points
    src_name = split_segment(args.input)[0]
    if Path(src_name).suffix.lower() == ".c3d" and Path(args.output).suffix.lower() != ".c3d":
        print(
            f"note: {args.output} holds IN's points only: a C3D's analog channels, events and "
            "parameter groups are written to a C3D OUT alone",
            file=sys.stderr,
        )
    if not kept:
        write_capture(result, args.output, like=args.input, kept=carried, calculated=calculated)
    summary = {
        "input": args.input,
        "output": args.output,
        "frames": frames,  # labeled by the labeler: the per-frame figures' frames
        "init_frames": init,  # written with their input labels, before those
        "frames_written": cap.n_frames,
        "markers": m,
        "observed_per_frame": round(observed / frames, 3),
        "recovered_per_frame": round(recovered / frames, 3),
        "agreement_with_input_labels": round(agree / compared, 6) if compared else None,
        "subjects": _subjects(lab.marker_names, seen[init:], cap.rate),
        "labeled_start": start if init > 0 and model is None else None,
        # why ``auto`` fell back to the labeler trained in place (None: it did not)
        "labeled_start_note": why,
        # markers the init window never showed: this start cannot label them
        "unseen_at_init": unseen,
        # what OUT keeps of a C3D IN besides its points (analog channels, events, ...)
        "kept_from_input": carried,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{args.output}: {plural(frames, 'frame')} labeled, "
            f"{summary['observed_per_frame']} of {plural(m, 'marker')} "
            f"observed and {summary['recovered_per_frame']} recovered per frame"
        )
        if carried:
            print(f"{args.output} keeps from {args.input}: {and_list(carried)}")
        if why is not None:
            print(f"labeled start: the labeler trained in place ({why})")
        if compared:
            print(f"agreement with the input's labels: {100 * agree / compared:.3f} %")
        never = []
        for subject, s in summary["subjects"].items():
            name = subject or "(markers without a subject prefix)"
            if s["first_labeled_s"] is None:
                never.append(name)
                continue
            print(
                f"  {name}: labeled from {s['first_labeled_s']:.2f} s, "
                f"{s['observed_per_frame']} of {plural(s['markers'], 'marker')} observed per frame"
            )
        if never:
            print(f"  never labeled: {', '.join(never)}")
        if unseen:
            shown = first_of(unseen, 8)
            print(
                f"  {plural(len(unseen), 'marker')} never visible in the {init} init frames, so "
                f"never labeled from this start: {shown} (a model trained on other frames, "
                "train structure then --model, labels them)"
            )
    if failed:
        where = f"{args.output} left as it was" if kept else f"output written to {args.output}"
        if model is not None:
            why = (
                "the boot found no performer of the model. A model labels the performers it was "
                "trained on: another person's distances differ by more than its templates "
                "allow (about 1 %), so train structure on a segment of these performers, or "
                "give --init-frames N when IN's first frames carry labels. Check too that the "
                "model's marker set matches the capture's (names) and the performers are in view"
            )
        else:
            why = (
                "does the capture's marker set match its labeled frames, and are the performers "
                "in view?"
            )
        raise LabelerError(
            f"{args.input}: no point was labeled in {plural(frames, 'frame')}: {why} ({where})"
        )
    return 0


def _subjects(names: tuple[str, ...], seen, rate: float) -> dict:
    """Per model subject: when its first marker was labeled (seconds after the init window;
    None: never, e.g. not in view or not booted) and its observed markers per frame."""
    from labeler_service.capture import subject_groups

    out = {}
    for name, cols in subject_groups(list(names)).items():
        per_frame = seen[:, cols].sum(axis=1)
        hit = per_frame.nonzero()[0]
        out[name] = {
            "markers": len(cols),
            "first_labeled_s": round(float(hit[0]) / rate, 4) if hit.size else None,
            "observed_per_frame": round(float(per_frame.mean()), 3) if per_frame.size else 0.0,
        }
    return out
