"""The TRC reader on files other tools (and a hostile tester) write: marker and frame counts
that disagree with the header, rows separated by spaces or commas, the Frame# and Time
columns, rows cut short. Each case reads right with a note, or is a one-line error naming the
file; none loses data silently."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.errors import CaptureFormatError


def _positions(frames: int = 6, markers: int = 3) -> np.ndarray:
    """Distinct, exactly printable coordinates: frame f, marker m, axis a -> f.m a."""
    f, m, a = np.meshgrid(np.arange(frames), np.arange(markers), np.arange(3), indexing="ij")
    return (100.0 * (f + 1) + 10.0 * m + a + 0.5).astype(np.float32)


def _trc(
    path: Path,
    pos: np.ndarray,
    *,
    rate: float = 100.0,
    n_frames: int | None = None,
    n_markers: int | None = None,
    names: list[str] | None = None,
    frames: list[int] | None = None,
    times: list[float] | None = None,
    sep: str = "\t",
) -> Path:
    """A TRC as other tools write one: the header's counts, the marker names, the Frame# and
    Time columns and the separator of the data rows can each be given wrong."""
    f, m = pos.shape[:2]
    names = [f"M{i}" for i in range(m)] if names is None else names
    frames = list(range(1, f + 1)) if frames is None else frames
    times = [i / rate for i in range(f)] if times is None else times
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits",
        f"{rate:g}\t{rate:g}\t{f if n_frames is None else n_frames}\t"
        f"{m if n_markers is None else n_markers}\tmm",
        "Frame#\tTime\t" + "\t".join(f"{x}\t\t" for x in names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(m)),
        "",
    ]
    for i in range(f):
        cells = ["" if np.isnan(v) else f"{v:g}" for v in pos[i].reshape(-1)]
        lines.append(sep.join([str(frames[i]), f"{times[i]:.6f}", *cells]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _edit_line(path: Path, k: int, edit: Callable[[str], str]) -> Path:
    """The TRC at ``path`` with its line ``k`` (0-based) replaced by ``edit(line)``."""
    lines = path.read_text().splitlines()
    lines[k] = edit(lines[k])
    path.write_text("\n".join(lines) + "\n")
    return path


def _said(cap: Capture, *words: str) -> bool:
    return any(all(w in note for w in words) for note in cap.notes)


# ----------------------------------------------------------- 1: marker and frame counts
@pytest.mark.parametrize("declared", [2, 5])
def test_num_markers_unlike_the_columns_reads_every_column_with_a_note(tmp_path, declared) -> None:
    """NumMarkers 2 or 5 over three named columns of data: the third column was dropped
    silently (2), or the file refused ("header says 5 markers")."""
    pos = _positions(markers=3)
    cap = read_capture(_trc(tmp_path / "t.trc", pos, n_markers=declared))
    assert cap.labels == ("t:M0", "t:M1", "t:M2")
    np.testing.assert_array_equal(cap.positions, pos)
    assert _said(cap, f"NumMarkers {declared}", "3 markers"), cap.notes


def test_data_columns_without_a_name_read_as_unlabeled_tracks(tmp_path) -> None:
    pos = _positions(markers=3)
    cap = read_capture(_trc(tmp_path / "t.trc", pos, names=["M0", "M1"]))
    assert cap.labels == ("t:M0", "t:M1", "*2")
    np.testing.assert_array_equal(cap.positions, pos)
    assert _said(cap, "names 2", "3 markers"), cap.notes


@pytest.mark.parametrize(
    ("names", "labels"),
    [
        (["M0", "", "M2"], ("t:M0", "*1", "t:M2")),
        (["", "M1", "M2"], ("*0", "t:M1", "t:M2")),
        (["M0", "", "", "M3"], ("t:M0", "*1", "*2", "t:M3")),
    ],
)
def test_a_blank_marker_name_keeps_the_names_after_it_on_their_columns(
    tmp_path, names, labels
) -> None:
    """A blank name in the tab-separated name row shifted every later name one marker to the
    left (``M2`` read the second marker's data) and left the last column unnamed."""
    pos = _positions(markers=len(names))
    cap = read_capture(_trc(tmp_path / "t.trc", pos, names=names))
    assert cap.labels == labels
    np.testing.assert_array_equal(cap.positions, pos)
    assert _said(cap, "empty label", "unlabeled tracks"), cap.notes


def test_names_in_adjacent_cells_are_read_in_order(tmp_path) -> None:
    """A name row without the empty cells between names (some exporters) is read as before."""
    pos = _positions(markers=3)
    path = _edit_line(_trc(tmp_path / "t.trc", pos), 3, lambda _: "Frame#\tTime\tA\tB\tC")
    assert read_capture(path).labels == ("t:A", "t:B", "t:C")


def test_named_markers_without_data_are_missing_with_a_note(tmp_path) -> None:
    pos = _positions(markers=2)
    cap = read_capture(_trc(tmp_path / "t.trc", pos, names=["M0", "M1", "M2"], n_markers=3))
    assert cap.labels == ("t:M0", "t:M1", "t:M2")
    np.testing.assert_array_equal(cap.positions[:, :2], pos)
    assert np.isnan(cap.positions[:, 2]).all()
    assert _said(cap, "names 3", "2 markers"), cap.notes


def test_num_frames_unlike_the_rows_reads_the_rows_with_a_note(tmp_path) -> None:
    pos = _positions(frames=6)
    for declared in (4, 9):
        cap = read_capture(_trc(tmp_path / "t.trc", pos, n_frames=declared))
        np.testing.assert_array_equal(cap.positions, pos)
        assert _said(cap, f"NumFrames {declared}", "6 data rows"), cap.notes


def test_marker_names_with_spaces_in_a_file_without_tabs_are_refused(tmp_path) -> None:
    pos = _positions(markers=2)
    path = _edit_line(
        _trc(tmp_path / "t.trc", pos, sep=" "), 3, lambda _: "Frame# Time L Knee R Knee"
    )
    with pytest.raises(CaptureFormatError, match=r"t\.trc: the marker-name row names 4"):
        read_capture(path)


# ------------------------------------------------------------------ 2: separators
@pytest.mark.parametrize("sep", [" ", "   ", ",", ", "])
def test_rows_separated_by_spaces_or_commas_read(tmp_path, sep: str) -> None:
    """Every sample read as missing: the rows were split at tabs only."""
    pos = _positions()
    cap = read_capture(_trc(tmp_path / "t.trc", pos, sep=sep))
    np.testing.assert_array_equal(cap.positions, pos)
    assert cap.notes == (), cap.notes


def test_comma_rows_keep_empty_cells_as_missing_samples(tmp_path) -> None:
    pos = _positions()
    pos[2, 1] = np.nan
    cap = read_capture(_trc(tmp_path / "t.trc", pos, sep=","))
    np.testing.assert_array_equal(cap.positions, pos)


def test_a_space_separated_row_short_of_cells_is_refused(tmp_path) -> None:
    """Between spaces no cell is empty: a row short of a sample cannot say which one."""
    pos = _positions()
    path = _trc(tmp_path / "t.trc", pos, sep=" ")
    _edit_line(path, 8, lambda line: " ".join(line.split()[:-3]))  # frame 3 lacks a sample
    with pytest.raises(CaptureFormatError, match=r"t\.trc: line 9: 8 cells .* 11 expected"):
        read_capture(path)


def test_spaces_inside_comma_separated_cells_are_refused(tmp_path) -> None:
    """``1,5 2,5``: decimal commas between spaces, or commas between cells? Neither is read."""
    pos = _positions(frames=2, markers=1)
    path = _edit_line(
        _trc(tmp_path / "t.trc", pos, sep=","), 6, lambda _: "1 0,0 100,5 101,5 102,5"
    )
    with pytest.raises(CaptureFormatError, match=r"t\.trc: line 7: .*commas and spaces"):
        read_capture(path)


# ------------------------------------------------------------------ 3: Frame# and Time
def test_a_data_rate_unlike_the_time_column_is_noted(tmp_path) -> None:
    """DataRate 100 over a Time column 1/120 s apart: read at 100 Hz without a word."""
    pos = _positions(frames=30, markers=1)
    times = [i / 120.0 for i in range(30)]
    cap = read_capture(_trc(tmp_path / "t.trc", pos, rate=100.0, times=times))
    assert cap.rate == 100.0
    assert _said(cap, "DataRate 100", "120 Hz"), cap.notes


def test_times_rounded_to_milliseconds_agree_with_the_rate(tmp_path) -> None:
    pos = _positions(frames=50, markers=1)
    times = [round(i / 240.0, 3) for i in range(50)]
    cap = read_capture(_trc(tmp_path / "t.trc", pos, rate=240.0, times=times))
    assert cap.notes == (), cap.notes


def _without_rates(path: Path) -> Path:
    """The TRC at ``path`` without its DataRate and CameraRate header cells."""
    lines = path.read_text().splitlines()
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    keep = [i for i, k in enumerate(keys) if k not in ("DataRate", "CameraRate")]
    _edit_line(path, 1, lambda _: "\t".join(keys[i] for i in keep))
    return _edit_line(path, 2, lambda _: "\t".join(values[i] for i in keep))


@pytest.mark.parametrize(("rate", "said"), [(0.0, "DataRate 0 Hz"), (1e7, "DataRate 1e+07 Hz")])
def test_a_data_rate_no_capture_has_reads_the_time_column(tmp_path, rate, said) -> None:
    """DataRate 0 was refused as "invalid frame rate 0.0" and 1e7 read as 1e7 Hz (noted):
    both read at the Time column's rate, saying so."""
    pos = _positions(frames=30, markers=2)
    times = [i / 120.0 for i in range(30)]
    cap = read_capture(_trc(tmp_path / "t.trc", pos, rate=rate, times=times))
    assert cap.rate == 120.0
    assert _said(cap, said, "no frame rate", "read at 120 Hz, the Time column"), cap.notes
    np.testing.assert_array_equal(cap.positions, pos)


def test_a_trc_without_data_rate_reads_the_time_column(tmp_path) -> None:
    """No DataRate (nor CameraRate) was "invalid frame rate nan"; times written to 1 ms at
    240 Hz (240.2 Hz over 50 frames) read as 240 Hz."""
    pos = _positions(frames=50, markers=1)
    times = [round(i / 240.0, 3) for i in range(50)]
    cap = read_capture(_without_rates(_trc(tmp_path / "t.trc", pos, times=times)))
    assert cap.rate == 240.0
    assert _said(cap, "no DataRate", "read at 240 Hz, the Time column"), cap.notes


def test_a_trc_with_no_rate_to_read_is_a_clear_error(tmp_path) -> None:
    pos = _positions(frames=6, markers=1)
    path = _without_rates(_trc(tmp_path / "t.trc", pos, times=[0.0] * 6))
    with pytest.raises(CaptureFormatError, match=r"t\.trc: no DataRate .* Time does not increase"):
        read_capture(path)


@pytest.mark.parametrize(
    ("frames", "words"),
    [
        ([1, 2, 4, 3, 5, 6], ("out of order",)),
        ([1, 2, 3, 3, 4, 5], ("repeated",)),
        ([1, 2, 3, 6, 1e9, 1e9 + 1], ("skip", "read as consecutive")),
    ],
)
def test_frame_numbers_out_of_order_repeated_or_skipped_are_noted(tmp_path, frames, words):
    pos = _positions(frames=6, markers=1)
    times = [(f - 1) / 100.0 for f in frames]
    cap = read_capture(_trc(tmp_path / "t.trc", pos, frames=frames, times=times))
    np.testing.assert_array_equal(cap.positions, pos)  # read in file order
    assert _said(cap, "Frame#", *words), cap.notes


def test_frame_numbers_that_skip_frames_place_each_row_at_its_frame(tmp_path, rng, capsys):
    """An exporter that leaves out frames with nothing seen (Frame# 1-3 then 6-8): read as two
    empty frames, so the rows after the gap keep their times (read as consecutive, they came
    0.02 s early, a jump tracked as one frame's motion), and ``label`` writes them back at their
    frame numbers."""
    pos = _positions(frames=6, markers=1)
    frames = [1, 2, 3, 6, 7, 8]
    path = _trc(tmp_path / "t.trc", pos, frames=frames, times=[(f - 1) / 100.0 for f in frames])
    cap = read_capture(path)
    assert cap.n_frames == 8
    np.testing.assert_array_equal(cap.positions[[0, 1, 2, 5, 6, 7]], pos)
    assert np.isnan(cap.positions[3:5]).all()
    assert _said(cap, "Frame#", "skip 2 frames", "no marker seen"), cap.notes


# ------------------------------------------------------------------ 4: rows cut short
def test_a_last_row_cut_mid_line_reads_its_complete_samples_with_a_note(tmp_path) -> None:
    """The file ends inside a number: '-' failed with "could not convert string to float"."""
    pos = _positions(frames=4, markers=2)
    pos[3, 1, 1] = -pos[3, 1, 1]
    path = _trc(tmp_path / "t.trc", pos)
    text = path.read_text()
    path.write_text(text[: text.rindex("\t-") + 2])  # frame 4 ends '...\t-' (no newline)
    cap = read_capture(path)
    np.testing.assert_array_equal(cap.positions[:3], pos[:3])
    np.testing.assert_array_equal(cap.positions[3, 0], pos[3, 0])
    assert np.isnan(cap.positions[3, 1]).all()
    assert _said(cap, "truncated", "line 10"), cap.notes


def test_a_cut_number_is_not_read_as_a_shorter_one(tmp_path) -> None:
    """'402.5' cut to '40' at the end of the file was read as Z = 40."""
    pos = _positions(frames=4, markers=2)
    path = _trc(tmp_path / "t.trc", pos)
    text = path.read_text()
    cut = text.rindex(f"\t{pos[3, 0, 2]:g}") + 3
    path.write_text(text[:cut])
    cap = read_capture(path)
    np.testing.assert_array_equal(cap.positions[:3], pos[:3])
    assert np.isnan(cap.positions[3]).all()
    assert _said(cap, "truncated"), cap.notes


def test_a_last_cell_cut_to_its_sign_reads_as_missing(tmp_path) -> None:
    pos = _positions(frames=4, markers=2)
    pos[3, 1, 2] = -pos[3, 1, 2]
    path = _trc(tmp_path / "t.trc", pos)
    text = path.read_text()
    path.write_text(text[: text.rindex("\t-") + 2])  # every cell there, the last one '-'
    cap = read_capture(path)
    np.testing.assert_array_equal(cap.positions[:, 0], pos[:, 0])
    np.testing.assert_array_equal(cap.positions[:3, 1], pos[:3, 1])
    assert np.isnan(cap.positions[3, 1]).all()
    assert _said(cap, "truncated", "line 10"), cap.notes


def test_rows_short_of_cells_read_as_missing_with_a_note(tmp_path) -> None:
    """Tab rows that stop before their last samples were padded with missing silently."""
    pos = _positions(frames=5, markers=3)
    path = _trc(tmp_path / "t.trc", pos)  # frame 2: marker 1's Z and marker 2 gone
    _edit_line(path, 7, lambda line: "\t".join(line.split("\t")[:-4]))
    cap = read_capture(path)
    expected = pos.copy()
    expected[1, 1:] = np.nan
    np.testing.assert_array_equal(cap.positions, expected)
    assert _said(cap, "1 row", "line 8", "missing"), cap.notes


def test_a_file_cut_in_or_after_its_header_is_a_clear_error(tmp_path) -> None:
    path = _trc(tmp_path / "t.trc", _positions())
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:6]) + "\n")
    with pytest.raises(CaptureFormatError, match=r"t\.trc: .*no frame data.*truncated"):
        read_capture(path)
    path.write_text("\n".join(lines[:3]))
    with pytest.raises(CaptureFormatError, match=r"t\.trc: .*ends inside its header"):
        read_capture(path)
    path.write_text("\n".join(lines[:7])[:-9])  # the first data row cut mid-number
    with pytest.raises(CaptureFormatError, match=r"t\.trc: .*ends inside its first data row"):
        read_capture(path)


# ------------------------------------------------------------------ the writer
@pytest.mark.parametrize("rate", [100.0, 59.94, 360.0])
def test_write_then_read_is_lossless_and_says_nothing(tmp_path, rng, rate: float) -> None:
    pos = (rng.normal(size=(400, 5, 3)) * 500).astype(np.float32)
    pos[3, 1] = np.nan
    pos[10:20, 4] = np.nan
    cap = Capture(pos, tuple(f"S:m{i}" for i in range(5)), rate, source="mem")
    back = read_capture(write_capture(cap, tmp_path / "w.trc"))
    assert back.labels == cap.labels and back.rate == pytest.approx(rate)
    np.testing.assert_array_equal(back.positions, cap.positions)  # repr() of the float32
    assert back.notes == (), back.notes
