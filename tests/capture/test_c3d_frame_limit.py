"""A C3D counts its frames in 16 bits: ezc3d wrote 100,000 frames and read back 65,535, with no
word (a composed 100,000-frame scene; ``label`` and ``subscribe --out`` write the same way). Past
65,535 frames a C3D is refused before any work, ``subscribe --out`` writes NPZ instead, and a
C3D holding data past its count is read with a note."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import Capture, c3d_frames_fit, read_capture, write_capture
from labeler_service.capture.io import C3D_MAX_FRAMES
from labeler_service.cli.main import main
from labeler_service.errors import CaptureError
from labeler_service.tools.subscribe import Recorder


def _long(n: int) -> Capture:
    pos = np.zeros((n, 1, 3), dtype=np.float32)
    pos[:, 0, 0] = np.arange(n) % 1000 + 1.0
    pos[:, 0, 2] = 1000.0
    return Capture(pos, ("S:a",), 100.0)


def test_more_frames_than_a_c3d_counts_are_refused_not_cut(tmp_path):
    with pytest.raises(CaptureError, match="at most 65,535 frames"):
        write_capture(_long(C3D_MAX_FRAMES + 1), tmp_path / "x.c3d")
    assert not list(tmp_path.iterdir())  # no file, no temporary left
    c3d_frames_fit(tmp_path / "x.npz", 10**6)  # NPZ and TRC hold any count
    c3d_frames_fit(tmp_path / "x.trc", 10**6)
    with pytest.raises(CaptureError, match=r"write \.npz or \.trc"):
        c3d_frames_fit(tmp_path / "x.C3D", C3D_MAX_FRAMES + 1)
    cap = read_capture(write_capture(_long(C3D_MAX_FRAMES), tmp_path / "full.c3d"))
    assert cap.n_frames == C3D_MAX_FRAMES and not cap.notes


def test_compose_refuses_a_c3d_scene_longer_than_a_c3d_before_composing(tmp_path, capsys):
    take = write_capture(_long(50), tmp_path / "t.c3d")
    rc = main(["compose", str(tmp_path / "scene.c3d"), str(take), "--radius", "0",
               "--frames", "70000", "--seed", "1"])  # fmt: skip
    assert rc == 2
    assert "at most 65,535 frames" in capsys.readouterr().err
    assert not (tmp_path / "scene.c3d").exists()


def test_a_long_subscribe_recording_is_written_as_npz_beside_the_c3d_asked(tmp_path):
    rec = Recorder()
    rec.names, rec.rate = ("S:a",), 100.0
    rec.positions = list(_long(C3D_MAX_FRAMES + 5).positions)
    assert rec.write(tmp_path / "session.c3d") == C3D_MAX_FRAMES + 5
    assert rec.written == tmp_path / "session.npz"
    assert read_capture(tmp_path / "session.npz").n_frames == C3D_MAX_FRAMES + 5
    assert not (tmp_path / "session.c3d").exists()


def test_a_c3d_with_data_past_its_16_bit_count_is_read_with_a_note(tmp_path):
    import ezc3d

    n = C3D_MAX_FRAMES + 400
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["S:a"]
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [""]
    pts = np.ones((4, 1, n))
    pts[0, 0] = np.arange(n) % 1000 + 1.0
    c["data"]["points"] = pts
    c.write(str(tmp_path / "long.c3d"))
    cap = read_capture(tmp_path / "long.c3d")
    assert cap.n_frames == C3D_MAX_FRAMES
    assert any("past its 65,535-frame count" in note for note in cap.notes), cap.notes
