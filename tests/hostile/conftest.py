"""Fixtures of the hostile-input suite: a small capture as C3D/NPZ and a trained model file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic import moving_clusters

from labeler_service.capture import write_capture
from labeler_service.labeling.templates import LabelerModel, save_model
from labeler_service.labeling.training import train_subject


@pytest.fixture
def small_cap():
    return moving_clusters(np.random.default_rng(5), subjects=2, markers=6, frames=60)


@pytest.fixture
def ok_c3d(tmp_path, small_cap):
    return write_capture(small_cap, tmp_path / "ok.c3d")


@pytest.fixture
def bad_label_c3d(tmp_path, ok_c3d):
    """The same C3D with one label byte replaced by 0xFF (not UTF-8)."""
    b = ok_c3d.read_bytes()
    i = b.find(b"S0:m1")
    assert i > 0
    p = tmp_path / "bad_label.c3d"
    p.write_bytes(b[: i + 3] + b"\xff" + b[i + 4 :])
    return p


@pytest.fixture
def model_dict(small_cap):
    subjects = []
    for s in small_cap.subjects:
        cols = small_cap.subject_columns(s)
        markers = [small_cap.labels[c].split(":")[1] for c in cols]
        subjects.append(train_subject(s, markers, small_cap.positions[:, cols], small_cap.rate))
    return json.loads(LabelerModel(rate=small_cap.rate, subjects=subjects).model_dump_json())


@pytest.fixture
def model_file(tmp_path, model_dict):
    p = tmp_path / "model.json"
    save_model(LabelerModel.model_validate(model_dict), p)
    return p
