"""Argument types and input checks shared by the commands."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from labeler_service.errors import MocapError
from labeler_service.wording import plural


def _checked(text: str, convert, ok, what: str):
    """``convert(text)`` when it parses and ``ok`` holds, else argparse's usage error (exit 2,
    ``what`` and the text given)."""
    try:
        value = convert(text)
    except ValueError:
        value = None
    if value is None or not ok(value):
        raise argparse.ArgumentTypeError(f"{what}, got {text!r}")
    return value


def seed(text: str) -> int:
    """``--seed``: a whole number >= 0 (numpy refuses a negative seed with a traceback)."""
    return _checked(text, int, lambda v: v >= 0, "a seed is a whole number >= 0")


def port(text: str) -> int:
    """``--port``, ``--view-port``: a TCP port 0-65535 (0: any free one); a bind would raise
    ``OverflowError`` with a traceback past that."""
    return _checked(text, int, lambda v: 0 <= v <= 65535, "a port is a whole number 0-65535")


def positive(text: str) -> float:
    """A limit that must be a finite number > 0 (``--seconds``): a negative one ended the
    command at once with exit 0."""
    return _checked(text, float, lambda v: 0 < v < float("inf"), "expected a finite number > 0")


def rate(text: str) -> float:
    """``--rate``: a frame rate in Hz that some capture could have
    (:func:`~labeler_service.capture.model.rate_problem`: 0, NaN and 1e7 were taken)."""
    from labeler_service.capture.model import MAX_RATE_HZ, MIN_RATE_HZ, rate_problem

    return _checked(
        text, float, lambda v: rate_problem(v) is None,
        f"expected a frame rate of {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz",
    )  # fmt: skip


def strain_ratio(text: str) -> float:
    """An edge-length ratio limit (``train shoulder --max-strain``): finite and > 1, as the
    95th / 5th percentile of a length is at least 1 (nan, -1, 0 and 1 all kept no triangle, and
    the report said 'edge strain <= nan')."""
    return _checked(
        text, float, lambda v: 1 < v < float("inf"),
        "expected a finite ratio > 1 (an edge's 95th / 5th percentile length)",
    )  # fmt: skip


def positive_int(text: str) -> int:
    """A count that must be a whole number > 0 (``--frames``)."""
    return _checked(text, int, lambda v: v > 0, "expected a whole number > 0")


def check_init_window(cap, spec: str, init: int, step: int = 1, subjects: bool = True) -> None:
    """Refuses a capture with no frames, and labeled init frames (the first ``init`` frames,
    every ``step``-th) that show no labeled marker at all (a take that starts before anyone
    is in view), or, with ``subjects``, that show a subject in fewer than the trainer's
    ``min_pair_frames`` (3) frames (no marker of his can be trained: he walks in later),
    naming the frame to start at as ``FILE:start`` (in the file's numbering, as ``spec``'s
    range is); the labeler's own error said only "start where the subject is in the
    volume"."""
    import numpy as np

    from labeler_service.capture import subject_groups
    from labeler_service.capture.io import split_segment
    from labeler_service.errors import LabelerError
    from labeler_service.labeling.structure import StructureTrainer

    if cap.n_frames == 0:
        raise LabelerError(f"{spec}: no frames (nothing to label)")
    if init <= 0:
        return
    need = StructureTrainer().min_pair_frames  # frames a marker must be seen in to be trained
    named = np.flatnonzero(~cap.ghost_mask)
    visible = np.isfinite(cap.positions[:, named, 0])
    seen = visible.any(axis=1)
    window = visible[: init * step : step]
    path, start, _ = split_segment(spec)
    if not window.any() and seen.any():
        first = start + int(np.argmax(seen))
        where = f"the first frame that shows one is {first} ({path}:{first})"
        every = visible.all(axis=1)
        if every.any() and start + int(np.argmax(every)) > first:
            full = start + int(np.argmax(every))
            where += (
                f", the first that shows all {visible.shape[1]} is {full} ({path}:{full}; the "
                "markers a window does not show stay unlabeled)"
            )
        raise LabelerError(
            f"{spec}: no labeled marker is seen in the first {plural(init, 'frame')} (the "
            "labeled init "
            f"window): {where}"
        )
    if not subjects or init < need:  # (too few init frames: the commands say so)
        return
    groups = subject_groups([cap.labels[i] for i in named])
    outside = [s for s, cols in groups.items() if window[:, cols].sum(axis=0).max() < need]
    if not outside or not window.any():
        return
    present = np.stack([visible[:, cols].any(axis=1) for cols in groups.values()], axis=1)
    every = np.asarray(present.all(axis=1))
    if not every.any() or every[0]:
        return  # the labeler's own error names the subject (no later start would help)
    first = start + int(np.argmax(every))
    more = f" (and {len(outside) - 1} more)" if len(outside) > 1 else ""
    raise LabelerError(
        f"{spec}: subject {outside[0] or '(no prefix)'}{more} shows no marker in "
        f"{need} or more of the first {plural(init, 'frame')} (the labeled init "
        "window), so "
        f"nothing of him can be learned: every subject is in view from frame {first} "
        f"({path}:{first})"
    )


def without_absent_subjects(cap, spec: str):
    """``cap`` without the subjects never seen in it (:meth:`Capture.without_absent_subjects`),
    each said on stderr."""
    import sys

    kept, absent = cap.without_absent_subjects()
    for name in absent:
        print(f"note: {spec}: subject {name} is never seen in the take: left out", file=sys.stderr)
    return kept


def _labeler_name(text: str) -> str:
    return "baseline" if text == "closest-point" else text


def add_labeler_argument(p) -> None:
    """``--labeler``: the online labeler or the closest-point baseline, named ``baseline`` (the
    service's name) or ``closest-point`` (``evaluate --method``'s); parsed to the service's."""
    p.add_argument(
        "--labeler",
        type=_labeler_name,
        choices=["online", "baseline"],
        default="online",
        metavar="{online,closest-point}",
        help="the online labeler, or the closest-point baseline (also called baseline)",
    )


#: labeled init frames of ``label`` and ``evaluate`` without ``--model`` (with one: 0, a boot)
INIT_FRAMES = 50


def init_frames(asked: int | None, model: object) -> int:
    """``--init-frames`` as given, else the default of ``label`` and ``evaluate``: 0 with a
    model (a boot from anonymous points, as a live stream), else :data:`INIT_FRAMES`."""
    if asked is not None:
        return asked
    return 0 if model is not None else INIT_FRAMES


def usable_folder(path: Path, flag: str) -> Path:
    """Creates the folder a command writes its files into (``demo --out``, ``bench latency
    --workdir``) and proves it writable before any work is done: a file there, or an
    unwritable place, ended the command with a traceback after the scene was built."""
    from labeler_service.capture.io import os_reason

    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.NamedTemporaryFile(dir=path, prefix=".probe-").close()
    except OSError as exc:
        raise MocapError(f"{path}: cannot use as {flag}: {os_reason(exc)}") from exc
    return path
