"""Simulated walkers for the boot tests: a model trained on the first half of the take, the
stream it is to boot on the second (the models are trained on other frames than the ones
scored, as the boot issue asks)."""

from __future__ import annotations

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
    """A simulated walk: the model of its first half and its second half."""
    cap = simulate_scene(performers, seconds, "walk", seed=seed, rate=rate, ghosts=ghosts)
    half = cap.n_frames // 2
    return train(cap.frames(0, half)), cap.frames(half, cap.n_frames)
