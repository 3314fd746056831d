"""Twin markers in training (offline/structure.twin_pairs, twin_witnesses)."""

from __future__ import annotations

import numpy as np
from labeling.twin_scene import MARKERS, twin_capture

from labeler_service.capture import Capture
from offline.structure import StructureTrainer, twin_pairs, twin_witnesses

RADIUS, ULNA = MARKERS.index("Radius"), MARKERS.index("Ulna")


def _fit():
    cap = twin_capture(2)
    s = StructureTrainer().fit([cap]).model_.subjects[0]
    return cap.positions.astype(np.float64), s


def test_the_symmetric_wrist_markers_are_the_only_twins():
    pos, s = _fit()
    assert twin_pairs(pos, s.D_array(), s.A_array(), s.bodies, s.chirality) == [(RADIUS, ULNA)]


def test_a_chirality_quadruple_the_exchange_reverses_separates_them():
    pos, s = _fit()
    # a quadruple over the pair and the upper arm, as a model trained on a still arm has
    sep = [[RADIUS, ULNA, MARKERS.index("Shoulder"), MARKERS.index("T1")]]
    assert twin_pairs(pos, s.D_array(), s.A_array(), s.bodies, s.chirality + sep) == []
    assert twin_witnesses(pos, s.D_array(), s.A_array(), s.bodies, s.chirality + sep) == []


def test_markers_whose_distances_differ_are_no_twins():
    pos, s = _fit()
    pos = pos.copy()
    # move the ulna marker 25 mm along the forearm: the finger tells the two apart now
    u = pos[:, MARKERS.index("Finger")] - pos[:, MARKERS.index("Elbow")]
    pos[:, ULNA] += 25.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    cap = Capture(pos.astype(np.float32), tuple(f"P:{m}" for m in MARKERS), 120.0)
    s2 = StructureTrainer().fit([cap]).model_.subjects[0]
    assert s2.twin_witnesses == []
