"""Shared fixtures: seeded RNG, real-data paths (skip with a reason when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labeler_service.testing.realdata import real_data_dir


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def real_dir() -> Path:
    d = real_data_dir()
    if d is None:
        pytest.skip("real captures not found: set MOCAP_DATA_DIR or place ../shared/data/real")
    return d


@pytest.fixture(scope="session")
def real_path(real_dir: Path):
    """``real_path(name)``: a real capture's path, skipping when that file is missing."""

    def get(name: str) -> Path:
        p = real_dir / name
        if not p.is_file():
            pytest.skip(f"real capture {name} not found in {real_dir}")
        return p

    return get
