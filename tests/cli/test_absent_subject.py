"""A take that lists a subject never seen in it (a Vicon session whose subject list holds
someone not in this capture): ``label``, ``evaluate`` and ``train structure`` stopped with
"subject 'Viktor': no marker is seen in 3 or more of its 50 labeled training frames ...", and
the performers who were there went unlabeled. The absent subject is now left out, with a note
on stderr; a subject seen later in the take still asks for a window that shows him."""

from __future__ import annotations

import json

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, split_label, write_capture
from labeler_service.cli.main import main
from labeler_service.labeling.templates import load_model


@pytest.fixture
def take(rng, tmp_path):
    pos, names = articulated(rng, subjects=3, frames=200)
    pos = np.array(pos, dtype=np.float32)
    gone = [i for i, n in enumerate(names) if split_label(n)[0] == names[-1].split(":")[0]]
    pos[:, gone] = np.nan  # the last subject never appears
    return write_capture(Capture(pos, names, 120.0, source="t"), tmp_path / "take.npz"), names


def test_label_leaves_an_absent_subject_out(take, tmp_path, capsys):
    path, names = take
    absent = split_label(names[-1])[0]
    assert main(["label", str(path), str(tmp_path / "out.c3d")]) == 0
    assert f"subject {absent} is never seen in the take: left out" in capsys.readouterr().err


def test_evaluate_scores_the_subjects_that_are_there(take, capsys):
    path, names = take
    assert main(["evaluate", str(path), "--json"]) == 0
    out = capsys.readouterr()
    assert "is never seen in the take: left out" in out.err
    report = json.loads(out.out.strip().splitlines()[-1])
    assert report["subjects"] == 2 and report["methods"]["online"]["accuracy"] > 0.9


def test_train_structure_leaves_an_absent_subject_out(take, tmp_path, capsys):
    path, names = take
    out = tmp_path / "m.json"
    assert main(["train", "structure", str(path), "--out", str(out)]) == 0
    assert "is never seen in the take: left out" in capsys.readouterr().err
    assert len(load_model(out).subjects) == 2
