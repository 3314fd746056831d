"""What the benchmark scripts share. They run as ``python benchmarks/NAME.py``, so the
script's folder is on ``sys.path`` and ``from _common import emit`` resolves."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def emit(result: dict[str, Any], out: str | Path | None = None) -> None:
    """Prints ``result`` as one JSON line on stdout and, with ``out``, writes the same line
    there (creating its folder)."""
    line = json.dumps(result)
    print(line)
    if out:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(line + "\n")


def warm_kernels() -> None:
    """Compiles (or loads) the labeler's and the boot's kernels in this process before a pool
    of workers forks from it: they inherit them. Two workers compiling the same kernels at
    once on a cold numba cache (the first run after a kernel change) raced: one failed with a
    TypingError listing a kernel's "known signatures" (`generalization.py --jobs 2`,
    2026-12-02; numba/numba#4807, #10128)."""
    from labeler_service.labeling.booting import warmup_booting
    from labeler_service.labeling.config import LabelerConfig

    warmup_booting(120.0, LabelerConfig())


def add_hug_args(ap: argparse.ArgumentParser, seconds: float) -> None:
    """The simulated hug the boot-cost benchmarks stream (the service bench's scene): its
    performers, rate, streamed and training seconds, seed."""
    ap.add_argument("--subjects", type=int, default=10)
    ap.add_argument("--rate", type=float, default=360.0)
    ap.add_argument("--seconds", type=float, default=seconds, help="streamed seconds")
    ap.add_argument("--train-seconds", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=0)


def hug_scene(a: argparse.Namespace, protect_frames: int = 0) -> tuple[Any, Any]:
    """``(model, frames)`` for :func:`add_hug_args`' arguments: a model trained on the first
    ``train_seconds``, then the rest with the default corruption (``protect_frames`` at its
    start left whole)."""
    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.scenes.simulate import simulate_scene
    from offline.structure import StructureTrainer

    cap = simulate_scene(performers=a.subjects, seconds=a.train_seconds + a.seconds,
                         scenario="hug", seed=a.seed, rate=a.rate)  # fmt: skip
    split = int(round(a.train_seconds * a.rate))
    model = StructureTrainer().fit([cap.frames(0, split)]).model_
    spec = CorruptionSpec(protect_frames=protect_frames, seed=a.seed)
    return model, corrupt(cap.frames(split, cap.n_frames), spec)


def until_first_attempt(lab: Any, frames: Any) -> tuple[Any, int]:
    """Feeds ``frames`` to the booting labeler ``lab`` (``inline_boot=False``) until its first
    boot attempt is due: ``(snapshot, index of the frame it was taken after)``."""
    f = 0
    while True:
        lab.process(frames.points[f], float(frames.times[f]))
        f += 1
        if lab.needs_boot():
            snap = lab.boot_snapshot()
            if snap.subjects:
                return snap, f - 1


def booting_streams(model: Any, name: str, count: int = 1, rate: float | None = None) -> list:
    """``count`` :class:`~labeler_service.service.stream.StreamState` of a ``boot = true``
    model stream ``name`` (``boot_worker = "thread"``: attempts run where the caller runs
    them), each started from ``model`` as the service starts it (its spare built)."""
    import tempfile

    from labeler_service.labeling.templates import save_model
    from labeler_service.service.settings import load_settings
    from labeler_service.service.stream import StreamState

    stream: dict[str, Any] = {"name": name}
    if rate is not None:
        stream["rate"] = rate
    with tempfile.TemporaryDirectory() as d:
        stream["model"] = str(Path(d) / "model.json")
        save_model(model, stream["model"])
        settings = load_settings(
            labeler="online", metrics_port=None, boot=True, boot_worker="thread",
            udp={"port": 0}, streams=[stream],
        )  # fmt: skip
        states = [StreamState(name, settings, settings.streams[0]) for _ in range(count)]
        for st in states:
            st.start_from_model()
    return states


def real_root(out: str | Path | None) -> Path | None:
    """The real takes' folder (``MOCAP_DATA_DIR``, default ``../shared/data/real``), or None
    after emitting the skip (a benchmark that needs them then returns)."""
    from labeler_service.testing.realdata import real_data_dir

    root = real_data_dir()
    if root is None:
        emit({"skipped": "no real takes (MOCAP_DATA_DIR or ../shared/data/real)"}, out)
    return root


def real_args(
    ap: argparse.ArgumentParser, argv: list[str] | None = None
) -> tuple[argparse.Namespace, Path | None]:
    """``ap`` with ``--out``, parsed (``argv``, else the command line), and the real takes'
    folder (None: skipped and said)."""
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    return a, real_root(a.out)
