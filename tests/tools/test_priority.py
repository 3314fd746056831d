"""The viewer's CPU priority: ``idle`` really puts the process (and its children) in SCHED_IDLE."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from labeler_service.tools.priority import lower_priority

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="no SCHED_IDLE here")

_CHILD = """
import os, subprocess, sys
from labeler_service.tools.priority import lower_priority
print(lower_priority(sys.argv[1]))
print(os.sched_getscheduler(0) == os.SCHED_IDLE, os.nice(0))
# a child (like the browser Playwright launches) inherits the class
print(subprocess.check_output([sys.executable, "-c",
      "import os; print(os.sched_getscheduler(0) == os.SCHED_IDLE)"], text=True).strip())
"""


def _run(priority: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", _CHILD, priority], capture_output=True,
                         text=True, check=True, timeout=60)  # fmt: skip
    return out.stdout.split("\n")


def test_idle_is_sched_idle_and_inherited():
    did, own, child, _ = _run("idle")
    assert did == "SCHED_IDLE"
    assert own.split()[0] == "True"
    assert child == "True"


def test_low_is_nice_10_and_normal_changes_nothing():
    base = os.nice(0)
    did, own, child, _ = _run("low")
    assert did == "nice 10" and own == f"False {base + 10}" and child == "False"
    did, own, child, _ = _run("normal")
    assert did == "normal" and own == f"False {base}" and child == "False"


def test_unknown_priority_is_refused():
    with pytest.raises(ValueError, match="idle, low, normal"):
        lower_priority("fast")
