"""The versioned template schema: round trip and clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.errors import ModelError
from labeler_service.labeling.templates import LabelerModel, load_model, make_subject, save_model


def _subject(name="s"):
    D = np.array([[0, 100, 120], [100, 0, 80], [120, 80, 0]], dtype=float)
    A = np.full((3, 3), 1.5)
    np.fill_diagonal(A, 0)
    A[0, 2] = A[2, 0] = np.nan  # never seen together
    shape = np.array([[0, 0, 0], [100, 0, 0], [40, 60, 0]], dtype=float)
    return make_subject(name, ["a", "b", "c"], D, A, [[0, 1, 2]], [shape], np.ones(3) * 1e5)


def test_round_trip(tmp_path):
    model = LabelerModel(rate=120.0, subjects=[_subject("s1"), _subject("s2")])
    p = tmp_path / "m.json"
    save_model(model, p)
    back = load_model(p)
    assert back == model
    assert back.marker_names == ("s1:a", "s1:b", "s1:c", "s2:a", "s2:b", "s2:c")
    assert np.isnan(back.subjects[0].A_array()[0, 2])
    assert json.loads(p.read_text())["version"] == 1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(version=2), "unsupported model version 2"),
        (lambda d: d["subjects"][0].update(bodies=[[0, 1, 7]]), "out-of-range"),
        (lambda d: d["subjects"][0].update(motion_noise=[1.0, -1.0, 1.0]), "motion_noise"),
        (lambda d: d["subjects"][0].update(D=[[0.0]]), "D must be 3x3"),
        (lambda d: d["subjects"][0].update(shapes=[]), "1 bodies but 0 shapes"),
        (lambda d: d.update(rate=0), "rate"),
        (lambda d: d["subjects"].append(d["subjects"][0]), "duplicate subject"),
        # names a labeled capture would not give back (a hand-edited model)
        (lambda d: d["subjects"][0].update(name="Der:rick"), "would read back as subject 'Der'"),
        (lambda d: d["subjects"][0].update(markers=["a", "*0", "c"]), "unlabeled track"),
        (lambda d: d["subjects"][0].update(markers=["a", " ", "c"]), "is empty"),
        (lambda d: d["subjects"][0].update(markers=["a", "b\nc", "c"]), "control character"),
        (lambda d: d["subjects"][0].update(name="Der\trick"), "subject name 'Der\\\\trick'"),
    ],
)
def test_invalid_models_raise_model_error(tmp_path, edit, message):
    model = LabelerModel(rate=120.0, subjects=[_subject()])
    data = json.loads(model.model_dump_json())
    edit(data)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ModelError, match=message):
        load_model(p)


def test_unreadable_files(tmp_path):
    with pytest.raises(ModelError, match="cannot read"):
        load_model(tmp_path / "missing.json")
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(ModelError, match="not JSON"):
        load_model(p)
    p.write_text("[1, 2]")
    with pytest.raises(ModelError, match="not a JSON object"):
        load_model(p)


def test_make_subject_names_the_subject():
    with pytest.raises(ModelError, match="subject 'bad'"):
        make_subject("bad", ["a", "a"], np.zeros((2, 2)), np.zeros((2, 2)), [], [], np.ones(2))


def test_model_errors_carry_no_pydantic_prefix(tmp_path):
    """'invalid model: Value error, duplicate subject names': pydantic's prefix, not ours."""
    with pytest.raises(ModelError) as err:
        make_subject("bad", ["a", "a"], np.zeros((2, 2)), np.zeros((2, 2)), [], [], np.ones(2))
    assert "Value error" not in str(err.value)
    path = tmp_path / "m.json"
    save_model(LabelerModel(rate=120.0, subjects=[_subject("s")]), path)
    import json

    raw = json.loads(path.read_text())
    raw["subjects"].append(raw["subjects"][0])
    path.write_text(json.dumps(raw))
    with pytest.raises(ModelError, match="duplicate subject names") as err:
        load_model(path)
    assert "Value error" not in str(err.value)


def test_a_file_that_is_no_model_says_what_a_model_is(tmp_path):
    """``--model take.c3d`` said "not UTF-8 text (byte 14)", a JSON of something else
    "unsupported model version None": neither named the mistake nor the fix."""
    take = tmp_path / "take.c3d"
    take.write_bytes(b"\x02\x50" + bytes(range(256)))
    with pytest.raises(ModelError) as err:
        load_model(take)
    assert "named as a capture, not a subject model" in str(err.value)
    assert f"mocap-labeler train structure {take} --out MODEL.json" in str(err.value)
    other = tmp_path / "settings.json"
    # a shoulder skeleton (``train shoulder``) has a version too: it said "rate: Field required"
    skeleton = '{"format": "mocap-labeler/shoulder-skeleton", "version": 1, "markers": []}'
    for text in ('{"udp": {"port": 9870}}', "[1, 2]", "{not json", skeleton):
        other.write_text(text)
        with pytest.raises(ModelError) as err:
            load_model(other)
        assert "not a subject model; a subject model is the JSON file" in str(err.value)
        assert "train structure TAKE... --out MODEL.json" in str(err.value)
