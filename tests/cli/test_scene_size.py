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
    assert "compose at most 13541656 frames" in err
    assert not out.exists()


def test_the_limit_itself_composes_and_reads_back(take, tmp_path, monkeypatch, capsys):
    """The most frames the error names are composed, and the scene they make is read back under
    the same limit (the positions alone were counted: at that many frames the NPZ's labels and
    headers put it over, and ``info`` refused the scene compose had just written); one more
    frame is refused."""
    import re

    monkeypatch.setenv("MOCAP_MAX_NPZ_BYTES", str(8 * 12 * 500))
    out = tmp_path / "scene.npz"
    assert main(_compose(take, out, "500")) == 2  # 500 frames of positions alone fill it
    most = int(re.search(r"compose at most (\d+) frames", capsys.readouterr().err)[1])
    assert 490 <= most < 500
    assert main(_compose(take, out, str(most + 1))) == 2
    assert f"compose at most {most} frames" in capsys.readouterr().err
    assert main(_compose(take, out, str(most))) == 0
    assert read_capture(out).n_frames == most  # (under the same limit)
    assert main(["info", str(out)]) == 0


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


def test_a_memory_error_without_a_message_says_what_failed(take, tmp_path, monkeypatch, capsys):
    """A bare ``MemoryError()`` (Python's own allocations give no text) printed "out of memory:
    (ask for less ..." with nothing after the colon: an exception is truthy even when its text
    is empty."""
    import labeler_service.scenes.compose as compose

    def exhausted(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(compose, "compose_scene", exhausted)
    assert main(_compose(take, tmp_path / "scene.npz", "10")) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory: an allocation failed (ask for less")
