"""A label with an empty subject prefix (``:CLAV``) is the bare marker name: split it kept the
empty prefix, joined it lost it, and ``evaluate`` stopped with "model marker 'CLAV' is not a
labeler marker"."""

from __future__ import annotations

import json

import numpy as np

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main


def _body(rng, n: int = 6, frames: int = 80) -> np.ndarray:
    t = np.arange(frames)[:, None, None] / 100.0
    return rng.normal(scale=300.0, size=(1, n, 3)) + np.array([200.0, 0.0, 0.0]) * t


def test_an_empty_subject_prefix_is_dropped_with_a_note(tmp_path, rng, capsys):
    labels = tuple(f":m{i}" for i in range(6))
    path = write_capture(Capture(_body(rng), labels, 100.0), tmp_path / "take.c3d")
    cap = read_capture(path)
    assert cap.labels == tuple(f"take:m{i}" for i in range(6))  # bare names: the file's subject
    assert any("empty subject prefix" in n and "':m0'" in n for n in cap.notes), cap.notes
    assert main(["evaluate", str(path), "--init-frames", "5", "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["methods"]["online"]["accuracy"] > 0.9


def test_one_empty_prefix_among_named_labels(tmp_path, rng):
    labels = ("S:a", ":b", "S:c", "S:d")
    path = write_capture(Capture(_body(rng, n=4), labels, 100.0), tmp_path / "mix.npz")
    cap = read_capture(path)
    assert cap.labels == ("S:a", "b", "S:c", "S:d")
