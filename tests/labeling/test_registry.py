"""The one labeler factory (labeling/registry.py)."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.errors import LabelerError
from labeler_service.labeling.baseline import ClosestPointLabeler
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.registry import make_labeler
from labeler_service.labeling.templates import LabelerModel, save_model
from labeler_service.labeling.training import train_subject

NAMES = ("a:m1", "a:m2", "a:m3", "b:m1", "b:m2", "b:m3")


def test_kinds_aliases_and_config():
    cfg = LabelerConfig()
    online = make_labeler("online", marker_names=NAMES, rate=100.0, config=cfg)
    assert isinstance(online, Labeler) and online.config is cfg
    for kind in ("baseline", "closest-point"):
        lab = make_labeler(kind, marker_names=NAMES, rate=100.0)
        assert isinstance(lab, ClosestPointLabeler) and lab.marker_names == NAMES
        assert np.isnan(lab.body_extent()).all()
        lab.warmup()


def test_unknown_kind_and_empty_marker_set_are_labeler_errors():
    with pytest.raises(LabelerError, match="unknown labeler kind 'nope'.*online, baseline"):
        make_labeler("nope", marker_names=NAMES, rate=100.0)
    for kind in ("online", "baseline"):
        with pytest.raises(LabelerError, match="at least one marker"):
            make_labeler(kind, rate=100.0)


def test_model_object_or_path_gives_the_models_marker_set(rng, tmp_path):
    pos = rng.normal(scale=50.0, size=(1, 4, 3)) + rng.normal(scale=1.0, size=(20, 4, 3))
    model = LabelerModel(
        rate=100.0, subjects=[train_subject("s", ["p", "q", "r", "t"], pos, 100.0)]
    )
    path = tmp_path / "model.json"
    save_model(model, path)
    for source in (model, path, str(path)):
        lab = make_labeler("online", marker_names=("ignored",), rate=100.0, model=source)
        assert lab.marker_names == model.marker_names and lab.model is not None
        base = make_labeler("baseline", rate=100.0, model=source)
        assert base.marker_names == model.marker_names
