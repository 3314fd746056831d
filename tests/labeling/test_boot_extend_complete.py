"""``Booter.extend`` skips the completion of a subject with every marker placed: it has no
marker to add, and its re-readings without weak markers run only while some marker is
missing (boot_match._complete_weak), so the result is the same, without its cost (1-4 ms a
subject at 6 performers in each extension that has a free point anywhere)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

import labeler_service.labeling.boot as boot_mod
from labeler_service.labeling.boot import Booter


@pytest.fixture(scope="module")
def walk():
    return split_walk(2, 4.0, seed=3, rate=120.0)


def _with_free_point(walk):
    tpl, _, pts, hist = subject_on_its_points(walk)
    shift = np.array([60.0, 0.0, 0.0])  # a tracked free point beside the subject
    pts = np.vstack([pts, pts[0] + shift])
    hist = np.concatenate([hist, hist[:1] + shift], axis=0)
    return tpl, pts, hist


def test_extend_leaves_a_complete_subject_alone(walk, monkeypatch):
    model, _ = walk
    tpl, pts, hist = _with_free_point(walk)
    calls = []
    real = boot_mod._complete_weak

    def spy(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(boot_mod, "_complete_weak", spy)
    labels = np.append(np.arange(tpl.n) + tpl.offset, -1)
    out = Booter(model).extend(pts, hist, labels, [0], np.full(pts.shape[0], 1.0))
    assert np.array_equal(out, labels)
    assert calls == []
    # one marker missing: the completion runs
    labels[3] = -1
    Booter(model).extend(pts, hist, labels, [0], np.full(pts.shape[0], 1.0))
    assert calls == [1]
