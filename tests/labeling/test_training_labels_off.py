"""Training on labels that do not stay on their markers (a client's init frames with their
labels shuffled every frame): the template's bodies then vary by ~230 mm, match any points,
and a boot attempt with it ran for minutes (issue 11, a hostile user's run). Training refuses
such labels with a message that says so, and a model file with such bodies is refused at load."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.errors import LabelerError, ModelError
from labeler_service.labeling.templates import (
    LABELS_OFF_MM,
    LabelerModel,
    load_model,
    save_model,
)
from labeler_service.labeling.training import train_subject


def _body_walk(rng, frames: int = 20, markers: int = 12) -> np.ndarray:
    """Three rigid clusters of four markers, each turning its own way, walking at 1 m/s."""
    t = np.arange(frames)[:, None] / 50.0
    out = np.empty((frames, markers, 3))
    for c in range(markers // 4):
        shape = rng.normal(scale=60.0, size=(4, 3))
        for f in range(frames):
            a = 2.0 * t[f, 0] * (c + 1)
            rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            out[f, 4 * c : 4 * c + 4] = shape @ rot.T + [1000.0 * t[f, 0], 300.0 * c, 1000.0]
    return out


def test_labels_shuffled_every_frame_are_refused(rng):
    names = [f"m{i}" for i in range(12)]
    pos = _body_walk(rng)
    template = train_subject("S", names, pos, 50.0)  # the right labels train
    assert len(template.bodies) >= 3
    shuffled = np.stack([p[rng.permutation(12)] for p in pos])
    with pytest.raises(LabelerError, match="labels do not stay on their markers"):
        train_subject("S", names, shuffled, 50.0)


def test_a_model_file_whose_bodies_do_not_hold_is_refused_at_load(rng, tmp_path):
    names = [f"m{i}" for i in range(12)]
    template = train_subject("S", names, _body_walk(rng), 50.0)
    path = tmp_path / "m.json"
    save_model(LabelerModel(rate=50.0, subjects=[template]), path)
    assert load_model(path).subjects[0].name == "S"
    doc = json.loads(path.read_text())
    sub = doc["subjects"][0]
    for body in sub["bodies"]:  # every body link deviating like shuffled labels'
        for k, i in enumerate(body):
            for j in body[k + 1 :]:
                d = sub["D"][i][j]
                sub["A"][i][j] = sub["A"][j][i] = min(d * 0.9, 3 * LABELS_OFF_MM)
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="labels that do not stay on their markers"):
        load_model(path)
