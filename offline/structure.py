"""Offline training of subject templates (``mocap-labeler train structure``), sklearn style.

``StructureTrainer(...).fit(captures)`` learns one
:class:`~labeler_service.labeling.templates.SubjectTemplate`
per subject with the same code the online labeler uses on its training window
(:func:`labeler_service.labeling.training.train_subject`): D and A (Yu et al. 2007, Eq. 1-2),
rigid bodies, reference shapes and per-marker motion noise. Frames of several captures are
pooled per subject; the motion noise is learned per capture (it depends on the rate) and averaged.
The fitted template set is ``model_`` (a :class:`~labeler_service.labeling.templates.LabelerModel`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from labeler_service.capture import Capture, read_capture, split_label
from labeler_service.errors import ModelError
from labeler_service.labeling.templates import LabelerModel
from labeler_service.labeling.training import motion_noise, train_subject


class StructureTrainer:
    """Learns subject templates from labeled captures.

    Parameters are those of the rigid-body rule (see :mod:`labeler_service.labeling.training`):
    ``tolerance_mm`` (largest ``A + distance_weight D`` inside a body), ``distance_weight``,
    ``min_size``/``max_size`` (markers per body, 1-8), ``min_pair_frames`` (samples needed for a
    pair's statistics), ``all_seeds`` (every marker seeds a body: offline there is time for the
    richer, overlapping body set) and ``up`` (vertical axis when reading files).
    """

    def __init__(
        self,
        tolerance_mm: float = 6.0,
        distance_weight: float = 0.02,
        min_size: int = 3,
        max_size: int = 6,
        min_pair_frames: int = 3,
        all_seeds: bool = True,
        up: str = "z",
    ) -> None:
        self.tolerance_mm = tolerance_mm
        self.distance_weight = distance_weight
        self.min_size = min_size
        self.max_size = max_size
        self.min_pair_frames = min_pair_frames
        self.all_seeds = all_seeds
        self.up = up

    def _load(self, captures: Sequence[Capture | str | Path]) -> list[Capture]:
        out = []
        for c in captures:
            out.append(c if isinstance(c, Capture) else read_capture(c, up=self.up))
        if not out:
            raise ModelError("train structure needs at least one capture")
        return out

    def fit(self, captures: Sequence[Capture | str | Path]) -> StructureTrainer:
        """Learns ``model_`` (one template per subject found in the captures)."""
        caps = self._load(captures)
        # subject -> marker names in order of first appearance
        subjects: dict[str, list[str]] = {}
        for cap in caps:
            for s in cap.subjects:
                names = subjects.setdefault(s, [])
                for i in cap.subject_columns(s):
                    marker = split_label(cap.labels[i])[1]
                    if marker not in names:
                        names.append(marker)
        if not subjects:
            raise ModelError("no labeled markers in the captures (only unlabeled *N tracks?)")
        templates = []
        for subject, markers in subjects.items():
            blocks, noises = [], []
            for cap in caps:
                cols = {split_label(cap.labels[i])[1]: i for i in cap.subject_columns(subject)}
                if not cols:
                    continue
                pos = np.full((cap.n_frames, len(markers), 3), np.nan, dtype=np.float32)
                for k, mk in enumerate(markers):
                    if mk in cols:
                        pos[:, k] = cap.positions[:, cols[mk]]
                blocks.append(pos)
                noises.append(motion_noise(pos, cap.rate))
            pos = np.concatenate(blocks)
            t = train_subject(
                subject or "subject",
                markers,
                pos,
                caps[0].rate,
                tolerance_mm=self.tolerance_mm,
                distance_weight=self.distance_weight,
                min_size=self.min_size,
                max_size=self.max_size,
                min_pair_frames=self.min_pair_frames,
                all_seeds=self.all_seeds,
            )
            # the pooled frames' motion noise is replaced: noise depends on the rate, so it is
            # learned per capture and averaged (positive and finite like each capture's)
            q = np.mean(noises, axis=0)
            templates.append(t.model_copy(update={"motion_noise": [float(x) for x in q]}))
        rates = sorted({c.rate for c in caps})
        self.model_ = LabelerModel(
            rate=rates[0],
            subjects=templates,
            source=", ".join(c.source or "capture" for c in caps),
        )
        self.n_frames_ = int(sum(c.n_frames for c in caps))
        return self
