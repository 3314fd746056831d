"""Benchmark scripts imported by path for their tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_benchmark(name: str) -> ModuleType:
    """Imports benchmarks/NAME.py by path: putting benchmarks/ on sys.path would shadow test
    packages of the same name (benchmarks/hostile.py vs tests/hostile)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    bench_dir = str(path.parent)
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    sys.path.insert(0, bench_dir)  # for the benchmark's own `from _common import ...`
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(bench_dir)
    return module
