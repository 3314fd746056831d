"""A real Mosquitto broker on a free loopback port, started and stopped by the test.

Tests that use it are marked ``broker``; without the ``mosquitto`` binary they skip with a
reason (``make test`` installs it via scripts/ensure-mosquitto.sh).
"""

from __future__ import annotations

import pytest

from labeler_service.testing.broker import LocalBroker, mosquitto_binary


@pytest.fixture
def broker(tmp_path):
    if mosquitto_binary() is None:
        pytest.skip("mosquitto binary not found (make test installs it; apt install mosquitto)")
    b = LocalBroker(tmp_path)
    b.start()
    try:
        yield b
    finally:
        b.close()
