"""``label IN.c3d OUT.c3d`` keeps everything of IN but its points: a labeled take overlays the
take it came from. OUT was written from scratch: a user labeling the sprint take
(`sprint_51markers_250hz.c3d`) lost its 60 analog channels (force plates), its 10 gait events,
its force-platform and trial parameters, and its time base (first frame 833 became 1, so the
events and every other export of the trial no longer lined up)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main

ezc3d = pytest.importorskip("ezc3d")

RATE = 100.0
PER = 10  # analog samples per frame (1 kHz)
FIRST = 833  # the take's first frame (1-based), as a trimmed Vicon trial has


@pytest.fixture
def trial(rng, tmp_path):
    """A labeled C3D of two articulated performers in metres, with 4 analog channels, two
    events, a force platform, a ``TRIAL`` group and a first frame past 1."""
    truth, names = articulated(rng, subjects=2, frames=120, rate=RATE)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [RATE]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c.add_parameter("POINT", "UNITS", ["m"])
    pts = np.ones((4, len(names), truth.shape[0]))
    pts[:3] = np.transpose(truth / 1000.0, (2, 1, 0))
    c["data"]["points"] = pts
    c["parameters"]["ANALOG"]["RATE"]["value"] = [RATE * PER]
    c["parameters"]["ANALOG"]["LABELS"]["value"] = ["Fx", "Fy", "Fz", "EMG"]
    c["parameters"]["ANALOG"]["UNITS"]["value"] = ["N", "N", "N", "V"]
    analog = np.arange(4 * truth.shape[0] * PER, dtype=np.float64).reshape(1, 4, -1)
    c["data"]["analogs"] = analog
    c.add_parameter("EVENT", "USED", [2])
    c.add_parameter("EVENT", "LABELS", ["Foot Strike", "Foot Off"])
    c.add_parameter("EVENT", "TIMES", np.array([[0.0, 0.0], [8.6, 9.0]]))
    c.add_parameter("FORCE_PLATFORM", "USED", [1])
    c.add_parameter("FORCE_PLATFORM", "TYPE", [2])
    c.add_parameter("TRIAL", "ACTUAL_START_FIELD", [FIRST, 0])
    c.add_parameter("TRIAL", "ACTUAL_END_FIELD", [FIRST + truth.shape[0] - 1, 0])
    c["header"]["points"]["first_frame"] = FIRST - 1
    path = tmp_path / "trial.c3d"
    c.write(str(path))
    return path, truth, names, analog


def _label(src, out, capsys) -> dict:
    assert main(["label", str(src), str(out), "--init-frames", "40", "--json"]) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_label_keeps_the_analog_channels_events_groups_time_base_and_units(trial, tmp_path, capsys):
    src, truth, names, analog = trial
    out = tmp_path / "out.c3d"
    summary = _label(src, out, capsys)
    assert summary["agreement_with_input_labels"] == 1.0
    assert summary["kept_from_input"] == [
        "4 analog channels", "2 events", f"time base (first frame {FIRST})",
        "parameter groups EVENT, FORCE_PLATFORM, TRIAL",
    ]  # fmt: skip
    c = ezc3d.c3d(str(out))
    np.testing.assert_array_equal(c["data"]["analogs"], analog)
    assert c["parameters"]["ANALOG"]["LABELS"]["value"] == ["Fx", "Fy", "Fz", "EMG"]
    assert c["parameters"]["EVENT"]["LABELS"]["value"] == ["Foot Strike", "Foot Off"]
    np.testing.assert_allclose(c["parameters"]["EVENT"]["TIMES"]["value"][1], [8.6, 9.0])
    assert int(c["parameters"]["FORCE_PLATFORM"]["USED"]["value"][0]) == 1
    assert c["header"]["points"]["first_frame"] == FIRST - 1
    assert list(c["parameters"]["TRIAL"]["ACTUAL_START_FIELD"]["value"]) == [FIRST, 0]
    # the points in IN's units (metres), at IN's positions, under the labels
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["m"]
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    assert labels[: len(names)] == list(names)
    xyz = np.transpose(c["data"]["points"][:3, : len(names)], (2, 1, 0))
    np.testing.assert_allclose(xyz * 1000.0, truth, atol=0.01)
    assert c["parameters"]["SUBJECTS"]["NAMES"]["value"] == sorted({n.split(":")[0] for n in names})
    # and our own reader reads it back as the labeled take, in millimetres
    back = read_capture(out)
    np.testing.assert_allclose(back.positions[:, : len(names)], truth, atol=0.01)
    # every sample observed: residual 1 (a recovered one would have 0, C3D's calculated point)
    res = np.asarray(c["data"]["meta_points"]["residuals"])[0, : len(names)]
    assert np.all(res == 1.0)


def test_a_segment_keeps_its_own_frames_of_the_analog_channels_and_time_base(
    trial, tmp_path, capsys
):
    src, truth, names, analog = trial
    out = tmp_path / "seg.c3d"
    summary = _label(f"{src}:30:100", out, capsys)
    assert f"time base (first frame {FIRST + 30})" in summary["kept_from_input"]
    # its events: those within its frames (8.62-9.31 s on the take's time base)
    assert "1 event (1 outside its frames left out)" in summary["kept_from_input"]
    c = ezc3d.c3d(str(out))
    assert c["parameters"]["EVENT"]["LABELS"]["value"] == ["Foot Off"]
    np.testing.assert_allclose(c["parameters"]["EVENT"]["TIMES"]["value"], [[0.0], [9.0]])
    assert list(c["parameters"]["EVENT"]["USED"]["value"]) == [1]
    np.testing.assert_array_equal(c["data"]["analogs"], analog[:, :, 30 * PER : 100 * PER])
    assert c["header"]["points"]["first_frame"] == FIRST - 1 + 30
    assert list(c["parameters"]["TRIAL"]["ACTUAL_START_FIELD"]["value"]) == [FIRST + 30, 0]
    assert list(c["parameters"]["TRIAL"]["ACTUAL_END_FIELD"]["value"]) == [FIRST + 99, 0]
    xyz = np.transpose(c["data"]["points"][:3, : len(names)], (2, 1, 0))
    np.testing.assert_allclose(xyz * 1000.0, truth[30:100], atol=0.01)


def test_a_points_only_input_or_output_keeps_nothing_more(trial, rng, tmp_path, capsys):
    """A TRC or NPZ has no analog channels to keep; a C3D read into NPZ has no place for them.
    The text output says what was kept only when something was."""
    src, truth, names, _ = trial
    summary = _label(src, tmp_path / "out.npz", capsys)
    assert summary["kept_from_input"] == []
    npz = tmp_path / "take.npz"
    write_capture(Capture(truth, names, RATE, source="take"), npz)
    assert _label(npz, tmp_path / "o.c3d", capsys)["kept_from_input"] == []
    assert main(["label", str(src), str(tmp_path / "t.c3d"), "--init-frames", "40"]) == 0
    text = capsys.readouterr().out
    assert f"keeps from {src}: 4 analog channels, 2 events, time base (first frame {FIRST})" in text
    assert main(["label", str(npz), str(tmp_path / "t2.c3d"), "--init-frames", "40"]) == 0
    assert "keeps from" not in capsys.readouterr().out
    # a C3D IN into a TRC OUT: what is not carried over is said, not dropped silently
    assert main(["label", str(src), str(tmp_path / "t.trc"), "--init-frames", "40"]) == 0
    assert "t.trc holds IN's points only" in capsys.readouterr().err


def test_the_points_a_processing_model_wrote_are_not_written(rng, tmp_path, capsys):
    """Joint angles a modeling step wrote beside the markers were computed from the labels OUT
    replaces: they are left out when read (capture/io.py) and not written back, and the POINT
    parameter that listed them goes with them."""
    truth, names = articulated(rng, subjects=1, frames=80, rate=RATE)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [RATE]
    c["parameters"]["POINT"]["LABELS"]["value"] = [*names, "LHipAngles"]
    c.add_parameter("POINT", "UNITS", ["mm"])
    c.add_parameter("POINT", "ANGLES", ["LHipAngles"])
    pts = np.ones((4, len(names) + 1, truth.shape[0]))
    pts[:3, : len(names)] = np.transpose(truth, (2, 1, 0))
    pts[:3, -1] = 12.5  # degrees
    c["data"]["points"] = pts
    src = tmp_path / "modelled.c3d"
    c.write(str(src))
    out = tmp_path / "out.c3d"
    _label(src, out, capsys)
    w = ezc3d.c3d(str(out))
    assert "LHipAngles" not in w["parameters"]["POINT"]["LABELS"]["value"]
    assert "ANGLES" not in w["parameters"]["POINT"]


def test_an_input_that_cannot_be_written_back_still_gives_its_labeled_points(
    trial, tmp_path, capsys, monkeypatch, caplog
):
    """Whatever keeping IN's content fails on (a file ezc3d reads but will not write back),
    the labeling run is not lost: OUT holds the labeled points at IN's time base, and the log
    says why the rest is missing."""
    import labeler_service.capture.io as io

    def refuse(*_a, **_k):
        raise RuntimeError("ezc3d: bad parameter")

    monkeypatch.setattr(io, "_write_c3d_like", refuse)
    src, truth, names, _ = trial
    out = tmp_path / "out.c3d"
    summary = _label(src, out, capsys)
    assert summary["kept_from_input"] == [f"time base (first frame {FIRST})"]
    assert ezc3d.c3d(str(out))["header"]["points"]["first_frame"] == FIRST - 1
    assert "written without the rest of" in caplog.text and "bad parameter" in caplog.text
    back = read_capture(out)
    np.testing.assert_allclose(back.positions[:, : len(names)], truth, atol=0.01)


def test_a_trc_output_or_input_keeps_the_time_base(trial, rng, tmp_path, capsys):
    """Frame numbers and times of IN's frames: a TRC OUT of a trimmed C3D trial (frame 833 on)
    and of a TRC that starts at frame 501, 5.0 s; a C3D OUT of that TRC starts at frame 501."""
    src, truth, names, _ = trial
    out = tmp_path / "out.trc"
    summary = _label(f"{src}:10", out, capsys)
    assert summary["kept_from_input"] == [f"time base (first frame {FIRST + 10})"]
    rows = [x.split("\t") for x in out.read_text().splitlines()[5:] if x.strip()]
    assert [int(r[0]) for r in rows[:2]] == [FIRST + 10, FIRST + 11]
    np.testing.assert_allclose(
        [float(r[1]) for r in rows[:2]], [(FIRST + 9) / RATE, (FIRST + 10) / RATE]
    )
    assert out.read_text().splitlines()[2].split("\t")[6] == str(FIRST + 10)  # OrigDataStartFrame
    # a TRC input numbered from 501 at 5.0 s
    trc = tmp_path / "in.trc"
    write_capture(Capture(truth, names, RATE, source="in"), trc)
    lines = trc.read_text().splitlines()
    body = [x.split("\t") for x in lines[5:] if x.strip()]
    for i, r in enumerate(body):
        r[0], r[1] = str(501 + i), f"{5.0 + i / RATE:.6f}"
    trc.write_text("\n".join(lines[:5] + ["\t".join(r) for r in body]) + "\n")
    out2 = tmp_path / "out2.trc"
    assert _label(trc, out2, capsys)["kept_from_input"] == ["time base (first frame 501)"]
    first = next(x for x in out2.read_text().splitlines()[5:] if x.strip()).split("\t")
    assert first[0] == "501" and float(first[1]) == pytest.approx(5.0)
    out3 = tmp_path / "out3.c3d"
    _label(trc, out3, capsys)
    assert ezc3d.c3d(str(out3))["header"]["points"]["first_frame"] == 500
    # a file numbered from 1 has no time base worth a word
    plain = tmp_path / "plain.trc"
    write_capture(Capture(truth, names, RATE, source="plain"), plain)
    assert _label(plain, tmp_path / "o.trc", capsys)["kept_from_input"] == []


def test_a_recovered_sample_is_marked_calculated(rng, tmp_path, capsys):
    """A hidden marker's estimate written to a C3D has the residual 0 (C3D's calculated point),
    an observed sample 1, a missing one -1: a user (or Nexus, Mokka) tells them apart. With
    ``--drop-recovered`` none is written, and the summary counts none."""
    truth, names = articulated(rng, subjects=2, frames=120, rate=RATE)
    take = truth.copy()
    m = 3
    take[60:70, m] = np.nan
    src = tmp_path / "gap.c3d"
    write_capture(Capture(take, names, RATE, source="gap"), src)
    out = tmp_path / "out.c3d"
    summary = _label(src, out, capsys)
    c = ezc3d.c3d(str(out))
    res = np.asarray(c["data"]["meta_points"]["residuals"])[0].T  # (F, M)
    assert np.all(res[60:70, m] == 0.0)
    xyz = np.transpose(c["data"]["points"][:3], (2, 1, 0))
    assert np.linalg.norm(xyz[60:70, m] - truth[60:70, m], axis=1).max() < 5.0
    assert np.all(res[:60, m] == 1.0) and np.all(res[70:, m] == 1.0)
    assert summary["recovered_per_frame"] > 0
    assert main(["label", str(src), str(tmp_path / "d.c3d"), "--init-frames", "40",
                 "--drop-recovered", "--json"]) == 0  # fmt: skip
    dropped = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert dropped["recovered_per_frame"] == 0
    res = np.asarray(ezc3d.c3d(str(tmp_path / "d.c3d"))["data"]["meta_points"]["residuals"])[0].T
    assert np.all(res[60:70, m] == -1.0)


def test_markers_named_without_a_subject_come_back_so(rng, tmp_path, capsys):
    """A take whose labels name no subject (``L_IAS``; the reader gives them the file's stem)
    is written back with those names, not ``stem:L_IAS``: a pipeline reading OUT finds the
    names it knows."""
    truth, names = articulated(rng, subjects=1, frames=120, rate=RATE)
    bare = [n.split(":", 1)[1] for n in names]
    for suffix in (".c3d", ".trc"):
        src = tmp_path / f"walk{suffix}"
        write_capture(Capture(truth, bare, RATE, source="walk"), src)
        assert read_capture(src).labels[0] == f"walk:{bare[0]}"  # (as the reader names them)
        out = tmp_path / f"out{suffix}"
        summary = _label(src, out, capsys)
        assert summary["agreement_with_input_labels"] == 1.0
        assert list(read_capture(out).labels) == [f"out:{b}" for b in bare]
        if suffix == ".c3d":
            assert ezc3d.c3d(str(out))["parameters"]["POINT"]["LABELS"]["value"] == bare
