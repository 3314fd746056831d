"""``train shoulder`` into a folder of an earlier run with other ``--k`` (or plots, or tests):
the earlier run's ``skeleton_k5.json`` stayed beside this run's files, and a reader taking
every ``skeleton_k*.json`` of the folder took it for this run's. The files the study writes
that this run does not are removed, with a note; nothing else in the folder is touched."""

from __future__ import annotations

import json

import pytest

from labeler_service.cli.main import main


@pytest.fixture(scope="module")
def rom(tmp_path_factory):
    sim = tmp_path_factory.mktemp("sim")
    assert main(["simulate-shoulder", str(sim), "--frames", "300", "--test-frames", "100",
                 "--spacing", "45", "--format", "npz"]) == 0  # fmt: skip
    return sim / "rom.npz"


def _train(rom, out, *extra: str) -> list[str]:
    return ["train", "shoulder", str(rom), "--restarts", "3", "--out", str(out), *extra]


def test_a_later_run_removes_the_files_only_an_earlier_run_wrote(rom, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(_train(rom, out, "--k", "3", "5")) == 0
    assert (out / "skeleton_k5.json").is_file() and (out / "segments_k5.png").is_file()
    (out / "mine.json").write_text("{}")  # the user's own file, named like none of the study's
    capsys.readouterr()
    assert main(_train(rom, out, "--k", "3", "4", "--no-plots")) == 0
    captured = capsys.readouterr()
    skeletons = sorted(p.name for p in out.glob("skeleton_k*.json"))
    assert skeletons == ["skeleton_k3.json", "skeleton_k4.json"]
    assert not list(out.glob("*.png"))  # an earlier run's plots are not this run's
    assert (out / "mine.json").is_file() and (out / "faces.txt").is_file()
    said = "removed error_train.png, segments_k3.png, segments_k5.png, skeleton_k5.json"
    assert f"note: {said}" in captured.err
    r = json.loads((out / "results.json").read_text())
    assert any(n.startswith(said) for n in r["notes"])
    assert json.loads(captured.out.strip().splitlines()[-1])["ks"] == [3, 4]
