"""The cross-take benchmark's matrix: groups never mix, tennis stays together, starts skip
empty frames, every take has several partners."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest


def _load_benchmark(name: str):
    """Imports benchmarks/NAME.py by path: putting benchmarks/ on sys.path would shadow test
    packages of the same name (benchmarks/hostile.py vs tests/hostile)."""
    path = Path(__file__).resolve().parents[2] / "benchmarks" / f"{name}.py"
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


gen = _load_benchmark("generalization")


def test_split_keeps_the_tennis_data_together():
    groups = {t.key: t.group for t in gen.TAKES}
    tennis = [g for k, g in groups.items() if "tennis" in k or "two_players" in k]
    assert len(tennis) == 2 and len(set(tennis)) == 1
    clusters = [g for k, g in groups.items() if "clusters_73" in k]
    assert len(clusters) == 2 and len(set(clusters)) == 1
    assert not any("raw_unlabeled" in k for k in groups)
    assert set(groups.values()) == set(gen.GROUPS)


@pytest.mark.realdata
def test_matrix_scenes(real_path):
    real_path("tennis_serve_pig_39markers_50hz.c3d")  # skips without the real data
    scenes = gen.matrix("all", quick=False, seeds=2)
    pairs = [s for s in scenes if len(s.takes) == 2]
    alone = [s for s in scenes if len(s.takes) == 1]
    assert len(alone) == len(gen.TAKES)
    for s in pairs:
        assert {t.group for t, _ in s.takes} == {s.group}
    partners: dict[str, set[str]] = {}
    for s in pairs:
        a, b = (t.key for t, _ in s.takes)
        partners.setdefault(a, set()).add(b)
        partners.setdefault(b, set()).add(a)
    assert all(len(p) >= 3 for p in partners.values())
    assert len({s.seed for s in pairs}) == len(pairs)
    assert {s.radius for s in pairs} == set(gen.RADII)
    bts = next(s for s in alone if "gait_bts" in s.name)
    assert bts.takes[0][1] >= 239  # the BTS take is empty before frame 239
    tennis = next(s for s in pairs if "tennis" in s.takes[0][0].key)
    assert tennis.rate() == 50.0
    assert gen.matrix("holdout", quick=True, seeds=2)[0].group == "holdout"
