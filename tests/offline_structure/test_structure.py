"""``StructureTrainer`` and ``train structure``: templates from labeled captures."""

from __future__ import annotations

import json

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main
from labeler_service.errors import ModelError
from labeler_service.labeling.labeler import Labeler
from labeler_service.labeling.templates import load_model
from offline.structure import StructureTrainer, chirality_quads


def _capture(rng, subjects=2, frames=200):
    pos, names = articulated(rng, subjects=subjects, frames=frames)
    return Capture(pos, names, 120.0, source="synthetic")


def test_fit_learns_one_template_per_subject(rng):
    cap = _capture(rng)
    est = StructureTrainer(max_size=4)
    assert not hasattr(est, "model_")
    assert est.fit([cap]) is est
    model = est.model_
    assert [s.name for s in model.subjects] == ["P0", "P1"]
    for s in model.subjects:
        assert {i for b in s.bodies for i in b} == set(range(8))
        assert all(3 <= len(b) <= 4 for b in s.bodies)
        # each body lies on one rigid segment (a* or b* markers), never across the joint
        for b in s.bodies:
            assert len({s.markers[i][0] for i in b}) == 1
        shapes = [np.asarray(x) for x in s.shapes]
        for b, shape in zip(s.bodies, shapes, strict=True):
            np.testing.assert_allclose(shape.mean(axis=0), 0, atol=1e-3)
            d_shape = np.linalg.norm(shape[:, None] - shape[None], axis=2)
            np.testing.assert_allclose(d_shape, s.D_array()[np.ix_(b, b)], atol=1.0)
        assert all(q > 0 for q in s.motion_noise)


def test_fit_is_deterministic_and_pools_captures(rng):
    a = _capture(rng, frames=120)
    b = _capture(np.random.default_rng(7), frames=80)
    m1 = StructureTrainer().fit([a, b]).model_
    m2 = StructureTrainer().fit([a, b]).model_
    assert m1.model_dump() == m2.model_dump()
    assert StructureTrainer().fit([a, b]).n_frames_ == 200


def test_model_drives_labeler_from_one_labeled_frame(rng):
    cap = _capture(rng, frames=300)
    model = StructureTrainer().fit([cap.frames(0, 100)]).model_
    lab = Labeler.from_model(model, 120.0)
    order = [cap.labels.index(n) for n in lab.marker_names]
    pos = cap.positions[:, order]
    correct = 0
    for f in range(100, 300):
        perm = rng.permutation(pos.shape[1])
        out = lab.process(pos[f, perm], f / 120.0, perm if f == 100 else None)
        correct += int(np.count_nonzero(out.point_labels == perm))
    assert correct == 200 * pos.shape[1]


def test_unlabeled_capture_is_a_model_error(rng):
    cap = _capture(rng, subjects=1, frames=20)
    raw = Capture(cap.positions, tuple(f"*{i}" for i in range(cap.n_markers)), 120.0)
    with pytest.raises(ModelError, match="no labeled markers"):
        StructureTrainer().fit([raw])
    with pytest.raises(ModelError, match="at least one capture"):
        StructureTrainer().fit([])


def test_cli_writes_a_loadable_model(rng, tmp_path, capsys):
    cap = _capture(rng, frames=150)
    src = tmp_path / "take.npz"
    write_capture(cap, src)
    out = tmp_path / "model.json"
    assert main(["train", "structure", str(src), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["subjects"]["P0"]["markers"] == 8
    model = load_model(out)
    assert model.version == 1 and len(model.subjects) == 2
    # the summary tells how many chirality quadruples each subject learned
    for s in model.subjects:
        assert summary["subjects"][s.name]["chirality"] == len(s.chirality)
    assert main(["train", "structure", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for s in model.subjects:
        assert f"{s.name}: 8 markers in" in text and "chirality quadruples" in text
    assert summary["subjects"]["P0"]["no_body"] == [] and "never labeled" not in text
    assert load_model(out).source == str(src)
    # a model trained on segments names their frames (it said the whole take: a train / test
    # split looked like training on the frames scored)
    assert main(["train", "structure", f"{src}:0:100", f"{src}:120", "--out", str(out)]) == 0
    assert load_model(out).source == f"{src}:0:100, {src}:120"


def test_cli_says_when_two_subjects_have_one_template(rng, tmp_path, capsys):
    """A take and its copy 2 m away under another name (the tennis data's two players): one
    template, which a boot cannot tell apart; the summary and the text say so. Two different
    performers are not flagged (test above: ``same_template`` empty)."""
    cap = _capture(rng, subjects=1, frames=150)
    copy = cap.positions + np.array([2000.0, 0.0, 0.0], dtype=np.float32)
    names = list(cap.labels) + [n.replace("P0:", "Q0:") for n in cap.labels]
    pair = Capture(np.concatenate([cap.positions, copy], axis=1), names, cap.rate)
    src = tmp_path / "pair.npz"
    write_capture(pair, src)
    out = tmp_path / "model.json"
    assert main(["train", "structure", str(src), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["same_template"] == [["P0", "Q0"]]
    assert main(["train", "structure", str(src), "--out", str(out)]) == 0
    assert "P0 and Q0 have one template" in capsys.readouterr().out
    two = tmp_path / "two.npz"
    write_capture(_capture(rng, frames=150), two)
    assert main(["train", "structure", str(two), "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["same_template"] == []


def test_cli_names_a_split_track_that_will_never_be_labeled(rng, tmp_path, capsys):
    """A second name for one physical marker (4 mm off it, for 10 frames) is left out of the
    bodies, and the summary says which marker will never be labeled."""
    cap = _capture(rng, subjects=1, frames=150)
    dup = np.full((cap.n_frames, 1, 3), np.nan, dtype=np.float32)
    dup[40:50, 0] = cap.positions[40:50, 0] + np.array([4.0, 0.0, 0.0], dtype=np.float32)
    name = cap.labels[0] + "-1"
    cap = Capture(np.concatenate([cap.positions, dup], axis=1), (*cap.labels, name), cap.rate)
    src = tmp_path / "take.npz"
    write_capture(cap, src)
    out = tmp_path / "model.json"
    assert main(["train", "structure", str(src), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["subjects"]["P0"]["no_body"] == [name.split(":")[1]]
    assert main(["train", "structure", str(src), "--out", str(out)]) == 0
    assert "never labeled (no body" in capsys.readouterr().out


def test_cli_refuses_a_subject_it_could_never_label(rng, tmp_path, capsys):
    """A take in which only two of a subject's markers are ever seen trained a model of one
    two-marker body (exit 0); the labeler needs three markers to see a subject present, so
    that template labels nothing, and the boot then blamed the performers' distances. It is
    refused, naming the subject and what was seen, and no model is written."""
    cap = _capture(rng, subjects=2, frames=120)
    pos = cap.positions.copy()
    p1 = [i for i, name in enumerate(cap.labels) if name.startswith("P1:")]
    pos[:, p1[2:]] = np.nan  # P1: two markers seen
    src = tmp_path / "take.npz"
    write_capture(Capture(pos, cap.labels, cap.rate), src)
    out = tmp_path / "model.json"
    assert main(["train", "structure", str(src), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"to ever label this subject: P1 (2 of {len(p1)})" in err, err
    assert not out.exists()
    pos[:, p1[2]] = cap.positions[:, p1[2]]  # three: enough
    write_capture(Capture(pos, cap.labels, cap.rate), src)
    assert main(["train", "structure", str(src), "--out", str(out)]) == 0


@pytest.mark.realdata
def test_technical_clusters_each_land_in_one_body(real_path):
    model = StructureTrainer().fit([real_path("clusters_73markers_100hz.c3d")]).model_
    s = model.subjects[0]
    groups = {
        "LARM": ["LARM1", "LARM2", "LARM3"],
        "LFARM": ["LFARM1", "LFARM2", "LFARM3"],
        "RARM": ["RAMR1", "RARM2", "RARM3"],  # (sic) the file's spelling
        "RFARM": ["RFARM1", "RFARM2", "RFARM3"],
        "LTHI": ["LTHI1", "LTHI2", "LTHI3"],
        "RTHI": ["RTHI1", "RTHI2", "RTHI3"],
        "LLEG": ["LLEG1", "LLEG2", "LLEG3"],
        "RLEG": ["RLEG1", "RLEG2", "RLEG3"],
    }
    for name, members in groups.items():
        idx = {s.markers.index(m) for m in members}
        assert any(idx <= set(b) for b in s.bodies), f"{name} cluster split across bodies"
    assert {i for b in s.bodies for i in b} == set(range(len(s.markers)))


def test_a_body_never_seen_whole_gets_the_handedness_of_the_frames(tmp_path):
    """Five markers on one rigid plate, tumbling, but never all five seen in one frame: the
    body's reference shape then comes from its distances alone (multidimensional scaling),
    which are the same for the plate and its mirror image, so one of the two gets a shape of
    the wrong hand. The chirality quadruples come from the frames; the shape is turned to agree
    with them, so both saved models load (a shape reversing a quadruple inside its body is
    refused as a mirror image) and neither shape is a mirror of its plate."""
    from scipy.spatial.transform import Rotation

    from labeler_service.labeling.templates import save_model
    from offline.structure import handed_shapes

    n = 300
    t = np.arange(n) / 120.0
    rot = Rotation.from_rotvec(np.outer(t, [1.5, 0.8, 0.4])).as_matrix()  # a slow tumble
    for hand in (1.0, -1.0):
        plate = np.array(
            [[0, 0, 0], [120, 0, 0], [0, 90, 0], [30, 40, 70], [100, 80, 40]], float
        ) * np.array([1.0, 1.0, hand])
        pos = np.einsum("fij,mj->fmi", rot, plate) + np.outer(t, [300, 100, 0])[:, None, :]
        for f in range(n):  # one marker hidden in every frame, in turn
            pos[f, f % 5] = np.nan
        cap = Capture(pos.astype(np.float32), [f"S:m{i}" for i in range(5)], 120.0, source="p")
        model = StructureTrainer(min_size=3, max_size=5).fit([cap]).model_
        s = model.subjects[0]
        assert s.chirality, "the plate is thick: quadruples expected"
        whole = [b for b in s.bodies if len(b) == 5]
        assert whole, s.bodies
        path = tmp_path / f"m{hand:+.0f}.json"
        save_model(model, path)
        shape = np.asarray(load_model(path).subjects[0].shapes[s.bodies.index(whole[0])])
        src = shape - shape.mean(axis=0)
        dst = plate[whole[0]] - plate[whole[0]].mean(axis=0)
        u, _, vt = np.linalg.svd(src.T @ dst)
        assert np.linalg.det(u @ vt) > 0  # a proper rotation maps the shape onto the plate
    # handed_shapes itself: a shape reversing a quadruple inside its body is mirrored, one
    # that keeps it is kept
    quad = [q for q in s.chirality if set(q) <= set(whole[0])][0]
    mirrored = (dst * np.array([1, 1, -1])).tolist()
    np.testing.assert_allclose(np.asarray(handed_shapes([mirrored], [whole[0]], [quad])[0]), dst)
    assert handed_shapes([dst.tolist()], [whole[0]], [quad])[0] == dst.tolist()


def test_chirality_quadruples_across_a_hinge_need_no_steady_pairs():
    """Two bodies sharing two markers (a hinge: a foot and its ankle-knee body) give a
    quadruple whose far pair (knee to toe) changes by far more than 20 mm as the hinge turns,
    yet whose volume keeps its sign: it is learned when the bodies are given, not without."""
    ang = np.linspace(np.radians(30), np.radians(150), 60)  # hinge angle, never flat
    pos = np.zeros((ang.size, 4, 3))
    pos[:, 1] = [100.0, 0.0, 0.0]  # the hinge axis: markers 0 and 1 along x
    pos[:, 2] = [50.0, 120.0, 0.0]  # marker 2 on body one
    pos[:, 3, 0] = 50.0  # marker 3 on body two, turning about the axis
    pos[:, 3, 1] = 120.0 * np.cos(ang)
    pos[:, 3, 2] = 120.0 * np.sin(ang)
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=3)
    A = d.max(axis=0) - d.min(axis=0)
    assert A[2, 3] > 20.0
    assert chirality_quads(pos, A) == []
    quads = chirality_quads(pos, A, [[0, 1, 2], [0, 1, 3]])
    assert len(quads) == 1 and sorted(quads[0]) == [0, 1, 2, 3]
    a, b, c, e = quads[0]
    det = np.linalg.det(
        np.stack([pos[:, b] - pos[:, a], pos[:, c] - pos[:, a], pos[:, e] - pos[:, a]], axis=1)
    )
    assert np.all(det > 0)


def test_markers_that_kept_still_give_no_chirality_across_bodies(rng):
    """Steadiness is evidence of one rigid piece only for markers that moved against some
    partner: in a still capture (a kneeling segment) no quadruple across bodies is chosen for
    it, while quadruples inside a body still are."""
    from labeler_service.labeling.structure import _hinge_quads

    pos = rng.uniform(-300.0, 300.0, size=(1, 16, 3)) + rng.normal(scale=0.5, size=(40, 16, 3))
    cap = Capture(pos.astype("float32"), tuple(f"s:m{i}" for i in range(16)), 50.0)
    subj = StructureTrainer().fit([cap]).model_.subjects[0]
    inside = _hinge_quads(subj.bodies)
    assert subj.chirality
    assert all(tuple(sorted(q)) in inside for q in subj.chirality)
