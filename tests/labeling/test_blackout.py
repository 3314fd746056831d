"""Frames with no point at all (a camera dropout, a sender's empty frames) say nothing of who
left: the booting labeler holds its subjects over them (``BootConfig.blackout_hold_s``) and
takes their markers up where they return. A helper's 0.1 s dropout in the tennis serve at
50 Hz dropped the performer and booted him again 0.44 s later, nothing labeled in between."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk

from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.testing.frames import ModelFrames

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    return split_walk(2, 6.0, seed=5, rate=RATE)


def _run(model, cap, boot: BootConfig, empty: range):
    """Labels the stream with the frames ``empty`` sent with no point; returns the labeler and
    per frame the markers labeled right and wrong."""
    frames = ModelFrames(cap, model.marker_names, seed=5)
    lab = BootingLabeler(model, RATE, boot=boot)
    right, wrong = [], []
    for k in range(cap.n_frames):
        pts, truth = frames.frame(k)
        if k in empty:
            pts, truth = pts[:0], truth[:0]
        out = lab.process(pts, k / RATE)
        pl = out.point_labels
        right.append(int(np.count_nonzero((pl >= 0) & (pl == truth))))
        wrong.append(int(np.count_nonzero((pl >= 0) & (pl != truth))))
    return lab, np.array(right), np.array(wrong)


def test_a_short_dropout_keeps_every_subject(walk):
    model, cap = walk
    gap = range(150, 164)  # 0.12 s: past drop_after_s (0.1 s)
    lab, right, wrong = _run(model, cap, BootConfig(), gap)
    assert not [e for e in lab.events if e[1] == "drop"], lab.events
    n = right[gap.start - 1]
    assert n >= 60 and right[gap.stop + 2] >= n - 2  # taken up at once, where they return
    assert wrong[gap.stop : gap.stop + 5].sum() <= 2 and wrong[gap.stop + 5 :].sum() == 0
    # without the hold the same dropout dropped both and booted them again
    lab0, right0, _ = _run(model, cap, BootConfig(blackout_hold_s=0.0), gap)
    assert {w for _, k, w in lab0.events if k == "drop"} == {"P1", "P2"}
    assert right0[gap.stop + 2] == 0


def test_a_long_empty_run_drops_the_subjects_once_points_return(walk):
    """Past the hold, the empty frames count as usual: a performer gone for good (here every
    point gone for 0.8 s) is dropped and booted again."""
    model, cap = walk
    lab, right, wrong = _run(model, cap, BootConfig(), range(150, 250))
    drops = [t for t, k, _ in lab.events if k == "drop"]
    assert drops and min(drops) < 250 / RATE
    assert [e for e in lab.events if e[1] == "boot" and e[0] > 250 / RATE]
    assert wrong[-int(RATE) :].sum() == 0


def test_a_blackout_past_the_tracks_boots_everyone_again(walk):
    """Points back after more than ``blackout_reboot_s`` (0.25 s) with none: the tracks cannot
    follow the performers over it, so every subject is dropped ("blackout") and booted again
    at once. A hostile run's 0.3 s of empty frames (two CMU performers 300 mm apart) left a
    pelvis read mirrored and the feet exchanged to the end of the take, the labeled fraction
    high. Within it, a dropout is held (the test above)."""
    model, cap = walk
    gap = range(150, 186)  # 0.3 s
    lab, right, wrong = _run(model, cap, BootConfig(), gap)
    back = [(t, w) for t, k, w in lab.events if k == "blackout"]
    assert {w for _, w in back} == {"P1", "P2"}
    assert all(abs(t - gap.stop / RATE) < 1e-9 for t, _ in back)  # when the points return
    reboot = [t for t, k, _ in lab.events if k == "boot" and t >= gap.stop / RATE]
    assert reboot and max(reboot) < (gap.stop + 0.5 * RATE) / RATE
    assert wrong[gap.stop :].sum() == 0
    # 0.2 s is held
    lab, right, wrong = _run(model, cap, BootConfig(), range(150, 174))
    assert not [e for e in lab.events if e[1] in ("blackout", "drop")], lab.events
    # blackout_reboot_s = 0 turns it off
    lab, _, _ = _run(model, cap, BootConfig(blackout_reboot_s=0.0), gap)
    assert not [e for e in lab.events if e[1] == "blackout"], lab.events
