"""Booter.extend on a template with untrained markers (never seen in its training frames):
new markers need rigid evidence, and there is no joint fill."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.boot import BootConfig, Booter, _rigid_only, _untrained
from labeler_service.labeling.templates import LabelerModel
from labeler_service.scenes.simulate import simulate_scene

RATE = 120.0


@pytest.fixture(scope="module")
def walk():
    """P1 of a simulated walk: a full model, and one trained with LFIN never seen."""
    from offline.structure import StructureTrainer

    cap = simulate_scene(1, 4.0, "walk", seed=7, rate=RATE)
    half = cap.n_frames // 2
    train = cap.frames(0, half)
    full: LabelerModel = StructureTrainer().fit([train]).model_
    blind_pos = train.positions.copy()
    blind_pos[:, train.labels.index("P1:LFIN")] = np.nan
    blind = StructureTrainer().fit([train.with_positions(blind_pos)]).model_
    return full, blind, cap.frames(half, cap.n_frames)


def _frame(model: LabelerModel, cap):
    """The first frame whose 12-frame window sees every marker; point ``i`` is marker ``i``."""
    names = [f"P1:{n}" for n in model.subjects[0].markers]
    cols = [cap.labels.index(n) for n in names]
    seen = np.isfinite(cap.positions[:, cols, 0]).all(axis=1)
    f = next(f for f in range(11, cap.n_frames) if seen[f - 11 : f + 1].all())
    hist = np.transpose(cap.positions[f - 11 : f + 1][:, cols], (1, 0, 2)).astype(float)
    return np.ascontiguousarray(hist[:, -1]), hist, list(model.subjects[0].markers)


def test_untrained_markers_are_found(walk):
    from labeler_service.labeling.boot_match import _prepare

    full, blind, _ = walk
    assert not _untrained(_prepare(full, BootConfig())[0]).any()
    names = list(blind.subjects[0].markers)
    assert np.flatnonzero(_untrained(_prepare(blind, BootConfig())[0])).tolist() == [
        names.index("LFIN")
    ]
    assert Booter(full)._blind == [False] and Booter(blind)._blind == [True]


def test_rigid_only_keeps_markers_with_two_rigid_pairs(walk):
    from labeler_service.labeling.boot_match import _prepare

    full, _, cap = walk
    tpl = _prepare(full, BootConfig())[0]
    pts, _, names = _frame(full, cap)
    grown = np.arange(tpl.n)
    support = [
        int(np.count_nonzero(tpl.strict[m] & (np.abs(
            np.linalg.norm(pts - pts[m], axis=1) - tpl.D[m]) <= tpl.tol[m])))
        for m in range(tpl.n)
    ]  # fmt: skip
    strong = next(m for m in range(tpl.n) if support[m] >= 2)
    assign = grown.copy()
    assign[strong] = -1
    assert np.array_equal(_rigid_only(tpl, assign, grown, pts), grown)  # placed right: kept
    # the same marker on a point far from its body partners: no rigid pair holds
    far = pts.copy()
    far = np.vstack([far, pts[strong] + 400.0])
    wrong = grown.copy()
    wrong[strong] = far.shape[0] - 1
    out = _rigid_only(tpl, assign, wrong, far)
    assert out[strong] == -1 and np.array_equal(np.delete(out, strong), np.delete(wrong, strong))


def test_extension_of_a_blind_template_places_only_rigidly_supported_markers(walk):
    """With LFIN untrained the hand and wrist markers hidden at once come back only where two
    rigid pairs vouch for them; the full template's extension (with the joint fill) places
    them all."""
    from labeler_service.labeling.boot_match import _prepare

    full, blind, cap = walk
    for model in (full, blind):
        tpl = _prepare(model, BootConfig())[0]
        pts, hist, names = _frame(model, cap)
        ix = {n: i for i, n in enumerate(names)}
        labels = np.arange(tpl.n) + tpl.offset
        hidden = [ix[n] for n in ("LWRA", "LWRB", "LHM2", "LHM5")]
        labels[hidden] = -1
        labels[ix["LFIN"]] = -1
        out = Booter(model).extend(pts, hist, labels, [0], np.full(tpl.n, 1.0))
        new = np.flatnonzero((labels < 0) & (out >= 0))
        assert np.all(out[new] == new + tpl.offset)  # never a wrong marker
        if model is blind:
            assert out[ix["LFIN"]] == -1  # untrained: no evidence places it
            for m in new:
                d = np.linalg.norm(pts[out >= 0] - pts[m], axis=1)
                k = out[out >= 0] - tpl.offset
                ok = tpl.strict[m, k] & (np.abs(d - tpl.D[m, k]) <= tpl.tol[m, k])
                assert np.count_nonzero(ok) >= 2
