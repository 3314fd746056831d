"""A segment read again onto free points (boot_match._free_readings, issue 11): a model that
lacks a marker (its training never showed it) leaves that marker's point free in the stream,
and a plate read mirrored onto it keeps every distance of the plate. Reading the segment's
placed points among themselves (``_readings``) cannot reach the true point the mirror left
free; reading them over the free points can, and the rest of the body says which is right
(tune05 and tune06 with 9 markers dropped from the model: a Plug-in-Gait pelvis with LASI
unknown read RASI on LASI's point, the PSIS exchanged, 255 wrong labels; CMU's pelvis with
LFWT and RBWT unknown read on those two points, the performer never booted)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.walks import simulate_scene, train  # noqa: F401

RATE = 120.0


@pytest.fixture(scope="module")
def partial_model():
    """``(model, partial)``: the model without LASI, and :func:`partial`'s tuple."""
    return _partial()


@pytest.fixture(scope="module")
def partial(partial_model):
    return partial_model[1]


def _partial():
    """P1 of a simulated walk, with a model trained on the first half without LASI: ``(model,
    (tpl, ix, pts, hist, lasi))``: point ``i`` is the template's marker ``i``, point ``lasi`` (the
    last) is LASI's, a point the model cannot name; ``hist`` the points' 12-frame tracks."""
    from labeler_service.capture import split_label
    from labeler_service.labeling.boot import BootConfig
    from labeler_service.labeling.boot_match import _prepare

    cap = simulate_scene(3, 6.0, "walk", seed=7, rate=RATE)
    half = cap.n_frames // 2
    first = cap.frames(0, half)
    keep = [i for i, lab in enumerate(first.labels) if split_label(lab)[1] != "LASI"]
    model = train(first.select(keep))
    second = cap.frames(half, cap.n_frames)
    tpl = _prepare(model, BootConfig())[0]
    names = list(model.subjects[0].markers)
    assert "LASI" not in names
    cols = [second.labels.index(f"P1:{n}") for n in [*names, "LASI"]]
    seen = np.isfinite(second.positions[:, cols, 0]).all(axis=1)
    frame = next(f for f in range(11, second.n_frames) if seen[f - 11 : f + 1].all())
    hist = np.transpose(second.positions[frame - 11 : frame + 1][:, cols], (1, 0, 2))
    hist = np.ascontiguousarray(hist, dtype=float)
    return model, (tpl, {n: i for i, n in enumerate(names)}, hist[:, -1].copy(), hist, len(names))


def test_a_plate_read_mirrored_onto_an_unknown_markers_point_is_read_right(partial):
    from scipy.spatial import cKDTree

    from labeler_service.labeling.boot_match import _free_readings, _readings

    tpl, ix, pts, hist, lasi = partial
    assign = np.arange(tpl.n)
    assign[ix["RASI"]] = lasi  # RASI on LASI's point, the PSIS exchanged: RASI's point free
    assign[ix["RPSI"]], assign[ix["LPSI"]] = ix["LPSI"], ix["RPSI"]
    mirrored = assign.copy()
    _readings(tpl, assign, pts)  # the placed points among themselves: no better reading
    assert np.array_equal(assign, mirrored)
    free = np.zeros(pts.shape[0], dtype=bool)
    free[ix["RASI"]] = True
    _free_readings(tpl, assign, pts, free, cKDTree(pts), hist)
    assert np.array_equal(assign, np.arange(tpl.n))
    assert free[lasi] and not free[ix["RASI"]]


def test_a_move_the_window_does_not_confirm_is_not_made(partial):
    """The same mirrored plate, but RASI's true point tracked in its last frame only: the
    window cannot confirm the move (a coincidence of one frame at a low rate), so the plate is
    left as it was."""
    from scipy.spatial import cKDTree

    from labeler_service.labeling.boot_match import _free_readings

    tpl, ix, pts, hist, lasi = partial
    assign = np.arange(tpl.n)
    assign[ix["RASI"]] = lasi
    assign[ix["RPSI"]], assign[ix["LPSI"]] = ix["LPSI"], ix["RPSI"]
    mirrored = assign.copy()
    free = np.zeros(pts.shape[0], dtype=bool)
    free[ix["RASI"]] = True
    young = hist.copy()
    young[ix["RASI"], :-1] = np.nan
    _free_readings(tpl, assign, pts, free, cKDTree(pts), young)
    assert np.array_equal(assign, mirrored)


def test_a_right_reading_is_left_alone(partial):
    from scipy.spatial import cKDTree

    from labeler_service.labeling.boot_match import _free_readings

    tpl, _, pts, hist, lasi = partial
    assign = np.arange(tpl.n)
    free = np.zeros(pts.shape[0], dtype=bool)
    free[lasi] = True
    _free_readings(tpl, assign, pts, free, cKDTree(pts), hist)
    assert np.array_equal(assign, np.arange(tpl.n))
    assert free[lasi]


def _mirrored(ix: dict[str, int], n: int, lasi: int) -> np.ndarray:
    """The pelvis read mirrored: RASI on LASI's point, the PSIS exchanged (point -> marker)."""
    assign = np.arange(n)
    assign[ix["RASI"]] = lasi
    assign[ix["RPSI"]], assign[ix["LPSI"]] = ix["LPSI"], ix["RPSI"]
    return assign


def test_a_segment_needs_min_placed_markers_to_be_read_again(partial):
    """The pelvis has three placed markers (the model lacks LASI): read again with
    ``min_placed`` 3, left with 4 (a two-point reading keeps one distance, which a plate's two
    diagonals share: the extension asks for three)."""
    from scipy.spatial import cKDTree

    from labeler_service.labeling.boot_match import _free_readings

    tpl, ix, pts, hist, lasi = partial
    for need, right in ((3, True), (4, False)):
        assign = _mirrored(ix, tpl.n, lasi)
        free = np.zeros(pts.shape[0], dtype=bool)
        free[ix["RASI"]] = True
        _free_readings(tpl, assign, pts, free, cKDTree(pts), hist, min_placed=need)
        assert np.array_equal(assign, np.arange(tpl.n)) == right


def test_the_extension_reads_a_booted_subjects_segment_again(partial_model):
    """A booted subject (``checked``) with its pelvis read mirrored onto the point of the marker
    its model lacks is read right by the extension; a subject the stream's labels placed (a
    labeled start) keeps its labels."""
    from labeler_service.labeling.boot import BootConfig, Booter

    model, (tpl, ix, pts, hist, lasi) = partial_model
    booter = Booter(model, BootConfig())
    labels = np.full(pts.shape[0], -1, dtype=np.int64)
    labels[_mirrored(ix, tpl.n, lasi)] = np.arange(tpl.n)  # point -> marker (P1's offset is 0)
    kept = booter.extend(pts, hist, labels, [0])
    assert np.array_equal(kept, labels)
    fixed = booter.extend(pts, hist, labels, [0], checked=[0])
    want = np.full(pts.shape[0], -1, dtype=np.int64)
    want[: tpl.n] = np.arange(tpl.n)
    assert np.array_equal(fixed, want)


def test_a_segment_is_not_read_again_against_a_rest_in_doubt(partial):
    """A doubtful marker outside the segment (its pairs off: a reading already wrong there, a
    pile's performer read on four others' points) leaves the segment as it is: the move is
    judged against the rest of the subject, which is then no reference. A doubtful marker
    inside the segment does not stop it."""
    from scipy.spatial import cKDTree

    from labeler_service.labeling.boot_match import _free_readings

    tpl, ix, pts, hist, lasi = partial
    for inside, right in (("RPSI", True), ("LFHD", False)):
        assign = _mirrored(ix, tpl.n, lasi)
        free = np.zeros(pts.shape[0], dtype=bool)
        free[ix["RASI"]] = True
        doubt = np.zeros(tpl.n, dtype=bool)
        doubt[ix[inside]] = True
        _free_readings(tpl, assign, pts, free, cKDTree(pts), hist, min_placed=3, doubtful=doubt)
        assert np.array_equal(assign, np.arange(tpl.n)) == right
