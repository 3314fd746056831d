"""A marker outside every trained body is not placed where its named twin on the other side
fits better (``boot_match._twin_fits_better``).

The kneeling performer of the 62-marker take, booted from a model of the take's first 900
frames from frame 906 on (an operator's run through the service, then ``evaluate``): both
forearm plates lie outside every trained body (no mirror segment pairs them). The left arm
was not placed yet when the completion put a left forearm marker on the right forearm's point
beside the placed right upper arm, and the left plate was then read onto the right forearm
for the whole take (2,873 wrong labels, the performer booted and the stream online).
"""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.capture import split_label
from labeler_service.capture.io import read_capture
from labeler_service.labeling.registry import make_labeler


@pytest.mark.realdata
def test_a_left_forearm_is_not_read_onto_the_right_one(real_path):
    from offline.structure import StructureTrainer

    take = read_capture(real_path("kneel_to_prone_62markers_240hz.c3d"))
    model = StructureTrainer().fit([take.frames(0, 900)]).model_
    lab = make_labeler("online", rate=take.rate, model=model, boot=True)
    names = [split_label(n)[1] for n in lab.marker_names]
    col = np.array([names.index(split_label(n)[1]) for n in take.labels])
    rng = np.random.default_rng(0)
    crossed = labeled = 0
    for k in range(906, 906 + 300):
        p = take.positions[k]
        vis = np.isfinite(p).all(axis=1)
        pts, truth = p[vis], col[vis]
        order = rng.permutation(len(pts))
        pts, truth = pts[order], truth[order]
        got = np.asarray(lab.process(pts, (k - 906) / take.rate).point_labels)
        for g, t in zip(got[got >= 0], truth[got >= 0], strict=True):
            labeled += 1
            a, b = names[g][0], names[t][0]  # (the side letters)
            crossed += a in "LR" and b in "LR" and a != b
    assert labeled > 13_000  # (booted: 12,617 before, the right forearm unlabeled)
    assert crossed == 0  # (717 before)
