"""``evaluate``'s labeled start on a take whose labels do not all name their subject: the window
model names every subject (a bare ``LASI`` came back as ``subject:LASI``), so its markers were
never scored right; ``auto`` falls back to the labeler trained in place and ``model`` says why
it cannot run."""

from __future__ import annotations

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture
from labeler_service.errors import MocapError
from labeler_service.evaluation.scoring import evaluate


@pytest.fixture
def mixed(rng):
    """Two subjects: the first with bare marker names, the second ``s1:...``."""
    pos, names = articulated(rng, subjects=2, frames=160)
    bare = [n.split(":", 1)[1] if n.startswith(names[0].split(":")[0] + ":") else n for n in names]
    assert any(":" not in n for n in bare) and any(":" in n for n in bare)
    return Capture(pos, tuple(bare), 120.0, source="mixed")


def test_auto_runs_the_labeler_when_labels_are_bare(mixed):
    report, _ = evaluate(mixed, methods=["online"], init_frames=40)
    assert report["settings"]["labeled_start"] == "labeler"
    assert report["settings"]["labeled_start_asked"] == "auto"
    assert any("bare marker names" in n for n in report["notes"])
    assert report["accuracy"] >= 0.99


def test_model_start_refuses_bare_labels(mixed):
    with pytest.raises(MocapError, match="without a subject prefix"):
        evaluate(mixed, methods=["online"], init_frames=40, labeled_start="model")
