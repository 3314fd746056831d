"""``mocap-labeler demo``: the whole pipeline in one command on loopback UDP (no broker).

scene -> replay (shuffled, gaps, ghosts; first ``--init-frames`` frames labeled, or none) ->
``mocap-labeler serve`` (a subprocess; the stream starts from the labeled init frames, the
paper's training window, or boots its performers from subject models) -> subscriber. The
scene is composed from two real CMU takes when the real captures are present
(``MOCAP_DATA_DIR`` or ``../shared/data/real``), else simulated.

Scoring compares what the subscriber received with the truth. An observed marker's published
position is exactly the input point it was given, so per ``seq`` each published observed
position is matched to its input point, whose true label is known; the resulting labeled frames
are scored by :class:`~labeler_service.evaluation.scoring.Scorer`, the scorer of ``evaluate``
(same definitions, same error anatomy):

- ``accuracy``: correctly labeled visible true markers / visible true markers, over the frames
  after the init window (a frame lost on the way counts as unlabeled);
- ``ghost_labeled_rate``: ghost points published as some marker / ghost points;
- ``recovery_mean_mm``/``recovery_p95_mm``: error of the recovered positions of markers removed
  by the gaps (truth known);
- latency p50/p99/p99.9 (sender stamp -> subscriber receipt) and labeling time per frame.

``--start boot`` is the production path without labels: subject models are trained
(``StructureTrainer``, as ``train structure``) on other segments of the same takes (real: the
frames after the scene's window of each take; simulated: the same performers after the scene),
then the stream carries no labels at all and the service boots every performer; the report adds
``boot_s`` per subject, ``boot_s_max`` and ``accuracy_after_boot`` (the ``evaluate``
definitions); ``accuracy`` counts the frames before each boot as unlabeled. ``--init-frames 0``
alone means the same. Measured (BENCHMARKS.md, ``demo --start boot``): on the CMU scene both
performers boot in 0.24-0.32 s and are 99.85-99.87 % correct after boot (97.1-97.7 % over the
stream) against 99.997 % from the window; on the simulated 4-person hug (no real captures) one
hugged performer boots only after seconds. The default is the boot (:data:`DEFAULT_START`): a
live capture has no labels. ``--start window`` (alias ``labeled``; ``--init-frames N`` > 0 alone
means it too) starts from the labeled window. Known limit: with ``--frames 240`` (the model
trained on frames 240 on) one CMU performer never reaches the 95 % criterion: with the demo's
gap and ghost his right shoulder and elbow are read as the left ones (no learned chirality
quadruple covers them) and his left arm stays unlabeled; without them he boots in 0.31 s
(``evaluate`` of the same scene and model).

Writes ``report.json``, ``latency_histogram.png`` and ``accuracy_over_time.png`` (plus the
scene and the labeled output as C3D) into ``--out``.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import numpy as np

from labeler_service.cli.args import add_labeler_argument, port, seed, usable_folder
from labeler_service.errors import MocapError
from labeler_service.testing.realdata import real_file
from labeler_service.wording import plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("reports/demo"), help="report folder")
    p.add_argument("--seed", type=seed, default=7, help="scene and corruption seed")
    p.add_argument("--frames", type=int, default=1200, help="scene length (frames)")
    p.add_argument("--init-frames", type=int, default=None,
                   help="labeled frames at the start: N > 0 starts from a labeled window "
                        "(--start window), 0 sends no labels (--start boot); default: none, the "
                        "demo boots (50 with --start window)")  # fmt: skip
    p.add_argument("--gaps", type=int, default=1, help="markers hidden per subject per gap")
    p.add_argument("--gap-frames", type=int, default=20, help="frames per gap")
    p.add_argument("--ghosts", type=float, default=1.0, help="mean ghost points per frame")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed x capture rate")
    add_labeler_argument(p)
    p.add_argument("--start", choices=["window", "labeled", "boot"], default=None,
                   help=f"window (= labeled): the first --init-frames frames carry labels; "
                        f"boot: models trained on other segments, no labels sent (default: "
                        f"{DEFAULT_START}, or what --init-frames says)")  # fmt: skip
    p.add_argument("--view", action="store_true",
                   help="live 3D view of the stream in a browser (prints the URL; keeps serving "
                        "the last frames after the demo until Ctrl-C)")  # fmt: skip
    p.add_argument("--view-port", type=port, default=8765, help="HTTP port of the live view")


#: The demo's start when neither ``--start`` nor ``--init-frames`` says (module docstring).
DEFAULT_START = "boot"
#: Labeled frames of the window start when ``--init-frames`` is not given.
DEFAULT_INIT_FRAMES = 50


def resolve_start(
    start: str | None, init_frames: int | None, labeler: str = "online"
) -> tuple[str, int]:
    """``(start, init_frames)`` from the two options: ``labeled`` is ``window``; without
    ``--start``, ``--init-frames 0`` means boot and ``N`` > 0 the window, and neither means
    :data:`DEFAULT_START` (the window for the closest-point baseline, which has no boot);
    ``--start boot`` with labeled frames is an error (it sends none)."""
    if start == "labeled":
        start = "window"
    if start is None:
        if init_frames is None:
            start = DEFAULT_START if labeler == "online" else "window"
        else:
            start = "boot" if init_frames == 0 else "window"
    if init_frames is not None and init_frames < 0:
        raise MocapError(f"--init-frames must be >= 0, got {init_frames}")
    if start == "boot":
        if init_frames:
            raise MocapError("--start boot sends no labels: leave --init-frames out (or 0)")
        return start, 0
    from labeler_service.labeling.labeler import MIN_TRAIN_FRAMES

    if init_frames == 0:  # (said ">= 1", and 1 and 2 were then refused for the online labeler)
        need = MIN_TRAIN_FRAMES if labeler == "online" else 1
        raise MocapError(f"--start window needs labeled frames: --init-frames >= {need}")
    if labeler == "online" and init_frames is not None and init_frames < MIN_TRAIN_FRAMES:
        # (the service's training refused them and the demo ran on, every frame dropped)
        raise MocapError(
            f"--start window trains the labeler on the labeled frames: --init-frames must be "
            f">= {MIN_TRAIN_FRAMES}, got {init_frames}"
        )
    return start, DEFAULT_INIT_FRAMES if init_frames is None else init_frames


def _scene(seed: int, frames: int):
    a = real_file("cmu_01_01_playground.c3d")
    b = real_file("cmu_02_05_expressions.c3d")
    if a is not None and b is not None:
        from labeler_service.scenes.compose import compose_scene

        cap = compose_scene([f"{a}:600", str(b)], radius=300.0, frames=frames, seed=seed)
        return cap, "two real CMU takes composed at radius 300 mm"
    from labeler_service.scenes.simulate import simulate_scene

    cap = simulate_scene(performers=4, seconds=frames / 120.0, scenario="hug", seed=seed)
    return cap, "simulated 4-performer hug (no real captures found)"


def _boot_model(args: argparse.Namespace, path: Path):
    """``--start boot``: a model of the demo's performers trained on other segments of their
    takes (real) or on the same simulated performers after the scene's frames; returns its path."""
    from labeler_service.labeling.templates import save_model
    from offline.structure import StructureTrainer

    a = real_file("cmu_01_01_playground.c3d")
    b = real_file("cmu_02_05_expressions.c3d")
    if a is not None and b is not None:
        from labeler_service.capture import read_capture
        from labeler_service.scenes.compose import compose_scene

        # the scene uses a[600:600+F] and b[0:F]: train on the frames after those windows
        n = min(600, read_capture(a).n_frames - 600 - args.frames,
                read_capture(b).n_frames - args.frames)  # fmt: skip
        if n < 120:
            raise MocapError(f"--start boot: --frames {args.frames} leaves fewer than 120 frames "
                             "of the takes to train the models on")  # fmt: skip
        train = compose_scene([f"{a}:{600 + args.frames}", f"{b}:{args.frames}"], radius=300.0,
                              frames=n, seed=args.seed)  # fmt: skip
    else:
        from labeler_service.scenes.simulate import simulate_scene

        # the same performers (the scene's seed) in a take twice as long: train on its second
        # half, which the scene's frames do not contain (another seed is other people)
        sim = simulate_scene(performers=4, seconds=2 * args.frames / 120.0, scenario="hug",
                             seed=args.seed)  # fmt: skip
        train = sim.frames(args.frames, sim.n_frames)
    save_model(StructureTrainer().fit([train]).model_, path)
    return path


def score(frames, received, init_frames: int, rate: float | None = None):
    """Scores received labeled frames against the stream's truth (see the module docstring)
    with the scorer ``evaluate`` uses (:class:`~labeler_service.evaluation.scoring.Scorer`):
    each message becomes the :class:`LabeledFrame` the service computed, in the truth's
    marker order. A frame lost on the way is scored as all-unlabeled. ``rate`` (Hz) enables
    the boot scores (``boot_s``, ``accuracy_after_boot``)."""
    from labeler_service.evaluation.scoring import Scorer
    from labeler_service.labeling.frame import LabeledFrame

    names = frames.marker_names
    index = {n: i for i, n in enumerate(names)}
    by_seq = {r.msg.seq: r for r in received}
    col_of: dict[tuple[str, ...], np.ndarray] = {}
    scorer = Scorer(names, init_frames, frames.n_frames, rate=rate)
    m = len(names)
    for f in range(frames.n_frames):
        truth = frames.truth[f]
        r = by_seq.get(f) if f >= init_frames else None
        out = None
        if r is not None:
            if r.names not in col_of:  # service marker j -> column in the truth's marker list
                col_of[r.names] = np.array([index.get(n, -1) for n in r.names], dtype=np.int64)
            cols = col_of[r.names]
            known = cols >= 0  # the service publishes the truth's markers (same scene)
            # an observed marker's published position is exactly its input point
            point_of = {frames.points[f][i].tobytes(): i for i in range(len(truth))}
            labels = np.full(len(truth), -1, dtype=np.int32)
            for j in np.flatnonzero((r.msg.state == 1) & known):
                i = point_of.get(r.msg.positions[j].tobytes())
                if i is not None:
                    labels[i] = cols[j]
            state = np.zeros(m, dtype=np.uint8)
            positions = np.full((m, 3), np.nan, dtype=np.float32)
            state[cols[known]] = r.msg.state[known]
            positions[cols[known]] = r.msg.positions[known]
            out = LabeledFrame(float(frames.times[f]), labels, positions, state)
        scorer.add(f, truth, out, removed=frames.removed[f], positions=frames.positions[f])
    return scorer.result()


def _plots(out: Path, latency_ms: np.ndarray, per_frame: np.ndarray, rate: float, init: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    hi = np.percentile(latency_ms, 99.9) if latency_ms.size else 1.0
    ax.hist(np.clip(latency_ms, 0, hi), bins=80, color="#3b75af")
    for q, c in ((50, "k"), (99, "r")):
        if latency_ms.size:
            v = np.percentile(latency_ms, q)
            ax.axvline(v, color=c, ls="--", lw=1, label=f"p{q} {v:.2f} ms")
    ax.set_xlabel("end-to-end latency (ms): sender stamp -> subscriber receipt")
    ax.set_ylabel("frames")
    ax.set_title("demo: replay -> service (UDP loopback) -> subscriber")
    if latency_ms.size:  # (no frame received: no percentile lines to name)
        ax.legend()
    fig.tight_layout()
    p1 = out / "latency_histogram.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 3.6))
    t = np.arange(per_frame.size) / rate
    ax.plot(t[init:], 100 * per_frame[init:], lw=0.8)
    if init > 0:  # (a boot sends no labeled frame: no window to shade)
        ax.axvspan(0, init / rate, color="0.85", label="labeled training window")
    ax.set_ylim(max(0, np.nanmin(100 * per_frame[init:]) - 5) if per_frame.size > init else 0, 101)
    ax.set_xlabel("capture time (s)")
    ax.set_ylabel("correctly labeled (%)")
    ax.set_title("per-frame labeling accuracy of the streamed output")
    if init > 0:
        ax.legend(loc="lower right")
    fig.tight_layout()
    p2 = out / "accuracy_over_time.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return p1, p2


async def _run_pipeline(args, frames, workdir: Path):
    from labeler_service.testing.harness import run_pipeline, service_settings

    stream = {"name": "demo", "rate": frames.rate,
              **({"model": str(args.model)} if args.start == "boot" else {})}  # fmt: skip
    settings = service_settings(
        "udp", stream, 5.0, labeler=args.labeler, boot=args.start == "boot",
        udp={"enabled": True, "port": getattr(args, "udp_port", 0)},  # --view chooses it
        # absorbs the one-time training stall at the first unlabeled frame (docs/service.md)
        queue_size=256,
    )  # fmt: skip
    progress = None
    bar = None
    if sys.stderr.isatty():
        from rich.progress import Progress

        bar = Progress(transient=True)
        task = bar.add_task("streaming", total=frames.n_frames)
        bar.start()

        def progress(seq: int, f: int) -> None:
            bar.update(task, completed=seq + 1)

    try:
        return await run_pipeline(frames, settings, workdir, stream="demo",
                                  init_frames=args.init_frames, speed=args.speed,
                                  progress=progress)  # fmt: skip
    finally:
        if bar is not None:
            bar.stop()


def run(args: argparse.Namespace) -> int:
    from labeler_service.capture import write_capture
    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.tools.replay import check_pace
    from labeler_service.tools.subscribe import Recorder, percentiles, strict_json

    args.start, args.init_frames = resolve_start(args.start, args.init_frames, args.labeler)
    check_pace(args.speed, 1)  # (before the scene is built and the service started)
    out: Path = usable_folder(args.out, "--out")
    t_start = time.perf_counter()
    cap, what = _scene(args.seed, args.frames)
    if args.start == "boot":
        if args.labeler != "online":
            raise MocapError("--start boot needs --labeler online")
        args.model = _boot_model(args, out / "model.json")
    write_capture(cap, out / "scene.c3d")
    spec = CorruptionSpec(gaps=args.gaps, gap_frames=args.gap_frames, ghosts=args.ghosts,
                          protect_frames=args.init_frames, seed=args.seed)  # fmt: skip
    frames = corrupt(cap, spec)
    for note in frames.notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"scene: {what}: {plural(len(cap.subjects), 'subject')}, "
          f"{plural(len(frames.marker_names), 'marker')}, "
          f"{plural(frames.n_frames, 'frame')} at {frames.rate:g} Hz")  # fmt: skip
    labeled = (
        f"first {plural(args.init_frames, 'frame')} labeled"
        if args.init_frames
        else "no labels (the service boots the subjects)"
    )
    print(f"streaming over loopback UDP at {args.speed:g}x ({frames.n_frames / frames.rate / max(args.speed, 1e-9):.0f} s), "  # noqa: E501
          f"{labeled}, {args.gaps} gap(s)/subject, "
          f"{args.ghosts:g} ghosts/frame")  # fmt: skip
    view = _start_view(args, out) if args.view else None  # (process, url)
    print("starting the service: its first start in a fresh checkout compiles the labeling "
          "kernels (a minute or two); later starts load them", file=sys.stderr)  # fmt: skip
    res = asyncio.run(_run_pipeline(args, frames, out))
    scored = score(frames, res.received, args.init_frames, rate=frames.rate)
    s = scored.summary()
    lat = np.array([r.latency_ms for r in res.received if r.latency_ms is not None])
    # after start-up: from 1 s past the training window (the first unlabeled frame trains)
    start = args.init_frames + frames.rate
    steady = np.array(
        [r.latency_ms for r in res.received if r.msg.seq >= start and r.latency_ms is not None]
    )
    proc = np.array([r.msg.proc_us / 1e3 for r in res.received])
    expected = res.sent - args.init_frames
    lat_q, steady_q, proc_q = percentiles(lat), percentiles(steady), percentiles(proc)
    report = {
        "scene": what,
        "subjects": len(cap.subjects),
        "markers": len(frames.marker_names),
        "frames": frames.n_frames,
        "rate": frames.rate,
        "init_frames": args.init_frames,
        "start": args.start,
        "labeler": args.labeler,
        "transport": "udp (loopback)",
        "accuracy": s["accuracy"],
        "ghost_labeled_rate": s["ghost_labeled_rate"],
        "recovered_fraction": s["recovery_rate"],
        "recovery_mean_mm": s["recovery_mean_mm"],
        "recovery_p95_mm": s["recovery_p95_mm"],
        "errors": s["errors"],
        "max_swap_frames": s["max_swap_frames"],
        "worst_markers": s["worst_markers"][:5],
        "frames_sent": res.sent,
        "frames_received": len(res.received),
        "frames_lost": int(expected - len(res.received)),
        "service_drops": res.drops_service,
        "latency_ms_p50": lat_q["p50"],
        "latency_ms_p99": lat_q["p99"],
        "latency_ms_p99_9": lat_q["p99.9"],
        "steady_latency_ms_p50": steady_q["p50"],
        "steady_latency_ms_p99": steady_q["p99"],
        "labeling_ms_p50": proc_q["p50"],
        "labeling_ms_p99": proc_q["p99"],
        "seconds": time.perf_counter() - t_start,
    }
    if args.start == "boot":
        report.update(boot_s=s["boot_s"], boot_s_max=s["boot_s_max"],
                      accuracy_after_boot=s["accuracy_after_boot"])  # fmt: skip
    rec = Recorder()
    for r in res.received:
        rec.add(r, frames.rate)
    rec.write(out / "labeled.c3d")
    (out / "report.json").write_text(strict_json(report, indent=2))
    p1, p2 = _plots(out, lat, scored.per_frame_accuracy, frames.rate, args.init_frames)
    rec_txt = ("-" if s["recovery_mean_mm"] is None else
               f"{s['recovery_mean_mm']:.1f} mm mean, {s['recovery_p95_mm']:.1f} mm p95 "
               f"({100 * s['recovery_rate']:.0f} % of hidden samples recovered)")  # fmt: skip
    print(f"accuracy        {100 * s['accuracy']:.2f} % of visible markers labeled correctly")
    if args.start == "boot":
        after = s["accuracy_after_boot"]
        boot_s = s["boot_s"] or {}
        booted = {k: v for k, v in boot_s.items() if v is not None}
        never = [k for k, v in boot_s.items() if v is None]
        slowest = f" (slowest {max(booted.values()):.2f} s)" if booted else ""
        print(
            f"boot            {len(booted)} of {len(boot_s)} subjects booted{slowest}; "
            + (f"never: {', '.join(never)}; " if never else "")
            + f"after boot {'-' if after is None else f'{100 * after:.2f} %'} correct"
        )
    print(f"ghosts labeled  {100 * (s['ghost_labeled_rate'] or 0.0):.2f} %")
    print(f"recovery        {rec_txt}")
    print(f"latency         p50 {report['latency_ms_p50']:.2f} ms, p99 "
          f"{report['latency_ms_p99']:.2f} ms, p99.9 {report['latency_ms_p99_9']:.2f} ms "
          f"(labeling {report['labeling_ms_p50']:.2f} ms p50); after start-up p99 "
          f"{report['steady_latency_ms_p99']:.2f} ms")  # fmt: skip
    print(f"frames          {len(res.received)}/{expected} labeled frames received, "
          f"drops {res.drops_service or 'none'}")  # fmt: skip
    print(f"report          {out / 'report.json'}, {p1.name}, {p2.name}, labeled.c3d "
          f"({report['seconds']:.0f} s)")  # fmt: skip
    if view is not None:
        _keep_viewing(*view)
    return 0


def _start_view(args: argparse.Namespace, out: Path):
    """``--view``: ``mocap-labeler view`` in a subprocess on the demo's stream (its own process,
    like a user's viewer). The service's UDP port is chosen here so the viewer knows it first."""
    import atexit
    import signal
    import socket
    import subprocess

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        args.udp_port = s.getsockname()[1]
    cmd = [sys.executable, "-m", "labeler_service.cli.main", "view", "--from",
           f"udp://127.0.0.1:{args.udp_port}/demo", "--port", str(args.view_port)]  # fmt: skip
    with (out / "view.log").open("w") as log:  # the child keeps its own descriptor
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)

    def stop_viewer() -> None:
        if proc.poll() is None:
            proc.terminate()

    atexit.register(stop_viewer)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so that atexit runs
    assert proc.stdout is not None
    with proc.stdout:  # the viewer prints one line: its address
        line = proc.stdout.readline()
    if not line.startswith("view "):
        proc.wait(timeout=10)
        raise MocapError(f"the live view did not start: {(out / 'view.log').read_text()[-800:]}")
    url = line.split()[1]
    print(f"live view       {url}  (open it in a browser; log {out / 'view.log'})", flush=True)
    return proc, url


def _keep_viewing(proc, url: str) -> None:
    """Keeps the viewer serving the demo's last frames until Ctrl-C (or SIGTERM)."""
    import signal

    signal.signal(signal.SIGINT, signal.default_int_handler)  # even if started with it ignored
    print(f"the live view keeps showing the last frames at {url}: Ctrl-C to stop", flush=True)
    try:
        proc.wait()
    except KeyboardInterrupt:
        pass
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=10)
