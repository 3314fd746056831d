"""A subject named with fewer markers than the presence check needs is never labeled: the
report says so in its notes instead of scoring it 0 in silence; the label command says it on
stderr."""

from __future__ import annotations

import numpy as np
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main
from labeler_service.evaluation.scoring import evaluate
from labeler_service.labeling.registry import thin_subjects


def _with_pair(rng) -> Capture:
    """One articulated subject and a 2-marker prop 1.5 m beside it."""
    pos, names = articulated(rng, subjects=1, frames=120)
    prop = pos[:, :2] + np.array([1500.0, 0.0, 0.0], dtype=np.float32)
    return Capture(
        np.concatenate([pos, prop], axis=1), (*names, "Prop:a", "Prop:b"), 120.0, source="prop"
    )


def test_thin_subjects_names_them_and_respects_the_setting() -> None:
    labels = ["A:x", "A:y", "A:z", "B:p", "B:q", "*3", "*4", "*5"]
    (note,) = thin_subjects(labels)
    assert "subject B has 2 markers" in note and "fewer than the 3" in note
    assert thin_subjects(labels, min_markers=2) == []
    assert thin_subjects(labels, min_markers=0) == []
    assert len(thin_subjects(labels, min_markers=4)) == 2


def test_evaluate_and_label_say_a_subject_has_too_few_markers(rng, tmp_path, capsys) -> None:
    cap = _with_pair(rng)
    report, _ = evaluate(cap, methods=["online"], init_frames=40)
    assert any("subject Prop has 2 markers" in n for n in report["notes"])
    assert sum("markers, fewer than" in n for n in report["notes"]) == 1  # not the performer
    path = tmp_path / "prop.npz"
    write_capture(cap, path)
    assert main(["label", str(path), str(tmp_path / "out.npz"), "--init-frames", "40"]) == 0
    assert "subject Prop has 2 markers" in capsys.readouterr().err
