"""Capture writing fails loudly (disk full, unwritable folder, silent ezc3d) and a truncated C3D
is reported, never read as if it were complete."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest

from labeler_service.capture import Capture, check_writable, read_capture, write_capture
from labeler_service.cli.main import main
from labeler_service.errors import CaptureError

DEV_FULL = Path("/dev/full")


def _capture(rng: np.random.Generator, frames: int = 40, markers: int = 5) -> Capture:
    pos = (rng.normal(size=(frames, markers, 3)) * 500).astype(np.float32)
    return Capture(pos, tuple(f"A:m{i}" for i in range(markers)), 120.0, source="mem")


@pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")
@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".npz"])
def test_disk_full_is_an_error_not_a_success(tmp_path, rng, suffix):
    link = tmp_path / f"full{suffix}"
    link.symlink_to(DEV_FULL)
    with pytest.raises(CaptureError, match=r"cannot write: \[Errno 28\]"):
        write_capture(_capture(rng), link)
    assert link.is_symlink() and os.path.realpath(link) == str(DEV_FULL)  # device untouched


def test_silent_c3d_writer_is_caught_and_leaves_nothing(tmp_path, rng, monkeypatch):
    """ezc3d's ``write`` returns normally when it could not write: the size check catches it,
    the target keeps its old content and no temporary file is left."""
    import ezc3d

    out = tmp_path / "o.c3d"
    old = _capture(rng, frames=10)
    write_capture(old, out)
    before = out.read_bytes()

    def short_write(self, path, **kw):  # what a full disk looks like through ezc3d
        Path(path).write_bytes(b"\0" * 600)

    monkeypatch.setattr(ezc3d.c3d, "write", short_write)
    with pytest.raises(CaptureError, match=r"o\.c3d: cannot write: C3D writer stored 600 bytes"):
        write_capture(_capture(rng), out)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.c3d"]


@pytest.mark.parametrize("cut", ["data", "pointer"])
def test_a_c3d_cut_short_after_its_header_is_caught(tmp_path, rng, monkeypatch, cut):
    """A nearly full disk (a hostile run, 64 KB tmpfs): ezc3d's file lacked its last ~1,000
    bytes and its data-start pointer read block 1; the old check (512 header bytes plus the
    frames) passed it, and the file read back misaligned (97 % of the samples wrong), exit 0."""
    import ezc3d

    write = ezc3d.c3d.write

    def cut_write(self, path, **kw):
        write(self, path, **kw)
        raw = bytearray(Path(path).read_bytes())
        if cut == "pointer":
            raw[16:18] = (1).to_bytes(2, "little")  # the data start at block 1, size intact
        else:
            del raw[-1000:]
        Path(path).write_bytes(bytes(raw))

    monkeypatch.setattr(ezc3d.c3d, "write", cut_write)
    out = tmp_path / "o.c3d"
    cap = _capture(rng, frames=200, markers=20)
    with pytest.raises(CaptureError, match=r"o\.c3d: cannot write: C3D writer stored \d+ bytes"):
        write_capture(cap, out)
    assert not out.exists()
    monkeypatch.setattr(ezc3d.c3d, "write", write)
    np.testing.assert_array_equal(read_capture(write_capture(cap, out)).positions, cap.positions)


def test_unwritable_folder_is_an_error(tmp_path, rng):
    target = Path("/proc/self/no-such-dir/o.c3d")
    with pytest.raises(CaptureError, match=r"o\.c3d: cannot write"):
        write_capture(_capture(rng), target)
    with pytest.raises(CaptureError, match=r"o\.c3d: cannot write"):
        check_writable(target)
    folder = tmp_path / "d.c3d"
    folder.mkdir()
    with pytest.raises(CaptureError, match="is a directory"):
        write_capture(_capture(rng), folder)


def test_a_capture_without_frames_is_a_clear_error_as_c3d(tmp_path, rng):
    """A C3D holds at least one frame: ezc3d fails with a ZeroDivisionError, so the writer says
    so first and leaves nothing; TRC and NPZ write an empty capture that reads back."""
    empty = _capture(rng, frames=0)
    with pytest.raises(CaptureError, match=r"e\.c3d: cannot write: a C3D holds at least one"):
        write_capture(empty, tmp_path / "e.c3d")
    assert not list(tmp_path.iterdir())
    for suffix in (".trc", ".npz"):
        back = read_capture(write_capture(empty, tmp_path / f"e{suffix}"))
        assert back.n_frames == 0 and back.labels == empty.labels


def test_write_follows_a_symlink_and_replaces_the_file(tmp_path, rng):
    real = tmp_path / "real.c3d"
    link = tmp_path / "link.c3d"
    write_capture(_capture(rng, frames=5), real)
    link.symlink_to(real)
    write_capture(_capture(rng, frames=12), link)
    assert link.is_symlink()
    assert read_capture(real).n_frames == 12


def test_upper_case_suffix_writes_the_named_file(tmp_path, rng):
    out = tmp_path / "UP.C3D"
    write_capture(_capture(rng), out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["UP.C3D"]
    assert read_capture(out).n_frames == 40


def test_check_writable_refuses_bad_suffix_and_leaves_no_probe(tmp_path):
    with pytest.raises(CaptureError, match="unknown capture format"):
        check_writable(tmp_path / "o.txt")
    assert check_writable(tmp_path / "sub" / "o.c3d") == tmp_path / "sub" / "o.c3d"
    assert check_writable(tmp_path / "plot.png", suffixes=None) == tmp_path / "plot.png"
    assert not (tmp_path / "plot.png").exists()
    # the folders the probe made are gone again (a run that fails later leaves none behind; the
    # writers make them when they write), one that was there stays
    assert not (tmp_path / "sub").exists()
    assert check_writable(tmp_path / "a" / "b" / "o.c3d") and not (tmp_path / "a").exists()
    (tmp_path / "kept").mkdir()
    assert check_writable(tmp_path / "kept" / "x" / "o.npz") and (tmp_path / "kept").is_dir()
    assert list((tmp_path / "kept").iterdir()) == []
    cap = _capture(np.random.default_rng(0), frames=10, markers=2)
    assert write_capture(cap, tmp_path / "a" / "b" / "o.c3d").is_file()


def test_truncated_c3d_is_noted_and_warned(tmp_path, rng, caplog):
    full = tmp_path / "full.c3d"
    write_capture(_capture(rng, frames=600, markers=4), full)
    data = full.read_bytes()
    cut = tmp_path / "cut.c3d"
    data_start = (int.from_bytes(data[16:18], "little") - 1) * 512  # header word 9
    per_frame = 4 * 4 * 4  # 4 markers x (x, y, z, residual) x float32
    cut.write_bytes(data[: data_start + 73 * per_frame + 7])
    with caplog.at_level(logging.WARNING, logger="labeler_service.capture.io"):
        cap = read_capture(cut)
    assert cap.n_frames == 73
    assert "truncated: 73 of 600 frames (the file ends early)" in cap.notes
    assert any("cut.c3d: truncated: 73 of 600 frames" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="labeler_service.capture.io"):
        complete = read_capture(full)
    assert complete.n_frames == 600
    assert not any("truncated" in n for n in complete.notes) and not caplog.records


def test_a_c3d_cut_before_its_first_frame_says_so_in_our_words(tmp_path, rng):
    # ezc3d's own words were "Data::frame method is trying to access the frame 0 while the
    # maximum number of frames is 0."
    full = tmp_path / "full.c3d"
    write_capture(_capture(rng, frames=50, markers=4), full)
    raw = full.read_bytes()
    data_block = int.from_bytes(raw[16:18], "little")  # header word 9: first data block
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(raw[: (data_block - 1) * 512])
    with pytest.raises(CaptureError, match="holds no frame data") as info:
        read_capture(cut)
    assert "Data::frame" not in str(info.value)


def _zero_frame_c3d(path: Path) -> Path:
    """A C3D with markers and no frame, as ezc3d writes one (its Python wrapper cannot: a
    ZeroDivisionError; the C++ writer behind it can): header frames 1 to 1, POINT:FRAMES 0,
    the file ending where frame data would start."""
    import ezc3d

    c = ezc3d.ezc3d.c3d()
    for name in ("A:a", "A:b"):
        c.point(name)
    for group, name, value in (("POINT", "RATE", 100.0), ("POINT", "UNITS", "mm")):
        param = ezc3d.ezc3d.Parameter(name)
        param.set(value)
        c.parameter(group, param)
    c.write(str(path))
    return path


def test_a_c3d_with_no_frames_says_so_not_truncated(tmp_path, caplog, capsys):
    """A hostile run: a valid zero-frame C3D read as "truncated: 0 of 1 frames (the file ends
    early)", with that warning on stderr."""
    path = _zero_frame_c3d(tmp_path / "zero.c3d")
    with caplog.at_level(logging.WARNING, logger="labeler_service.capture.io"):
        cap = read_capture(path)
    assert cap.n_frames == 0 and cap.labels == ("A:a", "A:b") and cap.rate == 100.0
    assert not any("truncated" in n for n in cap.notes) and not caplog.records
    assert main(["info", str(path)]) == 0
    out, err = capsys.readouterr()
    assert "holds no frames" in out and "truncated" not in out + err
    code = main(["label", str(path), str(tmp_path / "out.c3d"), "--no-progress"])
    assert code == 2
    assert capsys.readouterr().err == f"error: {path}: no frames (nothing to label)\n"


def test_check_writable_names_a_file_where_a_folder_should_be(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    for out in (tmp_path / "notes.txt" / "o.c3d", tmp_path / "notes.txt" / "a" / "o.c3d"):
        with pytest.raises(CaptureError, match=r"notes.txt is a file, not a folder"):
            check_writable(out)
    assert (tmp_path / "notes.txt").read_text() == "x"


def _parameter_entry(data: bytes, name: bytes) -> int:
    """Byte offset of the first parameter entry called ``name`` in a C3D's parameter section
    (Intel byte order, as our writer writes)."""
    pos = 512 * (data[0] - 1) + 4
    while True:
        n = abs(int.from_bytes(data[pos : pos + 1], "little", signed=True))
        assert n, f"no entry {name!r}"
        if data[pos + 2 : pos + 2 + n] == name and data[pos + 1] < 128:  # a parameter (id > 0)
            return pos
        pos += 2 + n + int.from_bytes(data[pos + 2 + n : pos + 4 + n], "little", signed=True)


def _damaged(tmp_path: Path, rng, at: int | None, raw: bytes, name: bytes = b"") -> Path:
    good = tmp_path / "good.c3d"
    write_capture(_capture(rng), good)
    data = bytearray(good.read_bytes())
    if at is None:  # the data type byte of parameter ``name``
        at = _parameter_entry(bytes(data), name) + 2 + len(name) + 2
    data[at : at + len(raw)] = raw
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(bytes(data))
    return bad


def test_a_c3d_whose_parameter_pointers_are_damaged_is_refused_before_ezc3d(tmp_path, rng):
    """A helper's hostile run: 8 bytes of 0xFF at offset 520 of a real take (the first
    parameter entry) and ezc3d ended the process with a segmentation fault, no word said."""
    bad = _damaged(tmp_path, rng, 512 + 8, b"\xff" * 8)
    with pytest.raises(
        CaptureError, match=r"bad\.c3d: cannot be read as C3D \(damaged or trunc.*backwards"
    ):
        read_capture(bad)
    many = _damaged(tmp_path, rng, None, b"\xff\x70", b"USED")  # a type -1 with 112 dimensions
    with pytest.raises(CaptureError, match=r"112 dimensions \(C3D knows types -1, 1, 2, 4"):
        read_capture(many)


def test_a_c3d_ezc3d_crashes_on_is_an_error_not_a_dead_process(tmp_path, rng):
    """``POINT:USED`` stored as text (its type byte -1): every structure is sound and ezc3d
    still dies of a segmentation fault; the forked reader sees it first. Run as a user runs
    it (``info``, its own process): the command says so and exits 2, it is not killed."""
    import subprocess
    import sys

    bad = _damaged(tmp_path, rng, None, b"\xff", b"USED")
    run = subprocess.run(
        [sys.executable, "-m", "labeler_service.cli.main", "info", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2, (run.returncode, run.stderr[-500:])
    assert (
        "bad.c3d: cannot be read as C3D (damaged or truncated?): the C3D reader (ezc3d) "
        "crashes on it (SIGSEGV)" in run.stderr
    )
    assert read_capture(tmp_path / "good.c3d").n_frames == 40  # an intact file still reads


def test_the_forked_reader_is_skipped_while_other_threads_run(tmp_path, rng):
    """A fork copies only the calling thread; a lock another thread holds stays held in the
    child. With a thread running, the check forks nothing (the structure check stands)."""
    import threading

    from labeler_service.capture.io import _ezc3d_trouble

    bad = _damaged(tmp_path, rng, None, b"\xff", b"USED")
    assert _ezc3d_trouble(bad) is not None
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert _ezc3d_trouble(bad) is None
    finally:
        stop.set()
        t.join()
