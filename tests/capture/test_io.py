"""Capture I/O: round trips, missing-sample rules, real files, clear errors."""

from __future__ import annotations

import io
import json
import os
import tracemalloc
import zipfile

import numpy as np
import pytest

from labeler_service.capture import (
    Capture,
    is_ghost,
    join_label,
    read_capture,
    split_label,
    write_capture,
)
from labeler_service.capture.io import check_npz
from labeler_service.cli.main import main
from labeler_service.errors import CaptureError, CaptureFormatError

REAL_FILES = [
    "clusters_73markers_100hz.c3d",
    "cmu_01_01_playground.c3d",
    "cmu_02_05_expressions.c3d",
    "kneel_to_prone_62markers_240hz.c3d",
    "raw_unlabeled_kneel_to_run_240hz.c3d",
    "shoulder_upper_body_with_box_100hz.c3d",
    "two_players_shifted_copy_50hz.c3d",
]


def _capture(rng: np.random.Generator, frames: int = 15, markers: int = 7) -> Capture:
    pos = (rng.normal(size=(frames, markers, 3)) * 500).astype(np.float32)
    pos[2, 1] = np.nan
    pos[5:9, 3] = np.nan
    labels = tuple(f"A:m{i}" for i in range(markers - 2)) + ("B:x", "*0")
    return Capture(pos, labels, 120.0, source="mem")


def test_labels_split_and_ghosts() -> None:
    assert split_label("subj:LASI") == ("subj", "LASI")
    assert split_label("LASI") == (None, "LASI")
    for label in ("subj:LASI", "LASI", "a:b:c"):
        assert join_label(*split_label(label)) == label
    assert join_label("", "LASI") == "LASI"
    assert is_ghost("*12") and is_ghost("s:*3")
    assert not is_ghost("*x") and not is_ghost("LASI")


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".npz"])
def test_round_trip(tmp_path, rng, suffix: str) -> None:
    cap = _capture(rng)
    back = read_capture(write_capture(cap, tmp_path / f"x{suffix}"))
    assert back.labels == cap.labels
    assert back.rate == pytest.approx(cap.rate)
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(cap.positions))
    np.testing.assert_allclose(back.positions, cap.positions, rtol=1e-6, atol=1e-3)


def test_a_trc_header_names_the_file_not_its_temporary_name(tmp_path, rng) -> None:
    write_capture(_capture(rng), tmp_path / "walk.trc")
    first = (tmp_path / "walk.trc").read_text().splitlines()[0]
    assert first == "PathFileType\t4\t(X/Y/Z)\twalk.trc", first


@pytest.mark.parametrize("name", ["A:R\tASI", "A:R\nASI", "A:R\rASI"])
def test_a_trc_refuses_a_marker_name_it_cannot_hold(tmp_path, rng, name: str) -> None:
    """A tab or a line break in a name shifted every later column of the TRC, exit 0."""
    cap = _capture(rng)
    cap = Capture(cap.positions, (name,) + cap.labels[1:], cap.rate)
    with pytest.raises(CaptureError, match="a TRC cannot hold"):
        write_capture(cap, tmp_path / "x.trc")
    assert not (tmp_path / "x.trc").exists()
    back = read_capture(write_capture(cap, tmp_path / "x.npz"))  # a format that can
    assert back.labels == cap.labels


def test_c3d_round_trip_over_255_markers(tmp_path, rng) -> None:
    pos = rng.normal(size=(4, 300, 3)).astype(np.float32)
    cap = Capture(pos, tuple(f"s{i // 50}:m{i}" for i in range(300)), 60.0)
    back = read_capture(write_capture(cap, tmp_path / "big.c3d"))
    assert back.labels == cap.labels
    np.testing.assert_allclose(back.positions, pos, atol=1e-4)


def test_zero_samples_become_missing_and_metres_convert(tmp_path) -> None:
    pos = np.ones((3, 2, 3), dtype=np.float32)
    pos[1, 0] = 0.0
    (tmp_path / "m.trc").write_text(
        "PathFileType\t4\t(X/Y/Z)\tm.trc\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
        "100\t100\t3\t2\tm\n"
        "Frame#\tTime\tA\t\t\tB\n"
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n\n"
        "1\t0\t1\t2\t3\t0\t0\t0\n"
        "2\t0.01\t1\t2\t3\t\t\t\n"
        "3\t0.02\t1\t2\t3\t4\t5\t6\n"
    )
    cap = read_capture(tmp_path / "m.trc")
    assert cap.labels == ("m:A", "m:B")  # no prefix in the file: one subject named after stem
    np.testing.assert_allclose(cap.positions[0, 0], [1000, 2000, 3000])
    assert np.isnan(cap.positions[0, 1]).all() and np.isnan(cap.positions[1, 1]).all()
    assert any("m to mm" in n for n in cap.notes)


def test_y_up_rotation(tmp_path) -> None:
    pos = np.array([[[1.0, 2.0, 3.0]]], dtype=np.float32)
    p = write_capture(Capture(pos, ("s:a",), 100.0), tmp_path / "y.npz")
    cap = read_capture(p, up="y")
    np.testing.assert_allclose(cap.positions[0, 0], [1.0, -3.0, 2.0])
    assert "rotated from Y up to Z up" in cap.notes


def test_bad_files_raise_clear_errors(tmp_path) -> None:
    with pytest.raises(CaptureError, match="no such file"):
        read_capture(tmp_path / "none.c3d")
    (tmp_path / "takes.c3d").mkdir()  # a folder was called "no such file"
    with pytest.raises(CaptureError, match="takes.c3d: is a folder, not a capture file"):
        read_capture(tmp_path / "takes.c3d")
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"not a c3d")
    with pytest.raises(CaptureFormatError, match="bad.c3d"):
        read_capture(bad)
    other = tmp_path / "x.csv"
    other.write_text("1,2,3")
    with pytest.raises(CaptureError, match="unknown capture format"):
        read_capture(other)
    assert main(["info", str(bad)]) == 2


def test_gaps_and_empty_columns(rng) -> None:
    cap = _capture(rng)
    assert (3, 5, 4) in cap.gaps() and (1, 2, 1) in cap.gaps()
    pos = cap.positions.copy()
    pos[:, 0] = np.nan
    cap2 = cap.with_positions(pos)
    assert cap2.empty_columns().tolist() == [0]
    assert cap2.without_empty().n_markers == cap.n_markers - 1
    assert cap.subjects == ("A", "B")
    # The ghost column (*0) does not count as missing data.
    named = cap.visible[:, :-1]
    assert cap.missing_fraction == pytest.approx(1 - named.mean())


@pytest.mark.realdata
@pytest.mark.parametrize("name", REAL_FILES)
def test_every_real_file_loads(real_path, name: str) -> None:
    cap = read_capture(real_path(name))
    assert cap.n_frames > 100 and cap.n_markers > 20
    assert np.isfinite(cap.positions[cap.visible]).all()
    # No (0,0,0) sample survives as a position.
    assert not np.all(cap.positions == 0, axis=2).any()
    assert main(["info", str(real_path(name)), "--json"]) == 0


@pytest.mark.realdata
def test_real_special_cases(real_path) -> None:
    cmu = read_capture(real_path("cmu_01_01_playground.c3d"))
    assert "cmu_01_01_playground:RBAC-1" in cmu.labels
    dup = cmu.labels.index("cmu_01_01_playground:RBAC-1")
    assert cmu.visible[:, dup].mean() < 0.01  # the near-empty duplicate loads, flagged by gaps
    raw = read_capture(real_path("raw_unlabeled_kneel_to_run_240hz.c3d"))
    assert raw.ghost_mask.all() and raw.subjects == ()
    two = read_capture(real_path("two_players_shifted_copy_50hz.c3d"))
    assert two.subjects == ("Derrick", "Viktor")
    assert any("m to mm" in n for n in two.notes)
    # Metres were converted: a body is more than 1000 mm tall.
    z = two.positions[..., 2]
    assert np.nanmax(z) - np.nanmin(z) > 1000


def test_read_segment_reads_a_frame_range_with_clear_errors(tmp_path, rng) -> None:
    from labeler_service.capture import read_segment

    cap = _capture(rng, frames=30)
    path = tmp_path / "take.npz"
    write_capture(cap, path)
    whole = read_segment(path)
    assert whole.n_frames == 30
    seg = read_segment(f"{path}:10:25")
    assert seg.n_frames == 15 and seg.rate == cap.rate and seg.labels == whole.labels
    np.testing.assert_array_equal(seg.positions, whole.positions[10:25])
    assert any("frames 10-25" in n for n in seg.notes)
    assert read_segment(f"{path}:20").n_frames == 10
    # a file whose name holds colons is read whole
    odd = tmp_path / "a:1:2.npz"
    write_capture(cap, odd)
    assert read_segment(odd).n_frames == 30
    for bad, why in (
        (f"{path}:25:10", "start < stop"),
        (f"{path}:30", "past the capture's 30 frames"),
        (f"{path}:0:99", "stop 99 is past"),
        (f"{path}:x", "bad frame range 'x'"),
        (f"{path}:-5", "bad frame range '-5'"),
        (f"{path}:3:x", "bad frame range '3:x'"),
        (f"{tmp_path / 'none.npz'}:3", "none.npz: no such file"),
        # said "take.npz:10: no such file"
        (f"{path}:10:20:30", "too many ':' fields after .*take.npz: expected FILE"),
    ):
        with pytest.raises(CaptureError, match=why):
            read_segment(bad)
    fifo = tmp_path / "live.c3d"
    os.mkfifo(fifo)  # said "live.c3d: no such file"
    with pytest.raises(CaptureError, match="live.c3d: not a regular file"):
        read_segment(fifo)


def test_label_evaluate_and_replay_take_a_frame_range(tmp_path, capsys) -> None:
    """Train on one segment of a take, label and score another: ``IN[:start[:stop]]``."""
    import json

    from labeler_service.scenes.simulate import simulate_scene

    cap = simulate_scene(2, 4.0, "walk", seed=1, rate=60.0)
    path = tmp_path / "walk.npz"
    write_capture(cap, path)
    model = tmp_path / "m.json"
    assert main(["train", "structure", f"{path}:0:120", "--out", str(model)]) == 0
    out = tmp_path / "out.npz"
    args = ["label", f"{path}:120:240", str(out), "--model", str(model), "--json"]
    assert main([*args, "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 120 and read_capture(out).n_frames == 120
    args = ["evaluate", f"{path}:120:240", "--model", str(model), "--init-frames", "0"]
    assert main([*args, "--json", "--no-progress"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["frames"] == 120
    assert report["truth"] == f"{path}:120:240" and report["settings"]["model_file"] == str(model)
    assert main(["info", f"{path}:120:240", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames"] == 120
    assert main(["label", f"{path}:500", str(out), "--model", str(model)]) == 2
    assert "past the capture's 240 frames" in capsys.readouterr().err


def test_c3d_carries_the_subjects_group(tmp_path, rng) -> None:
    """Tools that list subjects from the C3D SUBJECTS group (Vicon's convention) see them."""
    import ezc3d

    cap = _capture(rng)
    write_capture(cap, tmp_path / "s.c3d")
    p = ezc3d.c3d(str(tmp_path / "s.c3d"))["parameters"]
    assert p["SUBJECTS"]["NAMES"]["value"] == ["A", "B"]
    assert p["SUBJECTS"]["LABEL_PREFIXES"]["value"] == ["A:", "B:"]
    assert list(p["SUBJECTS"]["USED"]["value"]) == [2]
    back = read_capture(tmp_path / "s.c3d")
    assert back.labels == cap.labels and back.subjects == ("A", "B")


def test_repeated_labels_are_renamed_and_a_repeated_ghost_stays_a_ghost(tmp_path) -> None:
    """A file may repeat a name: a marker gets ``~k``, an unlabeled ``*N`` a fresh ``*N``
    (read as a marker, it would be scored and trained as one)."""
    path = tmp_path / "dup.npz"
    pos = np.arange(2 * 6 * 3, dtype=np.float32).reshape(2, 6, 3) + 1.0
    labels = ["S:a", "S:a", "*3", "*3", "", "S:b"]
    np.savez(path, positions=pos, labels=np.asarray(labels, dtype=str), rate=np.float64(100.0))
    cap = read_capture(path)
    assert cap.labels[:2] == ("S:a", "S:a~1") and cap.labels[5] == "S:b"
    assert all(is_ghost(x) for x in cap.labels[2:5]) and len(set(cap.labels)) == 6
    assert any("duplicate label '*3' renamed" in n for n in cap.notes)
    # the empty label is said too: a column read as an unlabeled track, not a marker
    assert any("1 empty label read as unlabeled tracks *N" in n for n in cap.notes), cap.notes


def test_points_a_processing_model_wrote_are_not_markers(tmp_path, rng) -> None:
    """A processed Vicon C3D stores the model's outputs (angles, forces, user outputs such as
    EMG) and virtual markers (joint centres) as points beside the markers; the POINT group
    lists them. No camera sees them: they are left out, with a note naming them (a real jump
    take scored 0.74 with them read as markers, 0.997 without)."""
    import ezc3d

    labels = ("P:LASI", "P:RASI", "P:LKNE", "*3", "P:LKneeAngles", "P:LHJC", "USERMO0", "F1")
    pos = (rng.normal(size=(12, len(labels), 3)) * 300).astype(np.float32)
    write_capture(Capture(pos, labels, 100.0, source="mem"), tmp_path / "m.c3d")
    c = ezc3d.c3d(str(tmp_path / "m.c3d"))
    c.add_parameter("POINT", "ANGLES", ["P:LKneeAngles"])
    c.add_parameter("POINT", "MODELED_MARKERS", ["P:LHJC"])
    c.add_parameter("POINT", "USERMOS", ["USERMO0"])
    c.add_parameter("POINT", "FORCE_OUTPUTS", ["F1"])  # named only through TYPE_GROUPS
    c.add_parameter("POINT", "TYPE_GROUPS", ["MODELED_MARKERS", "MODELED_MARKER",
                                             "FORCE_OUTPUTS", "FORCE_OUTPUT"])  # fmt: skip
    c.write(str(tmp_path / "m.c3d"))
    cap = read_capture(tmp_path / "m.c3d")
    assert cap.labels == ("P:LASI", "P:RASI", "P:LKNE", "*3")
    np.testing.assert_allclose(cap.positions, pos[:, :4], rtol=1e-5, atol=1e-3)
    note = next(n for n in cap.notes if "processing model" in n)
    for name in ("ANGLES 1 (P:LKneeAngles)", "MODELED_MARKERS 1 (P:LHJC)", "USERMOS 1",
                 "FORCE_OUTPUTS 1 (F1)"):  # fmt: skip
        assert name in note


@pytest.mark.parametrize("suffix", [".c3d", ".npz"])
def test_a_point_written_twice_is_read_once(tmp_path, rng, suffix: str) -> None:
    """A pipeline may write one computed point under two names (a toe's proximal axis point
    is the foot's origin): no two markers share a position, and the pair could only be scored
    half wrong. The copy is left out with a note; a point that merely fills another's gap, or
    a marker that passes close once, is no copy."""
    pos = (rng.normal(size=(30, 6, 3)) * 300).astype(np.float32)
    pos[:, 3] = pos[:, 1]  # B is A written twice
    pos[:, 4] = pos[:, 2]
    pos[10:20, 4] = np.nan  # ... but C2 is seen alone: no copy
    pos[5, 5] = pos[5, 0]  # D meets M once
    labels = ("P:M", "P:A", "P:C", "P:B", "P:C2", "P:D")
    write_capture(Capture(pos, labels, 100.0, source="mem"), tmp_path / f"d{suffix}")
    cap = read_capture(tmp_path / f"d{suffix}")
    assert cap.labels == ("P:M", "P:A", "P:C", "P:C2", "P:D")
    assert any("P:B = P:A" in n for n in cap.notes)


def test_many_markers_at_one_position_read_in_linear_memory(tmp_path) -> None:
    """A broken export that writes thousands of markers at one position (a 120 KB TRC of
    one long row of ``1.0`` cells) must not make the reader's copy check enumerate every
    coincident pair: 3,333 such markers took 2.2 GB and 10,000 more than 11 GB. Each point's
    copies are looked for among its nearest few, so the check stays linear; the copies are
    still left out, with the note."""
    n = 2_000
    np.savez(
        tmp_path / "same.npz",
        positions=np.ones((3, n, 3), dtype=np.float32),
        labels=np.array([f"S:M{i}" for i in range(n)]),
        rate=100.0,
    )
    tracemalloc.start()
    try:
        cap = read_capture(tmp_path / "same.npz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6  # every pair (2 million tuples in a set) needed several hundred MB
    assert cap.labels == ("S:M0",)
    assert any("repeat another point exactly" in note for note in cap.notes)


@pytest.mark.parametrize("suffix", [".c3d", ".trc"])
def test_other_systems_unlabeled_names_are_unlabeled_tracks(tmp_path, rng, suffix: str) -> None:
    """Motive writes a trajectory nobody labeled as ``Unlabeled 1234`` (or ``_0001``), other
    exporters ``Unidentified 3``: read as markers, each would be scored and trained as a marker
    nobody can label. They are read as unlabeled tracks, like Vicon's ``*N``, with a note; a
    marker whose name merely contains such a word stays a marker."""
    labels = ["S:LASI", "Unlabeled 1234", "Unlabeled:1235", "S:_0001", "Unidentified 3",
              "S:unknown", "S:UnlabeledStrap", "S:RASI"]  # fmt: skip
    pos = rng.normal(0.0, 300.0, (5, len(labels), 3)).astype(np.float32)
    cap = Capture(positions=pos, labels=tuple(labels), rate=100.0)
    path = write_capture(cap, tmp_path / f"u{suffix}")
    cap = read_capture(path)
    assert [is_ghost(x) for x in cap.labels] == [False] + [True] * 5 + [False, False]
    assert cap.labels[0] == "S:LASI" and cap.labels[6:] == ("S:UnlabeledStrap", "S:RASI")
    assert len(set(cap.labels)) == len(labels)
    assert any("5 unlabeled trajectories" in n for n in cap.notes)
    np.testing.assert_allclose(cap.positions, pos, atol=1e-3)


def _malformed_npz(path, kind: str, rng: np.random.Generator) -> None:
    """A capture NPZ spoiled one way (``kind``)."""
    good = {
        "positions": (rng.normal(size=(400, 3, 3)) * 500).astype(np.float32),
        "labels": np.array(["A:a", "A:b", "A:c"]),
        "rate": np.float64(100.0),
    }
    if kind == "member cut":  # its zip entry intact, its array data 40 bytes short
        with zipfile.ZipFile(path, "w") as z:
            for key, value in good.items():
                buf = io.BytesIO()
                np.save(buf, value)
                z.writestr(
                    f"{key}.npy", buf.getvalue()[:-40] if key == "positions" else buf.getvalue()
                )
        return
    np.savez_compressed(path, **good)
    data = path.read_bytes()
    if kind == "cut":  # a copy that stopped half way
        path.write_bytes(data[: len(data) // 2])
        return
    if kind == "garbage":
        path.write_bytes(b"not a capture\n" * 40)
        return
    if kind == "member damaged":  # bytes inside the (first) positions member's compressed data
        path.write_bytes(data[:100] + b"\xa5" * 40 + data[140:])
        return
    spoil = {
        "missing key": {"labels": None},
        "object labels": {"labels": np.array(["A:a", 1, None], dtype=object)},
        "2-D positions": {"positions": good["positions"][:, :, 0]},
        "text positions": {"positions": np.full((4, 3, 3), "x")},
        "complex positions": {"positions": good["positions"] + 1j},
        "rate array": {"rate": np.array([100.0, 120.0])},
        "rate text": {"rate": np.array("fast")},
    }[kind]
    members = {k: v for k, v in {**good, **spoil}.items() if v is not None}
    np.savez(path, allow_pickle=True, **members)


@pytest.mark.parametrize(
    ("kind", "says"),
    [
        ("cut", "not an NPZ (zip) archive (damaged or truncated?)"),
        ("garbage", "not an NPZ (zip) archive (damaged or truncated?)"),
        ("member cut", "NPZ member positions.npy cannot be read (damaged or truncated?)"),
        ("member damaged", "NPZ member positions.npy cannot be read (damaged or truncated?)"),
        ("missing key", "not a capture NPZ: it lacks labels (it holds positions, rate)"),
        ("object labels", "NPZ member labels.npy holds Python objects (a pickle)"),
        ("2-D positions", "positions must be (frames, markers, 3), got shape (400, 3)"),
        ("text positions", "positions must be real numbers, got dtype <U1"),
        ("complex positions", "positions must be real numbers, got dtype complex"),
        ("rate array", "rate must be one number (Hz), got shape (2,)"),
        ("rate text", "rate must be one number (Hz), got 'fast'"),
    ],
)
def test_a_malformed_npz_says_what_is_wrong_with_which_file(tmp_path, rng, capsys, kind, says):
    """A hostile run: numpy's own words ("axis 2 is out of bounds for array of dimension 2",
    "Object arrays cannot be loaded when allow_pickle=False", "EOF: reading array data",
    "only 0-dimensional arrays can be converted to Python scalars") or zip's ("File is not a
    zip file", "Bad CRC-32") with nothing of what a capture NPZ should hold."""
    path = tmp_path / "take.npz"
    _malformed_npz(path, kind, rng)
    with pytest.raises(CaptureFormatError) as caught:
        read_capture(path)
    assert str(caught.value).startswith(f"{path}: ") and says in str(caught.value)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {caught.value}\n"


def test_npz_with_a_member_the_reader_does_not_read(tmp_path, rng) -> None:
    """A producer's own metadata beside the capture (here Python objects) is left alone: only
    the members the reader loads are refused for holding objects (a review of the malformed
    NPZ fix: it refused such a file, which was read before)."""
    pos = rng.normal(scale=300.0, size=(5, 2, 3))
    path = tmp_path / "m.npz"
    meta = np.array([{"operator": "x"}], dtype=object)
    np.savez(path, positions=pos, labels=np.array(["D:a", "D:b"]), rate=100.0, meta=meta)
    cap = read_capture(path)
    assert cap.labels == ("D:a", "D:b") and cap.rate == 100.0


def test_an_npz_that_cannot_be_opened_is_not_called_damaged(tmp_path) -> None:
    path = tmp_path / "folder.npz"
    path.mkdir()
    with pytest.raises(CaptureFormatError) as caught:
        check_npz(path)
    assert "cannot be read" in str(caught.value) and "damaged" not in str(caught.value)


def test_npz_labels_as_bytes_or_a_column(tmp_path, rng) -> None:
    """A hostile run: an NPZ whose labels are bytes read back as subject ``b'Derrick``; a (M, 1)
    column as ``['Derrick``."""
    pos = rng.normal(scale=300.0, size=(5, 3, 3))
    names = np.array(["D:a", "D:b", "D:c"])
    path = tmp_path / "b.npz"
    np.savez(path, positions=pos, labels=names.astype("S3"), rate=100.0)
    cap = read_capture(path)
    assert cap.labels == ("D:a", "D:b", "D:c") and cap.subjects == ("D",)
    np.savez(path, positions=pos, labels=names[:, None], rate=100.0)
    with pytest.raises(CaptureError, match=r"labels must be a 1-D array, got shape \(3, 1\)"):
        read_capture(path)


def test_info_lists_a_few_never_visible_markers_and_counts_the_rest(tmp_path, capsys) -> None:
    """A recording of a model's many markers, most never seen, printed every name on one
    "never visible" line; the text lists the first few and counts the rest, ``--json`` all."""
    n = 40
    pos = np.full((5, n, 3), np.nan, dtype=np.float32)
    pos[:, 0] = [[0.0, 0.0, 1000.0]]
    np.savez(tmp_path / "r.npz", positions=pos, labels=np.array([f"S:M{i}" for i in range(n)]),
             rate=100.0)  # fmt: skip
    assert main(["info", str(tmp_path / "r.npz")]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if "never visible" in x][0]
    assert line.strip() == (
        "never visible: 39 markers: " + ", ".join(f"S:M{i}" for i in range(1, 13)) + " and 27 more"
    ), line
    assert main(["info", str(tmp_path / "r.npz"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(summary["never_visible"]) == 39
