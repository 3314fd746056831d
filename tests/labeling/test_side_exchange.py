"""A booted subject read with a segment and its mirror twin exchanged (its two feet on each
other's points) gets them back (``BootConfig.verify_exchange``, labeling/boot_verify.py).

A helper's leave-and-return run through the service: a performer who stood still through a
stream's 50 labeled init frames came back, the recovery booted him from the model of those
frames, and his feet were read exchanged in 6 of 10 runs, for good; every distance inside a
foot holds, the pairs from the shins do not. Here the exchange is put in by hand after the
boot, in a simulated walk."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import train

from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.testing.frames import ModelFrames

RATE = 120.0
FEET = ("ANK", "HEE", "TOE", "MT5")
#: a whole leg: thigh, knee, shin and foot (nine pairs, more than every subset takes)
LEG = ("THI", "THA", "KNE", "TIB", "SHN", *FEET)


@pytest.fixture(scope="module")
def walk():
    scene = simulate_scene(2, 5.0, "walk", seed=3, rate=RATE)
    half = scene.n_frames // 2
    return train(scene.frames(0, half)), scene.frames(half, scene.n_frames)


def _run(model, cap, boot: BootConfig, swap_at: int | None, segment: tuple[str, ...] = FEET):
    """Labels the stream; at frame ``swap_at`` P1's feet (or ``segment``'s markers) are put
    on each other's points (as a boot that read them mirrored leaves them). Returns the
    labeler and, per frame, how many of those markers are on their own points and on wrong
    ones."""
    frames = ModelFrames(cap, model.marker_names, seed=3)
    lab = BootingLabeler(model, RATE, boot=boot)
    names = list(model.marker_names)
    pairs = np.array([[names.index(f"P1:L{m}"), names.index(f"P1:R{m}")] for m in segment])
    foot = pairs.ravel()
    right, wrong = [], []
    m = len(names)
    for k in range(cap.n_frames):
        if k == swap_at:
            assert "P1" in lab.active_subjects
            pos, state = np.full((m, 3), np.nan), np.zeros(m, np.uint8)
            lab._exchange(pairs, np.zeros(0, np.int64), pos, state)
        pts, truth = frames.frame(k)
        out = lab.process(pts, k / RATE)
        pl = out.point_labels
        mine = np.isin(pl, foot)
        right.append(int(np.count_nonzero(mine & (pl == truth))))
        wrong.append(int(np.count_nonzero(mine & (pl != truth))))
    return lab, np.array(right), np.array(wrong)


def test_feet_read_exchanged_are_exchanged_back(walk):
    model, cap = walk
    swap = int(1.0 * RATE)
    lab, right, wrong = _run(model, cap, BootConfig(), swap)
    assert wrong[swap] >= 6  # (the exchange put in: the feet on each other's points)
    back = [t for t, kind, who in lab.events if kind == "exchange" and who == "P1"]
    assert back and back[0] - swap / RATE <= 1.0, lab.events
    tail = slice(int((back[0] + 0.2) * RATE), cap.n_frames)
    assert wrong[tail].sum() == 0
    assert right[tail].mean() >= 6
    # a service counts it (mocap_boot_verify_total{event="exchange"}) and logs it
    from labeler_service.service.stream import _verify_events

    assert ("exchange", "P1") in _verify_events(lab, 0)


def test_a_whole_leg_read_exchanged_comes_back_whole(walk):
    """The two legs read on each other's points from the hips down (the still-window boot of
    a returning performer; a boot matrix cell's legs after gaps): off at the hips and where
    the two legs' markers are not mirror images, and no subset of the thigh's pairs reads it
    better. The thigh's body with every segment that hangs from it is one more reading,
    scored on the edges where the two readings differ (the leg's own pairs that hold either
    way would thin its excess below the threshold)."""
    model, cap = walk
    swap = int(1.0 * RATE)
    lab, right, wrong = _run(model, cap, BootConfig(), swap, LEG)
    assert wrong[swap] >= 16
    back = [t for t, kind, who in lab.events if kind == "exchange" and who == "P1"]
    assert back and back[0] - swap / RATE <= 1.0, lab.events
    tail = slice(int((back[-1] + 0.2) * RATE), cap.n_frames)
    assert wrong[tail].sum() == 0
    assert right[tail].mean() >= 17


def test_without_the_check_the_exchange_stays(walk):
    model, cap = walk
    swap = int(1.0 * RATE)
    lab, _, wrong = _run(model, cap, BootConfig(verify_exchange=False), swap)
    assert not [e for e in lab.events if e[1] == "exchange"]
    assert wrong[-int(RATE) :].mean() >= 4  # (for good: what the check removes)


def test_a_walk_read_right_is_never_exchanged(walk):
    model, cap = walk
    lab, _, wrong = _run(model, cap, BootConfig(), None)
    assert not [e for e in lab.events if e[1] == "exchange"], lab.events
    assert wrong.sum() == 0


def test_the_score_takes_the_exchange_that_reads_better_and_only_that(walk):
    """The exchange's score on one frame: the feet read right give no exchange; read on each
    other's points, the four pairs together (not a part of them: one foot's markers would stay
    across) read best."""
    from labeler_service.labeling.boot import Booter
    from labeler_service.labeling.boot_verify import BootVerifier

    model, cap = walk
    verifier = BootVerifier(Booter(model), RATE, BootConfig())
    names = list(model.marker_names)
    col = {n: i for i, n in enumerate(cap.labels)}
    p = np.array([cap.positions[40, col[n]] for n in names], dtype=np.float64)
    observed = np.isfinite(p[:, 0])
    units = [(names.index(f"P1:L{m}"), names.index(f"P1:R{m}")) for m in FEET]
    assert observed[np.ravel(units)].all()
    assert verifier._best_exchange(0, units, observed, p) is None
    crossed = p.copy()
    for a, b in units:
        crossed[[a, b]] = p[[b, a]]
    assert verifier._best_exchange(0, units, observed, crossed) == tuple(units)
