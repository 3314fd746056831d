"""The model's optional ``twin_witnesses`` field: old model files load without it, entries are
checked with errors that name the subject and the entry."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.errors import ModelError
from labeler_service.labeling.templates import LabelerModel, load_model, make_subject, save_model


def _model() -> LabelerModel:
    shape = np.array([[0, 0, 0], [100, 0, 0], [40, 60, 0], [30, 20, 70]], dtype=float)
    D = np.linalg.norm(shape[:, None] - shape[None], axis=2)
    A = np.full((4, 4), 1.5)
    np.fill_diagonal(A, 0)
    s = make_subject("s", ["a", "b", "c", "d"], D, A, [[0, 1, 2, 3]], [shape], np.ones(4) * 1e5)
    return LabelerModel(rate=120.0, subjects=[s])


def test_a_model_file_without_the_field_loads_with_no_witnesses(tmp_path):
    data = json.loads(_model().model_dump_json())
    del data["subjects"][0]["twin_witnesses"]
    p = tmp_path / "old.json"
    p.write_text(json.dumps(data))
    assert load_model(p).subjects[0].twin_witnesses == []


def test_witnesses_round_trip(tmp_path):
    m = _model()
    s = m.subjects[0].model_validate(
        {**m.subjects[0].model_dump(), "twin_witnesses": [[0, 1, 2, 3]]}
    )
    model = LabelerModel(rate=120.0, subjects=[s])
    save_model(model, tmp_path / "m.json")
    assert load_model(tmp_path / "m.json").subjects[0].twin_witnesses == [[0, 1, 2, 3]]


@pytest.mark.parametrize(
    ("witnesses", "message"),
    [
        ([[0, 1, 2]], r"twin witness \[0, 1, 2\] must be 4 distinct"),
        ([[0, 1, 2, 2]], "must be 4 distinct"),
        ([[0, 1, 2, 9]], "must be 4 distinct"),
        ([[0, 1, 2, 3], [1, 0, 3, 2]], "repeats another"),
        ([[0, 1, 2, 3]] * 1025, "more than 1024"),
    ],
)
def test_bad_witnesses_raise_model_error_naming_the_subject(tmp_path, witnesses, message):
    data = json.loads(_model().model_dump_json())
    data["subjects"][0]["twin_witnesses"] = witnesses
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ModelError, match=message) as err:
        load_model(p)
    assert "'s'" in str(err.value)
