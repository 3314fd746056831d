"""The one grouping of ``subject:marker`` names by subject, and what is built on it."""

from __future__ import annotations

import numpy as np

from labeler_service.capture import Capture, subject_groups
from labeler_service.service.stream import subject_slices

NAMES = ("A:m1", "B:m1", "A:m2", "*3", "m9", "B:*4", "A:m3")


def test_groups_in_order_of_first_appearance_with_and_without_ghosts():
    assert subject_groups(NAMES) == {"A": [0, 2, 6], "B": [1, 5], "": [3, 4]}
    assert subject_groups(NAMES, skip_ghosts=True) == {"A": [0, 2, 6], "B": [1], "": [4]}
    assert subject_groups(()) == {}


def test_capture_subjects_and_columns_use_it():
    cap = Capture(np.zeros((1, len(NAMES), 3), np.float32), NAMES, 100.0)
    assert cap.subjects == ("A", "B", "")
    assert cap.subject_columns("A").tolist() == [0, 2, 6]
    assert cap.subject_columns("B").tolist() == [1]
    assert cap.subject_columns("nobody").dtype == np.intp


def test_model_message_runs_are_contiguous_stretches_in_list_order():
    assert subject_slices(("A:m1", "A:m2", "B:m1")) == (("A", 0, 2), ("B", 2, 1))
    assert subject_slices(("A:m1", "B:m1", "A:m2", "A:m3")) == (
        ("A", 0, 1),
        ("B", 1, 1),
        ("A", 2, 2),
    )
    assert subject_slices(()) == ()
