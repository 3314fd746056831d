"""A C3D without a POINT:UNITS parameter: millimetres unless its coordinates can only be metres.

Some exporters leave UNITS out. Read as millimetres, a take in metres is a body 2 mm tall: the
labeler's gates (tens of millimetres) take every marker for every other, and a labeled start
scored 0.00007 on such a copy of the tennis take (0.989 from the same take in metres with
UNITS = "m"). No person fits within 50 mm of the origin, so coordinates that all do are metres.
"""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import read_capture

ezc3d = pytest.importorskip("ezc3d")


def _write(path, pos_mm_like: np.ndarray, units: str | None) -> None:
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    n = pos_mm_like.shape[1]
    c["parameters"]["POINT"]["LABELS"]["value"] = [f"S:m{i}" for i in range(n)]
    if units is not None:
        c.add_parameter("POINT", "UNITS", [units])
    pts = np.ones((4, n, pos_mm_like.shape[0]))
    pts[:3] = np.transpose(pos_mm_like, (2, 1, 0))
    c["data"]["points"] = pts
    c.write(str(path))


def _body(rng) -> np.ndarray:
    """10 frames of 5 markers of a person standing 2 m from the origin, in millimetres."""
    base = np.array([[2000.0, 500.0, 1700.0], [2100, 450, 1400], [1950, 520, 1000],
                     [2050, 480, 500], [2000, 500, 80]])  # fmt: skip
    return base[None] + rng.normal(scale=5.0, size=(10, 5, 3))


def test_no_units_and_metre_sized_coordinates_read_as_metres(tmp_path, rng) -> None:
    pos = _body(rng)
    _write(tmp_path / "m.c3d", pos / 1000.0, units=None)
    cap = read_capture(tmp_path / "m.c3d")
    np.testing.assert_allclose(cap.positions, pos, atol=0.05)
    assert any("no UNITS parameter" in n and "metres" in n for n in cap.notes), cap.notes


def test_no_units_and_millimetre_coordinates_stay_millimetres(tmp_path, rng) -> None:
    pos = _body(rng)
    _write(tmp_path / "mm.c3d", pos, units=None)
    cap = read_capture(tmp_path / "mm.c3d")
    np.testing.assert_allclose(cap.positions, pos, atol=1e-3)
    assert "no UNITS parameter: assumed mm" in cap.notes


def test_declared_units_are_trusted(tmp_path, rng) -> None:
    pos = _body(rng) / 1000.0
    _write(tmp_path / "said_mm.c3d", pos, units="mm")
    cap = read_capture(tmp_path / "said_mm.c3d")
    np.testing.assert_allclose(cap.positions, pos, atol=1e-6)
    # but a body 2 mm tall is said: the labeler labels nothing on it
    assert any("UNITS says mm" in n and "metres" in n for n in cap.notes), cap.notes


def test_metres_said_of_millimetre_coordinates_are_doubted(tmp_path, rng) -> None:
    """UNITS "m" on coordinates in millimetres read as a body 1.7 km tall with no word but a
    Y-up guess that contradicted itself; now the reader says the take may be in millimetres
    (the units are still trusted: the note says what to fix). A TRC's Units alike."""
    from labeler_service.capture import Capture, write_capture

    pos = _body(rng)
    _write(tmp_path / "said_m.c3d", pos, units="m")
    cap = read_capture(tmp_path / "said_m.c3d")
    np.testing.assert_allclose(cap.positions, pos * 1000.0, rtol=1e-6)
    assert any("UNITS says m" in n and "millimetres" in n for n in cap.notes), cap.notes
    trc = tmp_path / "t.trc"
    write_capture(Capture(pos, tuple(f"S:m{i}" for i in range(5)), 100.0), trc)
    lines = trc.read_text().splitlines()
    lines[2] = lines[2].replace("\tmm\t", "\tm\t")
    trc.write_text("\n".join(lines) + "\n")
    cap = read_capture(trc)
    assert any("Units says m" in n and "millimetres" in n for n in cap.notes), cap.notes
    _write(tmp_path / "ok.c3d", pos / 1000.0, units="m")
    assert not any("millimetres" in n for n in read_capture(tmp_path / "ok.c3d").notes)


@pytest.mark.parametrize(
    "units, scale",
    [("meter", 1000.0), ("Metres", 1000.0), ("millimetre", 1.0), ("MM", 1.0),
     ("centimeters", 10.0), ("cm ", 10.0)],
)  # fmt: skip
def test_other_spellings_of_the_units(tmp_path, rng, units, scale):
    """'meter' stopped the read with "unknown point units 'meter'"."""
    pos = _body(rng) / scale
    _write(tmp_path / "u.c3d", pos, units=units)
    cap = read_capture(tmp_path / "u.c3d")
    np.testing.assert_allclose(cap.positions, pos * scale, rtol=1e-5, atol=0.05)
