"""Class 8 of issue 12: files and models that are accepted but useless.

An NPZ that declares more than the cap, compresses like a bomb, or whose array header claims
more data than its member holds is refused before anything is decompressed. A model outside
what a human body allows (pair distances, deviations, motion noise, no rigid body) is refused
with the file and field named.
"""

from __future__ import annotations

import copy
import itertools
import json
import zipfile

import numpy as np
import pytest

from labeler_service.capture import read_capture, write_capture
from labeler_service.capture.io import check_npz
from labeler_service.cli.main import main
from labeler_service.errors import CaptureFormatError, ModelError
from labeler_service.labeling.templates import load_model


def _npz(path, members: dict[str, tuple[tuple[int, ...], bytes]], declared_only=False):
    """An NPZ whose members have the given header shape (float32) and raw body bytes."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, (shape, body) in members.items():
            with z.open(name, "w", force_zip64=True) as f:
                header = {"descr": "<f4", "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(f, header)
                f.write(body)
    return path


def test_a_real_npz_still_reads(tmp_path, small_cap):
    p = write_capture(small_cap, tmp_path / "ok.npz")
    assert read_capture(p).n_frames == small_cap.n_frames


def test_an_npz_bomb_is_refused_before_decompressing(tmp_path, capsys):
    p = _npz(tmp_path / "bomb.npz", {"positions.npy": ((8_000_000,), bytes(32_000_000))})
    assert p.stat().st_size < 100_000
    with pytest.raises(CaptureFormatError, match="decompression bomb"):
        read_capture(p)
    assert main(["info", str(p)]) == 2
    assert "bomb.npz" in capsys.readouterr().err


def test_an_npz_declaring_more_than_the_cap_is_refused(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    body = rng.normal(size=300_000).astype(np.float32).tobytes()  # incompressible, 1.2 MB
    p = _npz(tmp_path / "big.npz", {"positions.npy": ((300_000,), body)})
    with pytest.raises(CaptureFormatError, match="cap 1000000"):
        check_npz(p, max_bytes=1_000_000)
    monkeypatch.setenv("MOCAP_MAX_NPZ_BYTES", "1000000")
    with pytest.raises(CaptureFormatError, match="MOCAP_MAX_NPZ_BYTES"):
        read_capture(p)


def test_an_npz_header_claiming_more_than_its_member_is_refused(tmp_path):
    p = _npz(tmp_path / "liar.npz", {"positions.npy": ((10**10, 3), b"\0" * 64)})
    with pytest.raises(CaptureFormatError, match="declares shape"):
        read_capture(p)


def _write(tmp_path, d, name="m.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d))
    return p


def _first_offdiag(D):
    for i, row in enumerate(D):
        for j, v in enumerate(row):
            if i != j and v is not None:
                return i, j
    raise AssertionError("no pair distance")


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda s: s["motion_noise"].__setitem__(0, 1e300), "motion_noise[0]"),
        (lambda s: s["motion_noise"].__setitem__(1, 1e-3), "motion_noise[1]"),
        (lambda s: s.update(bodies=[], shapes=[]), "bodies"),
        ("D", "D["),
        ("D0", "D["),
        ("A", "A["),
    ],
    ids=["noise-huge", "noise-tiny", "no-bodies", "distance-huge", "distance-tiny", "dev-gt-dist"],
)
def test_models_outside_human_ranges_are_refused_naming_file_and_field(
    tmp_path, model_dict, mutate, field
):
    d = copy.deepcopy(model_dict)
    s = d["subjects"][0]
    if isinstance(mutate, str):
        i, j = _first_offdiag(s["D"])
        if mutate == "D":
            s["D"][i][j] = s["D"][j][i] = 5000.0
        elif mutate == "D0":
            s["D"][i][j] = s["D"][j][i] = 0.2
            s["A"][i][j] = s["A"][j][i] = 0.1
        else:
            s["A"][i][j] = s["A"][j][i] = s["D"][i][j] + 1.0
    else:
        mutate(s)
    p = _write(tmp_path, d, "odd_model.json")
    with pytest.raises(ModelError) as info:
        load_model(p)
    msg = str(info.value)
    assert "odd_model.json" in msg and field in msg and "subjects.0" in msg


@pytest.mark.parametrize("rate", [1e-6, 0.5, 20_000.0])
def test_a_model_rate_outside_1_to_10000_hz_is_refused(tmp_path, model_dict, rate):
    """A hostile run's model at 1e-6 Hz was accepted; its stream reported 0.0 Hz."""
    d = copy.deepcopy(model_dict)
    d["rate"] = rate
    with pytest.raises(ModelError, match="rate"):
        load_model(_write(tmp_path, d, "slow_model.json"))


def test_the_trained_model_passes_validation(model_file):
    assert load_model(model_file).subjects


def _thick_quad(s) -> list[int]:
    """The quadruple of one body with the thickest reference shape, ordered so that its signed
    volume is positive there (what ``train structure`` would write)."""
    best, quad = 0.0, None
    for body, shape in zip(s["bodies"], s["shapes"], strict=True):
        for q in itertools.combinations(range(len(body)), 4):
            p = np.asarray(shape, dtype=float)[list(q)]
            det = float(np.linalg.det(p[1:] - p[0]))
            if abs(det) > best:
                a, b, c, d = (body[k] for k in q)
                best, quad = abs(det), [a, b, c, d] if det > 0 else [a, b, d, c]
    assert quad is not None and np.cbrt(best) >= 10.0, "the fixture has a thick 4-marker body"
    return quad


@pytest.mark.parametrize(
    ("mutate", "words"),
    [
        (lambda s, q: s.update(chirality=[[q[0], q[1], q[3], q[2]]]), "is reversed against"),
        (lambda s, q: s.update(chirality=[q, [q[1], q[0], q[2], q[3]]]), "repeat markers"),
        (lambda s, q: s.update(chirality=[q] * 2000), "more than 1024"),
        (lambda s, q: s.update(chirality=[q[:3]]), "4 distinct marker indices"),
        (lambda s, q: s.update(chirality=[[q[0], q[0], q[1], q[2]]]), "4 distinct marker"),
        (lambda s, q: s.update(chirality=[[q[0], q[1], q[2], 999]]), "4 distinct marker"),
    ],
    ids=["reversed", "repeated", "huge", "three", "same-index", "out-of-range"],
)
def test_hostile_chirality_is_refused_naming_file_and_subject(tmp_path, model_dict, mutate, words):
    d = copy.deepcopy(model_dict)
    s = d["subjects"][0]
    q = _thick_quad(s)
    s["chirality"] = [q]
    assert load_model(_write(tmp_path, d, "right.json")).subjects[0].chirality == [q]
    mutate(s, q)
    with pytest.raises(ModelError) as info:
        load_model(_write(tmp_path, d, "odd_model.json"))
    msg = str(info.value)
    assert "odd_model.json" in msg and repr(s["name"]) in msg and words in msg, msg


def test_chirality_on_markers_never_trained_together_is_refused(tmp_path, model_dict):
    d = copy.deepcopy(model_dict)
    s = d["subjects"][0]
    q = _thick_quad(s)
    s["chirality"] = [q]
    i, j = q[0], q[1]
    for key in ("D", "A"):
        s[key][i][j] = s[key][j][i] = None
    with pytest.raises(ModelError, match="has no trained distance"):
        load_model(_write(tmp_path, d, "odd_model.json"))
    s["chirality"] = []  # the same pair without a quadruple on it is a valid model
    assert load_model(_write(tmp_path, d, "ok.json")).subjects


@pytest.mark.parametrize("entry", [[0, 1, 2, 3.5], [[0], 1, 2, 3], "abc"], ids=str)
def test_a_chirality_entry_of_the_wrong_type_names_the_subject(tmp_path, model_dict, entry):
    d = copy.deepcopy(model_dict)
    d["subjects"][0]["chirality"] = [entry]
    with pytest.raises(ModelError) as info:
        load_model(_write(tmp_path, d, "odd_model.json"))
    msg = str(info.value)
    name = d["subjects"][0]["name"]
    assert "odd_model.json" in msg and f"subjects.0 ({name!r}).chirality.0" in msg, msg
