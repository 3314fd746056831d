"""Boot results installed late, as the service installs them (``benchmarks/late_install.py``):
the kneeling performer booted from a model with no labeled frame, each attempt's result handed
back 5-80 frames after its snapshot. Two seeds that read the left wrist on the forearm plate's
points, then on the right arm, before the extension refused a marker another free point fits
as well (``boot_match._ambiguous``)."""

from __future__ import annotations

import contextlib
import io
import json

import pytest


@pytest.mark.realdata
@pytest.mark.parametrize("seed", [38, 43])
def test_a_late_installed_extension_does_not_grow_a_wrist_onto_a_plate(real_path, seed):
    from benchmark_scripts import load_benchmark

    real_path("kneel_to_prone_62markers_240hz.c3d")  # (skips without the real takes)
    bench = load_benchmark("late_install")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert bench.main(["--seeds", str(seed)]) == 0
    (run,) = json.loads(buf.getvalue())["per_run"]
    assert run["crossed"] == 0  # (22 and 80 before: left labels on the right arm)
    assert run["wrong"] <= 10  # (182 and 200 before)
