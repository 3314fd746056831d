"""A symmetric segment read the other way round (boot_match._window_symmetries): a hugging
performer's head plate booted turned half round (front markers on the back ones' points) kept
that reading for the whole 10 s of ``bench latency --start boot``: every pair of the plate
holds, so neither the pair exchange nor the re-verification's left-right exchanges saw it.
The extension reads it back from the rest of the subject along the window."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import split_walk, subject_on_its_points

from labeler_service.labeling.boot_match import _plate_symmetries, _window_symmetries

RATE = 120.0
HEAD = ("LFHD", "RFHD", "LBHD", "RBHD")


@pytest.fixture(scope="module")
def walker():
    tpl, names, pts, hist = subject_on_its_points(split_walk(3, 6.0, seed=11, rate=RATE))
    return tpl, {n: i for i, n in enumerate(names)}, hist


def _read(tpl, ix, pairs: dict[str, str]) -> np.ndarray:
    assign = np.arange(tpl.n)
    for a, b in pairs.items():
        assign[ix[a]] = ix[b]
    return assign


def test_the_head_plate_is_found_symmetric(walker):
    """Its half turn keeps every trained distance of the plate (the template's own bodies
    cannot tell), whether the trainer made it one body or two triangles."""
    tpl, ix, hist = walker
    head = sorted(ix[n] for n in HEAD)
    turns = [p for mk, perms in tpl.symmetric if mk.tolist() == head for p in perms]
    half = np.array([head.index(ix[n]) for n in ("RBHD", "LBHD", "RFHD", "LFHD")])
    assert any(np.array_equal(p, half) for p in turns)
    # (the plate turned over keeps its distances too: the chirality refuses that reading)
    assert len(turns) == 3
    assert len(_plate_symmetries(tpl)) == len(tpl.symmetric)


def test_a_head_plate_turned_half_round_is_read_back(walker):
    tpl, ix, hist = walker
    turned = _read(tpl, ix, {"LFHD": "RBHD", "RBHD": "LFHD", "RFHD": "LBHD", "LBHD": "RFHD"})
    out = _window_symmetries(tpl, turned, hist)
    assert np.array_equal(out, np.arange(tpl.n))


def test_a_right_reading_is_left_as_it_is(walker):
    tpl, ix, hist = walker
    assign = np.arange(tpl.n)
    assert _window_symmetries(tpl, assign, hist) is assign


def test_evidence_of_fewer_than_half_the_window_is_not_acted_on(walker):
    tpl, ix, hist = walker
    turned = _read(tpl, ix, {"LFHD": "RBHD", "RBHD": "LFHD", "RFHD": "LBHD", "LBHD": "RFHD"})
    short = hist.copy()
    w = short.shape[1]
    short[ix["LBHD"], : w - w // 2 + 1] = np.nan
    assert _window_symmetries(tpl, turned, short) is turned


def test_a_plate_with_a_marker_missing_is_left_alone(walker):
    tpl, ix, hist = walker
    turned = _read(tpl, ix, {"LFHD": "RBHD", "RBHD": "LFHD", "RFHD": "LBHD", "LBHD": "RFHD"})
    turned[ix["LBHD"]] = -1
    assert _window_symmetries(tpl, turned, hist) is turned


def _segment(points: np.ndarray):
    """A template-like object of one segment with these reference points (tolerance 3 mm)."""
    from types import SimpleNamespace

    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    return SimpleNamespace(segments=[np.arange(points.shape[0])], D=d, tol=np.full(d.shape, 3.0))


def test_a_square_plate_turned_a_quarter_is_not_a_symmetry():
    """A head yawed 90 degrees reads its square plate a quarter round as well as right (a
    dancer's, tune23 ``rate``): only half turns, which no joint makes, are offered."""
    square = np.array([[0.0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]])
    turns = [p.tolist() for _, perms in _plate_symmetries(_segment(square)) for p in perms]
    assert [2, 3, 0, 1] in turns  # half round
    assert [1, 2, 3, 0] not in turns and [3, 0, 1, 2] not in turns  # a quarter either way


def test_a_turn_about_markers_on_its_axis_is_not_a_symmetry():
    """A forearm segment turned about itself (elbow and finger on the axis, the wrist bar's
    two markers exchanged) is a pronation, not a misreading."""
    arm = np.array([[0.0, 0, 0], [150, 0, 0], [250, 30, 0], [250, -30, 0], [320, 0, 0]])
    assert _plate_symmetries(_segment(arm)) == []
