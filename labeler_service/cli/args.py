"""Argument types and input checks shared by the commands."""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """``--seed``: a whole number >= 0 (numpy refuses a negative seed with a traceback)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a whole number >= 0, got {text!r}")
    return value


def check_init_window(cap, spec: str, init: int) -> None:
    """Refuses labeled init frames that show no labeled marker at all (a take that starts
    before anyone is in view), naming the first frame that shows one as ``FILE:start`` (in
    the file's numbering, as ``spec``'s range is); the labeler's own error said only "start
    where the subject is in the volume"."""
    import numpy as np

    from labeler_service.capture.io import split_segment
    from labeler_service.errors import LabelerError

    if init <= 0:
        return
    visible = np.isfinite(cap.positions[:, ~cap.ghost_mask, 0])
    seen = visible.any(axis=1)
    if seen[:init].any() or not seen.any():
        return
    path, start, _ = split_segment(spec)
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
        f"{spec}: no labeled marker is seen in the first {init} frames (the labeled init "
        f"window): {where}"
    )


def without_absent_subjects(cap, spec: str):
    """``cap`` without the subjects never seen in it (:meth:`Capture.without_absent_subjects`),
    each said on stderr."""
    import sys

    kept, absent = cap.without_absent_subjects()
    for name in absent:
        print(f"note: {spec}: subject {name} is never seen in the take: left out", file=sys.stderr)
    return kept
