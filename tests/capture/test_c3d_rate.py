"""A C3D whose POINT:RATE is 0, negative, NaN or past any camera (a broken export) says so;
it said "no POINT:RATE", which sends the user looking for a parameter the file has."""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest

from labeler_service.capture import Capture, read_capture, write_capture
from labeler_service.errors import CaptureFormatError

MARK = 12345.0  # a rate to find in the file's bytes (ezc3d aborts on writing a rate of 0)


@pytest.mark.parametrize("rate", [0.0, -50.0, 0.5, 1e7])
def test_a_rate_no_capture_has_is_named(tmp_path, rng, rate):
    """0 and -50 Hz were refused; 0.5 Hz and 1e7 Hz were read without a word (a C3D has no
    clock of its own to read a rate from instead)."""
    pos = rng.normal(scale=300.0, size=(5, 3, 3)).astype(np.float32)
    path = write_capture(Capture(pos, ("S:a", "S:b", "S:c"), MARK), tmp_path / "r.c3d")
    raw = bytearray(path.read_bytes())
    old, new = struct.pack("<f", MARK), struct.pack("<f", rate)
    assert raw.count(old) >= 1
    path.write_bytes(bytes(raw).replace(old, new))
    why = re.escape(f"frame rate (POINT:RATE) is {rate:g} Hz: expected 1 to 10000 Hz")
    with pytest.raises(CaptureFormatError, match=why):
        read_capture(path)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_nan_rate_is_named_not_left_to_ezc3d(tmp_path, rng, bad):
    """A NaN rate (header and POINT:RATE) makes ezc3d itself fail (it divides by the rate
    while reading: ``vector::_M_default_append``), before the POINT:RATE check can run: the
    header's rate is read first and named."""
    pos = rng.normal(scale=300.0, size=(5, 3, 3)).astype(np.float32)
    path = write_capture(Capture(pos, ("S:a", "S:b", "S:c"), MARK), tmp_path / "r.c3d")
    raw = bytes(path.read_bytes()).replace(struct.pack("<f", MARK), struct.pack("<f", bad))
    path.write_bytes(raw)
    with pytest.raises(CaptureFormatError, match=f"frame rate .*{bad:g}"):
        read_capture(path)
