"""A mirror segment placed on one side is not guessed while nothing tells its side
(``boot_match._one_sided``), but a marker of it held to the rest of the subject by a pair of
one trained body is: that marker tells the side.

The kneeling performer of the 62-marker take, model of the take's first 900 frames: the left
wrist triangle (radius, ulna, hand) shares a trained body with the left forearm plate. Dropped
whole beside the placed plate, the next completion put the radius alone on the plate's
proximal point, the labeler added the ulna and hand next to it, and a window mirror test moved
the three to the right arm (a stream whose boot results came 5-80 frames late: 4 of 61 runs).
"""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import split_label
from labeler_service.capture.io import read_capture
from labeler_service.labeling import boot_match
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.booting import prepare_boot


@pytest.mark.realdata
def test_a_wrist_held_by_its_forearm_plate_keeps_its_side(real_path):
    from offline.structure import StructureTrainer

    take = read_capture(real_path("kneel_to_prone_62markers_240hz.c3d"))
    model = StructureTrainer().fit([take.frames(0, 900)]).model_
    booter, _ = prepare_boot(model, BootConfig(), take.rate)
    tpl = booter._templates[0]
    names = [split_label(n)[1] for n in model.marker_names]
    p = take.positions[967]  # (the frame of the late runs' extension)
    vis = np.flatnonzero(np.isfinite(p).all(axis=1))
    assign = np.full(tpl.n, -1, dtype=np.int64)
    for j, c in enumerate(vis):  # every visible marker on its own point ...
        assign[names.index(split_label(take.labels[c])[1])] = j
    # ... but the right forearm and wrist, and the left plate's proximal markers
    hidden = ["RRAD", "RULN", "RHAND", "RFAPA", "RFAPP", "RFADP", "RFADA", "LFAPA", "LFAPP"]
    assign[[names.index(n) for n in hidden]] = -1
    assert all(assign[names.index(n)] >= 0 for n in ("LRAD", "LULN", "LHAND", "LFADA"))
    left = [names[m] for m in boot_match._one_sided(tpl, assign, p[vis])]
    # the radius and ulna keep their distances to the distal plate (one trained body); the
    # hand is held by nothing outside the triangle and waits for its side's evidence
    assert left == ["LHAND"]
