"""The 62-marker kneeling performer booted from a model of the take's first 900 frames (no
labeled frame), frame by frame from a later start, as a stream: the labels it gives beside
the true marker of each point (the operator's run through the service, offline)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from labeler_service.capture import split_label
from labeler_service.capture.io import read_capture
from labeler_service.labeling.registry import make_labeler


def kneel_booted(real_path, start: int, frames: int) -> tuple[list[str], list[tuple]]:
    """The model's marker names (no subject) and per frame ``(given, truth)``: the model
    marker index each visible point got (-1 none) and its true one, points shuffled."""
    from offline.structure import StructureTrainer

    take = read_capture(real_path("kneel_to_prone_62markers_240hz.c3d"))
    model = StructureTrainer().fit([take.frames(0, 900)]).model_
    lab = make_labeler("online", rate=take.rate, model=model, boot=True)
    names = [split_label(n)[1] for n in lab.marker_names]
    col = np.array([names.index(split_label(n)[1]) for n in take.labels])
    rng = np.random.default_rng(0)
    out = []
    for k in range(start, start + frames):
        p = take.positions[k]
        vis = np.isfinite(p).all(axis=1)
        pts, truth = p[vis], col[vis]
        order = rng.permutation(len(pts))
        pts, truth = pts[order], truth[order]
        got = np.asarray(lab.process(pts, (k - start) / take.rate).point_labels)
        out.append((got, truth))
    return names, out


def kneel_labeled(real_path, start: int, frames: int) -> Iterator[tuple[str, str]]:
    """``(given, true)`` marker names of every point :func:`kneel_booted` labeled."""
    names, run = kneel_booted(real_path, start, frames)
    for got, truth in run:
        for g, t in zip(got[got >= 0], truth[got >= 0], strict=True):
            yield names[g], names[t]
