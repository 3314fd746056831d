"""``--seed -1``: every command that takes a seed refuses it as a usage error (exit 2, the
reason on stderr); numpy's "ValueError: expected non-negative integer" came out as a traceback
of evaluate, compose, simulate, replay and the rest after reading the inputs."""

from __future__ import annotations

import pytest

from labeler_service.cli.main import main

COMMANDS = [
    ["evaluate", "take.c3d"],
    ["compose", "out.c3d", "take.c3d", "--radius", "300", "--frames", "10"],
    ["simulate", "out.c3d", "--performers", "2", "--seconds", "1", "--scenario", "walk"],
    ["replay", "take.c3d", "--to", "udp://127.0.0.1:9/x"],
    ["label", "take.c3d", "out.c3d"],
    ["demo"],
    ["bench", "latency"],
    ["train", "shoulder", "take.c3d", "--out", "dir"],
    ["simulate-shoulder", "dir"],
]


@pytest.mark.parametrize("argv", COMMANDS, ids=lambda a: " ".join(a[:2]))
def test_a_negative_seed_is_a_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--seed", "-1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--seed" in err and "whole number >= 0" in err and "Traceback" not in err


def test_a_seed_of_zero_and_above_parses():
    from labeler_service.cli.args import seed

    assert seed("0") == 0 and seed("123") == 123
