"""Shared fixtures: seeded RNG, real-data paths (skip with a reason when absent), a real
Mosquitto broker on a free loopback port.

Broker tests are marked ``broker``; without the ``mosquitto`` binary they skip with a reason
(``make test`` installs it via scripts/ensure-mosquitto.sh)."""

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


@pytest.fixture
def broker(tmp_path):
    """A real Mosquitto on a free loopback port, started and stopped by the test."""
    from labeler_service.testing.broker import LocalBroker, mosquitto_binary

    if mosquitto_binary() is None:
        pytest.skip("mosquitto binary not found (make test installs it; apt install mosquitto)")
    b = LocalBroker(tmp_path)
    b.start()
    try:
        yield b
    finally:
        b.close()
