"""``closest-point`` (``evaluate --method``'s name) names the baseline wherever a labeler is
chosen; ``baseline`` stays accepted."""

from __future__ import annotations

import pytest

from labeler_service.cli.main import build_parser


@pytest.mark.parametrize("command", [["bench", "latency"], ["demo"]])
@pytest.mark.parametrize("name", ["closest-point", "baseline"])
def test_the_baseline_has_one_name_everywhere(command, name):
    argv = [*command, "--labeler", name]
    args = build_parser(argv).parse_args(argv)
    assert args.labeler == "baseline"  # (the service's name)
    bad = [*command, "--labeler", "nearest"]
    with pytest.raises(SystemExit):
        build_parser(bad).parse_args(bad)
