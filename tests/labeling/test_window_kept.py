"""The labeled start through a window model starts its inner labeler from the whole labeled
window (``make_window_labeler``'s ``labeled_kept_s``), as the labeler trained in place does,
not from its last ``LABELED_KEPT_S``: started from the last 0.5 s of a 50-frame window at 30 Hz
the inner labeler gave a ghost a hidden hand marker's label (acceptance scene c,
``downsample4``, frame 188, ``P6:RHM2``)."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture
from labeler_service.errors import LabelerError
from labeler_service.labeling.booting import LABELED_KEPT_S, BootingLabeler
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import make_window_labeler
from labeler_service.labeling.structure import window_model


def _frames(rng, n: int) -> np.ndarray:
    base = rng.normal(scale=80.0, size=(1, 6, 3))
    return (base + rng.normal(size=(n, 6, 3))).astype(np.float64)


def _labeled_frames_fed(monkeypatch, lab, pos: np.ndarray, rate: float, n_labeled: int) -> int:
    """Feeds ``n_labeled`` labeled frames then one unlabeled; returns how many labeled frames
    the inner labeler was started from."""
    fed = []
    real = Labeler.process

    def spy(self, points, t, labels=None):
        if labels is not None:
            fed.append(t)
        return real(self, points, t, labels)

    monkeypatch.setattr(Labeler, "process", spy)
    ids = np.arange(pos.shape[1], dtype=np.int32)
    for f in range(n_labeled + 1):
        lab.process(pos[f], f / rate, ids if f < n_labeled else None)
    return len(fed)


def test_window_labeler_starts_from_the_whole_window(rng, monkeypatch):
    rate, n = 30.0, 50  # 1.67 s of labeled window, longer than LABELED_KEPT_S
    assert n / rate > LABELED_KEPT_S
    pos = _frames(rng, n + 1)
    model = window_model(
        Capture(pos[:n].astype("float32"), tuple(f"s:m{i}" for i in range(6)), rate)
    )
    lab = make_window_labeler(model, rate=rate, window_frames=n)
    assert _labeled_frames_fed(monkeypatch, lab, pos, rate, n) == n


def test_booting_labeler_keeps_the_last_labeled_seconds_by_default(rng, monkeypatch):
    rate, n = 30.0, 50
    pos = _frames(rng, n + 1)
    model = window_model(
        Capture(pos[:n].astype("float32"), tuple(f"s:m{i}" for i in range(6)), rate)
    )
    lab = BootingLabeler(model, rate)
    assert _labeled_frames_fed(monkeypatch, lab, pos, rate, n) == round(LABELED_KEPT_S * rate)
    with pytest.raises(LabelerError, match="labeled_kept_s"):
        BootingLabeler(model, rate, labeled_kept_s=0.0)
