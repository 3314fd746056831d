"""Offline training of subject templates (``mocap-labeler train structure``), sklearn style.

The trainer itself lives in :mod:`labeler_service.labeling.structure` (the service trains a
stream's window model with it, and ``labeler_service`` may not import ``offline``); this module
adds reading the captures from files (``up``: the vertical axis of the files) and keeps the
names every caller imports from here.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from labeler_service.capture import Capture, read_capture
from labeler_service.labeling import structure as _core
from labeler_service.labeling.structure import (
    CHIRALITY_A_MM,
    CHIRALITY_AGREE,
    CHIRALITY_FRAMES,
    CHIRALITY_MAX,
    CHIRALITY_MIN_MM,
    CHIRALITY_PER_MARKER,
    CHIRALITY_POOL,
    HINGE_MAX_MARKERS,
    TWIN_AGREE,
    TWIN_MIN_FRAMES,
    TWIN_PER_MARKER,
    TWIN_REACH,
    TWIN_SEPARATED,
    TWIN_WITNESSES,
    TWIN_Z,
    chirality_quads,
    handed_shapes,
    twin_pairs,
    twin_witnesses,
)


class StructureTrainer(_core.StructureTrainer):
    """:class:`labeler_service.labeling.structure.StructureTrainer` that also takes capture
    files (``.c3d``/``.trc``/``.npz`` paths, read with ``up`` as the vertical axis)."""

    def __init__(self, *, up: str = "z", **rule: Any) -> None:
        """``rule``: the keywords of the core trainer (``tolerance_mm``, ``distance_weight``,
        ``min_size``, ``max_size``, ``min_pair_frames``, ``all_seeds``)."""
        super().__init__(**rule)
        self.up = up

    def fit(self, captures: Sequence[Capture | str | Path]) -> StructureTrainer:
        """Reads the captures given as paths, then learns ``model_`` (one template per
        subject found in them)."""
        caps = [c if isinstance(c, Capture) else read_capture(c, up=self.up) for c in captures]
        super().fit(caps)
        return self


__all__ = [
    "CHIRALITY_AGREE",
    "CHIRALITY_A_MM",
    "CHIRALITY_FRAMES",
    "CHIRALITY_MAX",
    "CHIRALITY_MIN_MM",
    "CHIRALITY_PER_MARKER",
    "CHIRALITY_POOL",
    "HINGE_MAX_MARKERS",
    "TWIN_AGREE",
    "TWIN_MIN_FRAMES",
    "TWIN_PER_MARKER",
    "TWIN_REACH",
    "TWIN_SEPARATED",
    "TWIN_WITNESSES",
    "TWIN_Z",
    "StructureTrainer",
    "chirality_quads",
    "handed_shapes",
    "twin_pairs",
    "twin_witnesses",
]
