"""A loose body's candidate on points a rigid plate of another segment explains better is
dropped (``boot_match._undominated``).

The kneeling performer booted from a model of the take's first 900 frames (its HIGH run
through the service, then ``evaluate kneel:920``): the model's loose triangles of the wrist,
ulna and hand markers (tolerances 10-20 mm) fit three points of each upper-arm plate (66 / 97
/ 84 mm against 72 / 108 / 80 mm), where the plate fits all four within a millimetre. The
completion read both wrists onto the upper-arm plates from the boot's first frame on (5,511
wrong labels over the take, the arms otherwise unlabeled)."""

from __future__ import annotations

import pytest

from tests.labeling.kneel import kneel_labeled

WRISTS = {"RRAD", "RULN", "RHAND", "LRAD", "LULN", "LHAND"}
PLATES = {f"{s}UA{p}" for s in "RL" for p in ("PA", "PP", "DP", "DA")}


@pytest.mark.realdata
def test_a_wrist_is_not_read_on_an_upper_arm_plate(real_path):
    on_plate = plate_right = 0
    for given, true in kneel_labeled(real_path, 920, 300):
        if true in PLATES:
            on_plate += given in WRISTS
            plate_right += given == true
    assert on_plate == 0  # (1,656 before: from the boot's first frame on)
    assert plate_right > 1_500  # (8 plate markers, 300 frames: 0 before)
