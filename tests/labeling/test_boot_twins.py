"""Twin markers at boot (boot_match._twins): two markers of one body whose exchange no trained
distance and no chirality quadruple tells (a forearm's radius and ulna) are placed by witness
quadruples learned in training (offline/structure.twin_witnesses)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.twin_scene import MARKERS, twin_capture

from labeler_service.capture import read_capture, split_label
from labeler_service.labeling.boot import BootConfig, Booter
from labeler_service.labeling.boot_match import _complete, _exchange, _twin_votes, _twins
from labeler_service.labeling.booting import BootingLabeler
from labeler_service.labeling.templates import LabelerModel
from offline.structure import StructureTrainer

RADIUS, ULNA = MARKERS.index("Radius"), MARKERS.index("Ulna")


@pytest.fixture(scope="module")
def model() -> LabelerModel:
    return StructureTrainer().fit([twin_capture(1)]).model_


def _bare(model: LabelerModel) -> LabelerModel:
    """The same model without witnesses (as a model file from before them)."""
    s = model.subjects[0].model_copy(update={"twin_witnesses": []})
    return model.model_copy(update={"subjects": [s]})


def _window(seed: int) -> np.ndarray:
    """``(N, W, 3)``: a 12-frame window of an unseen segment, point ``k`` = marker ``k``."""
    cap = twin_capture(seed, frames=60)
    return np.transpose(cap.positions[-12:].astype(np.float64), (1, 0, 2))


def test_the_model_has_witnesses_of_the_forearm_pair_only(model):
    w = np.asarray(model.subjects[0].twin_witnesses)
    assert w.shape[0] >= 3
    assert {tuple(sorted(q[:2])) for q in w.tolist()} == {(RADIUS, ULNA)}


def test_witnesses_keep_their_sign_in_training_and_reverse_on_exchange(model):
    pos = twin_capture(1).positions.astype(np.float64)
    for q in model.subjects[0].twin_witnesses:
        p = pos[:, q]
        det = np.linalg.det(p[:, 1:] - p[:, :1])
        assert np.mean(det > 0) >= 0.99
        swapped = pos[:, [q[1], q[0], q[2], q[3]]]
        assert np.mean(np.linalg.det(swapped[:, 1:] - swapped[:, :1]) < 0) >= 0.99


def test_an_exchanged_twin_pair_is_put_back_and_the_distances_cannot(model):
    tpl = Booter(model)._templates[0]
    for seed in (12, 13, 14):
        hist = _window(seed)
        pts = hist[:, -1]
        assign = np.arange(len(MARKERS))
        assign[[RADIUS, ULNA]] = [ULNA, RADIUS]
        if seed == 13:
            by_distance = assign.copy()
            _exchange(tpl, by_distance, pts)
            assert by_distance[RADIUS] == ULNA  # the pair distances leave it as it is
        _twins(tpl, assign, pts, hist)
        np.testing.assert_array_equal(assign, np.arange(len(MARKERS)))
        # ... and a right reading stays right
        _twins(tpl, assign, pts, hist)
        np.testing.assert_array_equal(assign, np.arange(len(MARKERS)))


def test_a_witness_near_its_flipping_pose_abstains(model):
    """Seed 13's last frames bring the finger beside two trunk markers' plane: two witnesses
    are near zero there (one slightly reversed on the right reading); counted as votes they
    split the pair 4 to 2 and nothing was put back."""
    tpl = Booter(model)._templates[0]
    hist = _window(13)
    right = np.arange(len(MARKERS))
    kept, rev, _, _ = _twin_votes(tpl, right, hist)[(RADIUS, ULNA)]
    assert rev == 0 and kept >= 3


def test_boot_reads_the_twin_pair_right_only_with_witnesses(model):
    hist = _window(35)
    got = Booter(model).run(hist[:, -1], hist).labels
    np.testing.assert_array_equal(got, np.arange(len(MARKERS)))
    bare = Booter(_bare(model)).run(hist[:, -1], hist).labels
    assert bare[RADIUS] == ULNA and bare[ULNA] == RADIUS  # the limit without witnesses


@pytest.mark.realdata
def test_dance_forearm_boots_the_right_way_round(real_path):
    """The lead's reproduction: the dancer's left radius and ulna markers (271.8 and 277.5 mm
    from the elbow, 143.4 and 143.1 from the finger) were exchanged for all 480 frames of the
    scored segment by a model of a later segment (0.9185 correct)."""
    cap = read_capture(real_path("dance_qualisys_28markers_60hz.c3d"))
    model = StructureTrainer().fit([cap.frames(540, 1020)]).model_
    names = model.subjects[0].markers
    pair = {names.index("Radius_L"), names.index("Ulna_L")}
    assert any(set(q[:2]) == pair for q in model.subjects[0].twin_witnesses)
    seg = cap.frames(0, 480)
    col = {split_label(lab)[1]: i for i, lab in enumerate(seg.labels)}
    lab = BootingLabeler(model, cap.rate)
    rng = np.random.default_rng(0)
    wrong = seen = 0
    for f in range(seg.n_frames):
        p = seg.positions[f]
        vis = rng.permutation(np.flatnonzero(np.isfinite(p[:, 0])))  # anonymous, any order
        out = np.asarray(lab.process(p[vis], f / cap.rate).point_labels)
        for name in ("Radius_L", "Ulna_L"):
            k = np.flatnonzero(vis == col[name])
            if f >= 30 and k.size:  # from 0.5 s
                seen += 1
                wrong += int(out[k[0]] >= 0 and out[k[0]] != names.index(name))
    assert seen > 800
    assert wrong == 0


def test_completion_places_a_new_twin_pair_the_right_way_round(model):
    """The subject booted without its wrist markers; the completion (``_complete``) adds them.
    Without witnesses it read them exchanged in 12 of these 20 unseen windows; with them, when
    the witnesses are counted as plain votes, in 2 (seeds 10 and 21: two witnesses over the
    finger and the trunk clearly flipped, 4 to 2); weighed by their evidence, in none."""
    config = BootConfig()
    twins = Booter(model)._templates[0]
    bare = Booter(_bare(model))._templates[0]
    wrong_bare = 0
    for seed in range(10, 30):
        hist = _window(seed)
        pts = hist[:, -1]
        assign = np.arange(len(MARKERS))
        assign[[RADIUS, ULNA]] = -1
        taken = np.zeros(len(MARKERS), dtype=bool)
        got = _complete(twins, assign, pts, hist, taken, config)
        assert got[RADIUS] == RADIUS and got[ULNA] == ULNA, seed
        wrong_bare += int(_complete(bare, assign, pts, hist, taken, config)[RADIUS] == ULNA)
    assert wrong_bare >= 8
