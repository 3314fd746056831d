"""Absurd limits are usage errors (exit 2, one reason, no traceback), from a hostile run:
``view --port 99999`` ended in ``OverflowError`` from ``bind``; ``subscribe --seconds -1`` and
``--frames -5`` exited 0 at once with ``latency p50 nan ms``; ``evaluate --ghosts 1e9`` asked
for 200 million ghost points a frame and died of memory."""

from __future__ import annotations

import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main
from labeler_service.errors import SceneError
from labeler_service.scenes.corrupt import MAX_GHOSTS, CorruptionSpec

USAGE = [
    (["view", "--from", "udp://127.0.0.1:9/x", "--port", "99999"], "--port", "0-65535"),
    (["view", "--from", "udp://127.0.0.1:9/x", "--port", "-1"], "--port", "0-65535"),
    (["view", "--from", "udp://127.0.0.1:9/x", "--seconds", "-1"], "--seconds", "> 0"),
    (["demo", "--view-port", "70000"], "--view-port", "0-65535"),
    (["subscribe", "--from", "udp://127.0.0.1:9/x", "--seconds", "-1"], "--seconds", "> 0"),
    (["subscribe", "--from", "udp://127.0.0.1:9/x", "--seconds", "nan"], "--seconds", "> 0"),
    (["subscribe", "--from", "udp://127.0.0.1:9/x", "--frames", "-5"], "--frames", "> 0"),
]


@pytest.mark.parametrize(("argv", "flag", "why"), USAGE, ids=lambda a: str(a))
def test_an_absurd_limit_is_a_usage_error(argv, flag, why, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and why in err and "Traceback" not in err


def test_ports_and_limits_in_range_parse():
    from labeler_service.cli.args import port, positive, positive_int

    assert port("0") == 0 and port("65535") == 65535
    assert positive("0.5") == 0.5 and positive_int("3") == 3


def test_ghosts_beyond_any_capture_are_refused_before_any_work(rng, tmp_path, capsys):
    with pytest.raises(
        SceneError,
        match=f"--ghosts must be from 0 to {MAX_GHOSTS:g} per frame \\(got 1000000000.0\\)",
    ):
        CorruptionSpec(ghosts=1e9)
    CorruptionSpec(ghosts=MAX_GHOSTS)  # the limit itself is allowed
    truth, names = articulated(rng, subjects=1, frames=80)
    take = tmp_path / "take.c3d"
    write_capture(Capture(truth, names, 120.0, source="take"), take)
    code = main(["evaluate", str(take), "--ghosts", "1e9", "--init-frames", "20"])
    assert code == 2
    err = capsys.readouterr().err
    assert (
        "Traceback" not in err
        and err.startswith("error: ")
        and "--ghosts must be from 0 to 1000 per frame (got 1000000000.0)" in err
    )


@pytest.mark.parametrize(
    ("flag", "value", "rule"),
    [
        ("--leave", "-1", "--leave must be >= 0 (got -1)"),
        ("--downsample", "0", "--downsample must be >= 1 (got 0)"),
        ("--gap-frames", "0", "--gap-frames must be >= 1 (got 0)"),
        ("--leave-seconds", "0", "--leave-seconds must be positive and finite (seconds) (got 0.0)"),
    ],
)
def test_evaluate_names_the_flag_of_a_bad_corruption_setting(
    tmp_path, rng, capsys, flag, value, rule
):
    """A helper's run: ``--leave -1`` said "invalid corruption setting: leave=-1", naming no
    flag and no range."""
    truth, names = articulated(rng, subjects=1, frames=80)
    take = tmp_path / "take.c3d"
    write_capture(Capture(truth, names, 120.0, source="take"), take)
    assert main(["evaluate", str(take), flag, value, "--init-frames", "20"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and rule in err and "Traceback" not in err


@pytest.mark.parametrize("n", ["0", "11"])
def test_bench_latency_names_its_own_flag(n, capsys):
    """``bench latency --subjects 0`` said "--performers must be 1..10", the simulator's flag."""
    assert main(["bench", "latency", "--subjects", n]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --subjects must be 1..10, got {n}") and "--performers" not in err


def test_bench_latency_boot_false_is_for_the_boot_start(capsys):
    """``--boot false`` (the service's default setting: the stream boots as a recovery) only
    means something with ``--start boot``; refused before the scene is simulated."""
    assert main(["bench", "latency", "--boot", "false"]) == 2
    assert "--boot false is for --start boot" in capsys.readouterr().err


def test_an_npz_that_is_not_a_capture_says_what_it_lacks(tmp_path, capsys):
    """It said ``NPZ capture lacks 'positions is not a file in the archive'``."""
    import numpy as np

    bad = tmp_path / "other.npz"
    np.savez(bad, foo=np.zeros(3), rate=np.array(100.0))
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "not a capture NPZ: it lacks positions, labels (it holds " in err
    assert "is not a file in the archive" not in err


@pytest.mark.parametrize("value", ["1e9", "-1", "nan", "inf"])
def test_simulate_refuses_ghosts_beyond_any_capture(value, tmp_path, capsys):
    """``simulate --ghosts 1e9`` asked numpy for 179 GiB (a traceback)."""
    argv = ["simulate", str(tmp_path / "s.c3d"), "--performers", "1", "--seconds", "1",
            "--scenario", "walk", "--seed", "1", "--ghosts", value]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--ghosts must be a mean number of points per frame, 0 to 1000" in err
    assert "Traceback" not in err
