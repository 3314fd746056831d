"""Counts in messages: ``1 frame``, ``2 frames`` (a new user's pass read "only 1 subjects",
"1 frames" in the CLI, the service log and the notes)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import moving_clusters

from labeler_service.errors import SceneError
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.wording import plural


def test_plural_says_the_count_with_the_noun_in_its_number():
    assert plural(1, "frame") == "1 frame"
    assert plural(0, "frame") == "0 frames"
    assert plural(2, "subject") == "2 subjects"
    assert plural(1, "body", "bodies") == "1 body"
    assert plural(3, "body", "bodies") == "3 bodies"
    assert plural(np.int64(1), "marker") == "1 marker"


def test_leave_on_a_one_subject_scene_says_one_subject(rng):
    cap = moving_clusters(rng, subjects=1, markers=4, frames=240)
    with pytest.raises(SceneError, match=r"the scene has only 1 subject\b"):
        corrupt(cap, CorruptionSpec(leave=2, protect_frames=20, seed=1))
