"""``--help`` says each option's default, once."""

from __future__ import annotations

import pytest

from labeler_service.cli.main import main


def _help(capsys, *command: str) -> str:
    with pytest.raises(SystemExit) as e:
        main([*command, "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # (argparse wraps lines)


def test_help_gives_the_defaults(capsys):
    text = _help(capsys, "evaluate")
    assert "length of each gap (frames) (default: 20)" in text
    assert "how long each --leave subject is gone (default: 1.0)" in text
    # a default the help already states, a computed one (None) and a flag: nothing added
    assert "(default: None)" not in text and "(default: False)" not in text
    assert "default 50; with --model default 0" in text
    text = _help(capsys, "bench", "latency")
    assert "performers (1-10) (default: 10)" in text


def test_a_bracketed_default_is_not_said_twice(capsys):
    text = _help(capsys, "simulate-shoulder")
    assert "frame rate, 10-10000 Hz [120]" in text and "(default: 120" not in text
