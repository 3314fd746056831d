"""Starting from a model with no labels: ``train structure TAKE:start:stop``, ``label --model``
on an unlabeled take, ``evaluate --model --init-frames 0 [--leave]``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.capture import Capture, read_capture, split_label, write_capture
from labeler_service.cli.main import main
from labeler_service.labeling.templates import load_model
from labeler_service.scenes.simulate import simulate_scene

RATE = 120.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three walkers, 8 s: the model is trained on the second half, scored on the first."""
    d = tmp_path_factory.mktemp("boot")
    cap = simulate_scene(3, 8.0, "walk", seed=4, rate=RATE, ghosts=1.0)
    path = d / "walk.npz"
    write_capture(cap, path)
    model = d / "m.json"
    half = cap.n_frames // 2
    assert main(["train", "structure", f"{path}:{half}:{cap.n_frames}", "--out", str(model)]) == 0
    test = d / "test.npz"
    write_capture(cap.frames(0, half), test)
    return d, cap, path, model, test


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_train_structure_on_a_frame_range_names_subjects_like_compose(scene, tmp_path, capsys):
    d, cap, path, model, _ = scene
    m = load_model(model)
    assert [s.name for s in m.subjects] == ["P1", "P2", "P3"]
    # an unprefixed single-person take trains the subject named by its file stem
    cols = cap.subject_columns("P2")
    bare = Capture(
        cap.positions[:, cols], tuple(split_label(cap.labels[i])[1] for i in cols), cap.rate
    )
    solo = tmp_path / "solo_take.npz"
    write_capture(bare, solo)
    out = tmp_path / "solo.json"
    assert main(["train", "structure", f"{solo}:0:400", "--out", str(out), "--json"]) == 0
    summary = _last_json(capsys)
    assert list(summary["subjects"]) == ["solo_take"] and summary["frames"] == 400
    args = ["train", "structure", str(solo), "--rename", "solo_take=P2", "--out", str(out)]
    assert main(args) == 0
    assert [s.name for s in load_model(out).subjects] == ["P2"]
    for bad, why in ((f"{solo}:5:2", "start < stop"), (f"{solo}:x", "TAKE[:start[:stop]]"),
                     (f"{solo}:99999", "past the take"),
                     (f"{solo}:100:99999", "stop 99999 is past the take")):  # fmt: skip
        assert main(["train", "structure", bad, "--out", str(out)]) == 2
        assert why in capsys.readouterr().err
    assert main(["train", "structure", str(solo), "--rename", "nope", "--out", str(out)]) == 2
    assert "OLD=NEW" in capsys.readouterr().err
    # a misspelt OLD renamed nothing and the model kept the old name, silently
    args = ["train", "structure", str(solo), "--rename", "solo-take=P2", "--out", str(out)]
    assert main(args) == 2
    assert "no subject 'solo-take' in the takes (found solo_take)" in capsys.readouterr().err


def test_train_structure_keeps_two_people_of_one_name_apart(scene, tmp_path, capsys):
    """One subject name in two inputs is one person's template: two different marker sets
    under one name are refused (they were merged into a template that fitted neither), and
    ``--rename K:OLD=NEW`` names a subject in one input only (as ``compose`` names a second
    subject of the same name ``NAME_2``)."""
    d, cap, path, _, _ = scene
    p1, p2 = cap.subject_columns("P1"), cap.subject_columns("P2")
    other = Capture(
        cap.positions[:, p2[:10]],
        tuple(f"P1:X{i}" for i in range(10)),  # P2's body, other markers, named P1
        cap.rate,
    )
    impostor = tmp_path / "impostor.npz"
    write_capture(other, impostor)
    one = tmp_path / "p1.npz"
    write_capture(cap.select(list(p1)), one)
    out = tmp_path / "m.json"
    assert main(["train", "structure", f"{one}:0:400", f"{impostor}:0:400", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "subject P1: input 1" in err and "0 of them in common" in err
    assert "--rename 2:P1=NEW" in err and not out.exists()
    # a clash made by a rename names the take's own name in the way out
    renamed = tmp_path / "other.npz"
    write_capture(Capture(other.positions, tuple(f"Q:X{i}" for i in range(10)), cap.rate), renamed)
    args = ["train", "structure", f"{one}:0:400", f"{renamed}:0:400", "--rename", "2:Q=P1",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 2
    assert "--rename 2:Q=NEW" in capsys.readouterr().err
    args = ["train", "structure", f"{one}:0:400", f"{impostor}:0:400", "--rename", "2:P1=P1_2",
            "--out", str(out), "--json"]  # fmt: skip
    assert main(args) == 0
    summary = _last_json(capsys)
    assert summary["subjects"]["P1"]["markers"] == len(p1)
    assert summary["subjects"]["P1_2"]["markers"] == 10
    # two segments of one person under one name stay one template
    args = ["train", "structure", f"{one}:0:300", f"{one}:300:600", "--out", str(out), "--json"]
    assert main(args) == 0
    assert list(_last_json(capsys)["subjects"]) == ["P1"]
    for bad, why in (
        (["--rename", "3:P1=Q"], "only 2 inputs given"),
        (["--rename", "P1=a=b"], "no ':' or '=' in NEW"),
        (["--rename", "\u00b2:P1=Q"], "K:OLD=NEW"),
        (["--rename", "P1=Q", "--rename", "P1=R"], "renamed twice"),
        (["--rename", "2:P2=Q"], "no subject 'P2' in input 2"),
        (["--rename", "x:P1=Q"], "K:OLD=NEW"),
        (["--rename", "0:P1=Q"], "from 1"),
    ):
        assert main(["train", "structure", str(one), str(impostor), *bad, "--out", str(out)]) == 2
        assert why in capsys.readouterr().err


def test_train_structure_refuses_a_rename_that_merges_two_people_of_one_take(
    scene, tmp_path, capsys
):
    """``--rename P2=P1`` (or ``P1=A --rename P2=A``) on a take of three walkers made one
    template of two people, silently (a hostile run on the tennis file: ``Derrick=Viktor``
    trained one subject of 39 markers where the take has two). A swap of names is fine."""
    d, cap, path, _, _ = scene
    out = tmp_path / "m.json"
    for ren in (["--rename", "P2=P1"], ["--rename", "P1=A", "--rename", "P2=A"]):
        assert main(["train", "structure", f"{path}:0:300", *ren, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "would have subjects P1 and P2 both named" in err and not out.exists()
    args = ["train", "structure", f"{path}:0:300", "--rename", "P1=P2", "--rename", "P2=P1",
            "--out", str(out), "--json"]  # fmt: skip
    assert main(args) == 0
    assert sorted(_last_json(capsys)["subjects"]) == ["P1", "P2", "P3"]


@pytest.mark.parametrize(
    ("option", "value", "why"),
    [("--tolerance-mm", "nan", "(--tolerance-mm) must be a finite distance > 0"),
     ("--tolerance-mm", "0", "(--tolerance-mm) must be"),
     ("--distance-weight", "nan", "(--distance-weight) must be a finite number >= 0"),
     ("--distance-weight", "-5", "(--distance-weight) must be"),
     ("--min-size", "7", "1 <= min <= max <= 8"), ("--max-size", "9", "1 <= min <= max <= 8")],
)  # fmt: skip
def test_train_structure_refuses_rule_values_that_make_no_body(scene, tmp_path, capsys, option,
                                                              value, why):  # fmt: skip
    _, _, path, _, _ = scene
    out = tmp_path / "m.json"
    assert main(["train", "structure", f"{path}:0:200", option, value, "--out", str(out)]) == 2
    assert why in capsys.readouterr().err and not out.exists()


def test_label_an_unlabeled_take_from_a_model(scene, tmp_path, capsys):
    d, cap, _, model, test = scene
    truth = read_capture(test)
    raw = tmp_path / "raw.npz"
    write_capture(
        Capture(truth.positions, tuple(f"*{i}" for i in range(len(truth.labels))), RATE), raw
    )
    out = tmp_path / "out.npz"
    assert main(["label", str(raw), str(out), "--model", str(model), "--json"]) == 0
    summary = _last_json(capsys)
    assert summary["agreement_with_input_labels"] is None  # nothing to compare: no labels
    # when each subject was first labeled (booted), and how much of it
    subj = summary["subjects"]
    assert set(subj) == {"P1", "P2", "P3"}
    for s in subj.values():
        assert s["first_labeled_s"] is not None and s["first_labeled_s"] <= 1.0, subj
        assert 0 < s["observed_per_frame"] <= s["markers"]
    assert main(["label", str(raw), str(out), "--model", str(model), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "  P1: labeled from " in text and "never labeled" not in text, text
    res = read_capture(out)
    names = load_model(model).marker_names
    assert res.labels[: len(names)] == names
    # after half a second, the labeled columns hold the true trajectories
    col = {n: i for i, n in enumerate(truth.labels)}
    start = round(0.5 * RATE)
    ok = tot = 0
    for k, n in enumerate(names):
        t = truth.positions[start:, col[n]]
        r = res.positions[start:, k]
        seen = np.isfinite(t[:, 0]) & np.isfinite(r[:, 0])
        tot += int(np.isfinite(t[:, 0]).sum())
        ok += int((np.linalg.norm(t[seen] - r[seen], axis=1) < 1.0).sum())
    assert ok / tot >= 0.9


def test_evaluate_from_a_model_without_labels(scene, capsys):
    _, _, _, model, test = scene
    # with --model the default is no labeled frame (a boot), as label's
    args = ["evaluate", str(test), "--model", str(model), "--json"]
    assert main([*args, "--no-progress"]) == 0
    r = _last_json(capsys)
    assert r["method"] == "online" and r["settings"]["init_frames"] == 0
    assert set(r["boot_s"]) == {"P1", "P2", "P3"}
    assert r["boot_s_max"] is not None and r["boot_s_max"] <= 1.0
    assert r["accuracy_after_boot"] >= 0.9
    assert r["absent_labeled"] == 0 and r["identity_swaps"] == 0
    # the model's markers are learned (they read unseen: accuracy_seen null, as label did not)
    assert r["unseen_at_init"] == 0 and r["accuracy_seen"] == r["accuracy"]
    assert main([*args, "--no-progress", "--leave", "1", "--leave-seconds", "0.5"]) == 0
    r = _last_json(capsys)
    assert len(r["departures"]) == 1 and len(r["reid_s"]) >= 1
    assert r["absent_labeled"] == 0


def test_evaluate_table_names_each_subject_and_fits_the_terminal(scene, capsys):
    """Without ``--json`` (a user reading the terminal, 80 columns when not a tty): no measure
    name cut off, the boot time of each subject by name, the subjects that never booted and
    who left; no 'unseen in the init window' count when there is no init window."""
    from labeler_service.cli.evaluate import _print_table

    _, _, _, model, test = scene
    args = ["evaluate", str(test), "--model", str(model), "--init-frames", "0", "--json"]
    assert main([*args, "--no-progress", "--leave", "1", "--leave-seconds", "0.5"]) == 0
    report = _last_json(capsys)
    report["boot_s"]["P2"] = None  # as when a subject never boots
    _print_table(report)
    out = " ".join(capsys.readouterr().out.split())
    for measure in ("ghost_labeled_rate", "recovery_mean_ratio", "ms_per_frame_p99"):
        assert measure in out, out
    # shares as percentages that never round a loss away (0.999968 read "1")
    report["methods"]["online"]["accuracy"] = 0.999968
    _print_table(report)
    assert "accuracy 99.997 %" in " ".join(capsys.readouterr().out.replace("│", " ").split())
    assert "P1 " in out and "P2 never" in out and "P3 " in out, out
    assert "never booted: P2" in out, out
    # why it never booted: its markers wrong in at least half their visible frames (a marker
    # its start never learned says so); a booted subject's markers are not listed
    w = {"same_subject": 0, "cross_subject": 0, "seen_at_init": True}
    report["worst_markers"] = [
        {**w, "marker": "P2:LFIN", "errors": 10, "visible": 10, "unlabeled": 10,
         "seen_at_init": False},
        {**w, "marker": "P1:LFIN", "errors": 9, "visible": 9, "unlabeled": 9},
        {**w, "marker": "P2:C7", "errors": 4, "visible": 8, "unlabeled": 4},
        {**w, "marker": "P2:T10", "errors": 3, "visible": 8, "unlabeled": 3},
    ]  # fmt: skip
    _print_table(report)
    said = " ".join(capsys.readouterr().out.split())
    assert (
        "P2 stayed under 95 % with LFIN wrong in 10 of its 10 visible frames (not learned at "
        "the start: never labeled); C7 wrong in 4 of its 8 visible frames accuracy" in said
    ), said
    assert "P1 stayed" not in said and "T10 wrong" not in said, said
    left = report["departures"][0]
    assert f"left: {left['subject']} (frames {left['first_frame']}-" in out, out
    assert "unseen in the init window" not in out
    # with labeled init frames and a model the count is of markers the model lacks, with the
    # accuracy over the others and each subject's boot over the markers the model knows
    report["settings"]["init_frames"] = 5
    report["unseen_at_init"], report["accuracy_seen"] = 12, 0.98765
    report["boot_s_known"] = {"P1": 0.0, "P2": 0.25, "P3": None}
    _print_table(report)
    out = " ".join(capsys.readouterr().out.split())
    assert "12 samples of markers the model lacks (accuracy without them 98.765 %)" in out, out
    assert "init window" not in out and "--model" not in out, out
    assert "can name (not those the model lacks): P1 0.000 s, P2 0.250 s, P3 never" in out, out
    # a labeled start without a model: markers its init window never showed, and what labels
    # them; none unseen: no count at all
    report["settings"]["model_file"] = None
    _print_table(report)
    out = " ".join(capsys.readouterr().out.split())
    assert "12 samples of markers unseen in the init window (accuracy without them" in out, out
    assert "a --model trained on frames that show them can label them" in out, out
    assert "(not those unseen in the init window): P1 0.000 s" in out, out
    report["unseen_at_init"], report["boot_s_known"] = 0, {}
    _print_table(report)
    out = " ".join(capsys.readouterr().out.split())
    assert "samples of markers" not in out and "can name" not in out, out


def test_evaluate_says_which_markers_kept_a_subject_from_booting(scene, tmp_path, capsys):
    """A model trained on frames that never show four of P1's markers has no body for them, so
    P1 never reaches the boot's 95 %; the text says which markers kept it under, and that the
    model cannot label them (it said only "never booted"); the subjects that booted get no
    such line."""
    _, cap, _, _, test = scene
    hidden = ["P1:LFIN", "P1:LWRA", "P1:LWRB", "P1:LFRM"]
    assert set(hidden) <= set(cap.labels)
    half = cap.n_frames // 2
    train = cap.frames(half, cap.n_frames)
    pos = train.positions.copy()
    pos[:, [cap.labels.index(h) for h in hidden]] = np.nan
    take = tmp_path / "train.npz"
    write_capture(train.with_positions(pos), take)
    model = tmp_path / "m.json"
    assert main(["train", "structure", str(take), "--out", str(model)]) == 0
    capsys.readouterr()
    args = ["evaluate", str(test), "--model", str(model), "--init-frames", "0", "--no-progress"]
    assert main(args) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "never booted: P1 " in out, out
    line = out.split("P1 stayed under 95 % with ", 1)[1].split(" accuracy after boot")[0]
    for h in hidden:
        name = h.split(":")[1]
        assert f"{name} wrong in " in line and "(in no body of the model: never labeled)" in line
    assert "P2 stayed under" not in out and "P3 stayed under" not in out, out


def test_evaluate_boot_errors(scene, capsys):
    _, _, _, model, test = scene
    assert main(["evaluate", str(test), "--init-frames", "0", "--no-progress"]) == 2
    assert "0 with a model" in capsys.readouterr().err
    args = ["evaluate", str(test), "--model", str(model), "--init-frames", "0"]
    assert main([*args, "--method", "closest-point", "--no-progress"]) == 2
    assert "closest-point cannot start" in capsys.readouterr().err


def test_replay_with_no_init_frames_sends_no_labels(scene):
    import asyncio

    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.service.protocol import decode
    from labeler_service.tools.replay import replay

    _, _, _, _, test = scene
    frames = corrupt(read_capture(test).frames(0, 20), CorruptionSpec(seed=1))
    sent = []

    async def send(payload: bytes) -> bool:
        sent.append(decode(payload))
        return True

    stats = asyncio.run(replay(frames, send, init_frames=0, speed=0))
    assert stats.sent == 20 and all(m.labels is None for m in sent)


def test_never_booted_says_when_samples_carried_another_subjects_labels():
    """A subject booted onto another performer's points (one person's copy: one template)
    read only "never booted", as if nothing had been labeled; the summary now says the
    samples carried another subject's labels, and says nothing when they are a small share."""
    from labeler_service.cli.evaluate import _labeled_as_others

    said = _labeled_as_others({"same_subject": 0, "cross_subject": 23175, "unlabeled": 23547})
    assert said.startswith("23175 samples carried another subject's labels"), said
    assert _labeled_as_others({"same_subject": 50, "cross_subject": 4, "unlabeled": 900}) == ""
    assert _labeled_as_others({"same_subject": 0, "cross_subject": 0, "unlabeled": 10}) == ""


@pytest.mark.realdata
def test_a_copied_performer_booted_onto_the_other_is_said(real_path, tmp_path, capsys):
    """The tennis data's two players are one person copied: a model of the server boots him
    on his copy's points; `evaluate` says so beside "never booted"."""
    tennis = real_path("tennis_serve_pig_39markers_50hz.c3d")
    copy = real_path("two_players_shifted_copy_50hz.c3d")
    model = tmp_path / "tennis.json"
    assert main(["train", "structure", f"{tennis}:0:600", "--out", str(model)]) == 0
    capsys.readouterr()
    main(["evaluate", f"{copy}:0:200", "--model", str(model), "--init-frames", "0"])
    out = " ".join(capsys.readouterr().out.split())
    assert "never booted: Derrick, Viktor" in out, out
    assert "samples carried another subject's labels" in out, out
