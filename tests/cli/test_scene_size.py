"""``compose --frames 10000000`` asked numpy for 8.7 GiB per take and died with a MemoryError
traceback. A scene larger than a capture the project reads (``MOCAP_MAX_NPZ_BYTES``, 1.3 GB of
positions) is refused before any take is resampled, naming the size, the limit and the most
frames that fit; any other MemoryError is one line too."""

from __future__ import annotations

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main


@pytest.fixture
def take(rng, tmp_path):
    pos, names = articulated(rng, subjects=1, frames=100)  # 8 markers
    path = tmp_path / "take.npz"
    write_capture(Capture(pos, names, 120.0, source="take"), path)
    return path


def _compose(take, out, frames: str) -> list[str]:
    return ["compose", str(out), str(take), "--radius", "300", "--frames", frames, "--seed", "1"]


def test_an_absurd_scene_length_is_refused_naming_the_size(take, tmp_path, capsys):
    out = tmp_path / "scene.npz"
    assert main(_compose(take, out, "100000000")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("error: --frames 100000000 of 8 markers is a 9.6 GB scene")
    assert "more than the 1.3 GB a capture is read within (MOCAP_MAX_NPZ_BYTES)" in err
    assert "compose at most 13541666 frames" in err
    assert not out.exists()


def test_the_limit_itself_composes(take, tmp_path, monkeypatch, capsys):
    """At most ``limit // (markers x 12)`` frames: that many are written (the take leaves the
    scene after its 100 frames), one more is refused."""
    monkeypatch.setenv("MOCAP_MAX_NPZ_BYTES", str(8 * 12 * 500))
    out = tmp_path / "scene.npz"
    assert main(_compose(take, out, "501")) == 2
    assert "compose at most 500 frames" in capsys.readouterr().err
    assert main(_compose(take, out, "500")) == 0
    monkeypatch.delenv("MOCAP_MAX_NPZ_BYTES")  # (its labels and headers come on top)
    assert read_capture(out).n_frames == 500


def test_a_memory_error_is_one_line(take, tmp_path, monkeypatch, capsys):
    import labeler_service.scenes.compose as compose

    def exhausted(*args, **kwargs):
        raise MemoryError("Unable to allocate 8.72 GiB for an array with shape (10000000, 39, 3)")

    monkeypatch.setattr(compose, "compose_scene", exhausted)
    assert main(_compose(take, tmp_path / "scene.npz", "10")) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("error: out of memory: Unable to allocate 8.72 GiB") and err.count("\n") == 1
    )
