"""Implausible frame rates are refused wherever a rate comes in, by one check
(``capture.model.rate_problem``: 1 to 10000 Hz): the ``--rate`` options, the readers, the
service's settings. ``compose --rate 0.001`` wrote a scene at a thousandth of a hertz, an NPZ or
C3D of 1e7 Hz was read without a word, and a stream's ``rate = inf`` or ``1e7`` was taken
(the TRC reader's fallback to the Time column is in ``tests/capture/test_trc_reader.py``)."""

from __future__ import annotations

import re

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.cli.main import main
from labeler_service.errors import CaptureFormatError, ConfigError, SceneError


def test_rate_problem_names_the_range():
    from labeler_service.capture.model import rate_problem

    assert rate_problem(120.0) is None and rate_problem(1) is None and rate_problem(1e4) is None
    for bad in (0, -1, float("nan"), float("inf"), 1e7, 0.5, "120", True):
        assert "expected 1 to 10000 Hz" in (rate_problem(bad) or ""), bad


@pytest.fixture
def take(rng, tmp_path):
    pos, names = articulated(rng, subjects=1, frames=120)
    path = tmp_path / "take.npz"
    write_capture(Capture(pos, names, 120.0, source="take"), path)
    return path


@pytest.mark.parametrize("value", ["0", "-5", "nan", "inf", "1e7", "0.001"])
@pytest.mark.parametrize("command", ["compose", "simulate", "bench"])
def test_a_rate_option_refuses_a_rate_no_capture_has(command, value, take, tmp_path, capsys):
    out = str(tmp_path / "out.npz")
    argv = {
        "compose": ["compose", out, str(take), "--radius", "300", "--frames", "50", "--seed", "1"],
        "simulate": [
            "simulate",
            out,
            "--performers",
            "1",
            "--seconds",
            "1",
            "--scenario",
            "walk",
            "--seed",
            "1",
        ],  # fmt: skip
        "bench": ["bench", "latency"],
    }[command]
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--rate", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--rate: expected a frame rate of 1 to 10000 Hz" in err and value in err
    assert "Traceback" not in err
    assert not (tmp_path / "out.npz").exists()


def test_the_library_checks_are_the_same(take):
    from labeler_service.scenes.compose import compose_scene
    from labeler_service.scenes.simulate import simulate_scene

    with pytest.raises(SceneError, match="--rate is 0.001 Hz: expected 1 to 10000 Hz"):
        compose_scene([take], radius=300.0, frames=50, seed=1, rate=0.001)
    with pytest.raises(SceneError, match="--rate is 5000 Hz: expected 1 to 2000 Hz"):
        simulate_scene(1, 1.0, "walk", 1, rate=5000.0)


@pytest.mark.parametrize("rate", [1e7, 0.5])
def test_a_capture_file_at_a_rate_no_capture_has_is_refused(rng, tmp_path, capsys, rate):
    pos, names = articulated(rng, subjects=1, frames=20)
    path = tmp_path / "odd.npz"
    write_capture(Capture(pos, names, rate), path)  # (a Capture holds any rate > 0)
    why = re.escape(f"odd.npz: frame rate is {rate:g} Hz: expected 1 to 10000 Hz")
    with pytest.raises(CaptureFormatError, match=why):
        read_capture(path)
    assert main(["info", str(path)]) == 2
    assert "frame rate is" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["inf", "1e7", "0.5"])
def test_a_stream_rate_no_capture_has_is_a_config_error(value, tmp_path):
    from labeler_service.service.settings import load_settings

    f = tmp_path / "s.toml"
    f.write_text(f'[[streams]]\nname = "vol1"\nrate = {value}\n')
    with pytest.raises(ConfigError, match="rate is .* Hz: expected 1 to 10000 Hz"):
        load_settings(f)


def test_a_rate_below_the_rates_measured_is_said_and_below_one_hertz_refused(rng, tmp_path, capsys):
    """Below the lowest rate the benchmarks measure (12.5 Hz) ``evaluate`` and ``label`` say
    so (a helper found 50 % at 5 Hz without a word); ``--downsample`` below 1 Hz is refused
    as every other rate is (it ran at 0.5 Hz)."""
    import json

    pos, names = articulated(rng, subjects=1, frames=60, rate=10.0)
    path = tmp_path / "slow.npz"
    write_capture(Capture(pos, names, 10.0, source="slow"), path)
    assert main(["evaluate", str(path), "--init-frames", "10", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert any("10 Hz is below the lowest rate measured (12.5 Hz)" in n for n in report["notes"])
    assert main(["label", str(path), str(tmp_path / "o.npz"), "--init-frames", "10"]) == 0
    assert "10 Hz is below the lowest rate measured" in capsys.readouterr().err
    fast = tmp_path / "fast.npz"
    write_capture(Capture(pos, names, 120.0, source="fast"), fast)
    assert main(["evaluate", str(fast), "--init-frames", "10", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert not any("below the lowest rate" in n for n in report["notes"])
    assert main(["evaluate", str(path), "--init-frames", "3", "--downsample", "15"]) != 0
    assert "--downsample 15 leaves 0.667 Hz" in capsys.readouterr().err
