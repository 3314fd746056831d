"""Simulated walkers for the boot tests: a model trained on the first half of the take, the
stream it is to boot on the second (the models are trained on other frames than the ones
scored, as the boot issue asks)."""

from __future__ import annotations

import copy
from functools import cache

from labeler_service.capture import Capture
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.simulate import simulate_scene


def train(capture: Capture) -> LabelerModel:
    """``train structure``'s model of ``capture``."""
    from offline.structure import StructureTrainer

    return StructureTrainer().fit([capture]).model_


def split_walk(
    performers: int, seconds: float, *, seed: int, rate: float, ghosts: float = 0.0
) -> tuple[LabelerModel, Capture]:
    """A simulated walk: the model of its first half and its second half.

    Simulated and trained once per session (1.5-2.5 s each; several boot modules ask for the
    same walk); every call returns its own deep copy, so a test that changes its walk changes
    no other module's."""
    return copy.deepcopy(_split_walk(performers, seconds, seed, rate, ghosts))


@cache
def _split_walk(
    performers: int, seconds: float, seed: int, rate: float, ghosts: float
) -> tuple[LabelerModel, Capture]:
    cap = simulate_scene(performers, seconds, "walk", seed=seed, rate=rate, ghosts=ghosts)
    half = cap.n_frames // 2
    return train(cap.frames(0, half)), cap.frames(half, cap.n_frames)


def absent_walk(rate: float) -> tuple[LabelerModel, Capture]:
    """Five simulated walkers; the model knows all five (first half), the stream carries the
    first three (second half): P4 and P5 are absent subjects of the model. (The walk of
    ``split_walk(5, 6.0, seed=7, ghosts=2.0)``, its second half without P4 and P5.)"""
    model, cap = split_walk(5, 6.0, seed=7, rate=rate, ghosts=2.0)
    keep = [i for i, lab in enumerate(cap.labels) if not lab.startswith(("P4:", "P5:"))]
    return model, cap.select(keep)


def subject_on_its_points(walk: tuple[LabelerModel, Capture], subject: str = "P1"):
    """``subject`` (the model's first template) on its true points, in the first frame whose
    12-frame window sees all of its markers: ``(tpl, names, pts, hist)``, the boot's prepared
    template, its marker names, the points (point ``i`` is marker ``i``) and their tracks
    ``(markers, 12, 3)``."""
    import numpy as np

    from labeler_service.labeling.boot import BootConfig
    from labeler_service.labeling.boot_match import _prepare

    model, cap = walk
    tpl = _prepare(model, BootConfig())[0]
    names = list(model.subjects[0].markers)
    cols = [cap.labels.index(f"{subject}:{n}") for n in names]
    seen = np.isfinite(cap.positions[:, cols, 0]).all(axis=1)
    frame = next(f for f in range(11, cap.n_frames) if seen[f - 11 : f + 1].all())
    hist = np.transpose(cap.positions[frame - 11 : frame + 1][:, cols], (1, 0, 2)).astype(float)
    return tpl, names, np.ascontiguousarray(hist[:, -1]), hist


def subject_with_leftover(walk: tuple[LabelerModel, Capture], leftover: tuple[str, ...]):
    """:func:`subject_on_its_points` with the ``leftover`` markers free (tracked, unplaced):
    ``(tpl, ix, assign, pts, hist, free, miss)`` - ``ix`` marker name -> index, ``assign``
    marker -> point (-1 for the leftover), ``free`` the points no marker holds, ``miss`` the
    leftover markers' indices."""
    import numpy as np

    tpl, names, pts, hist = subject_on_its_points(walk)
    ix = {n: i for i, n in enumerate(names)}
    miss = np.array([ix[n] for n in leftover])
    assign = np.arange(tpl.n)
    assign[miss] = -1
    free = np.zeros(tpl.n, dtype=bool)
    free[miss] = True
    return tpl, ix, assign, pts, hist, free, miss
