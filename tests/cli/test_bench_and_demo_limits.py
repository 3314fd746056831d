"""``bench latency`` and ``demo`` refuse what would end them late or wrongly, from a hostile
run: ``bench latency --init-frames 100000`` received no frame, printed ``"drops": -99760`` and
bare ``NaN`` in its JSON and exited 0; ``demo --out FILE`` and ``--workdir /proc/x`` ended in a
traceback after the scene was built; ``demo --speed -1`` was refused only once the service
ran."""

from __future__ import annotations

import json
import math

import pytest

import labeler_service.cli.bench_latency as bench_latency
from labeler_service.cli.main import main

BENCH_REFUSED = [
    (["--init-frames", "-1"], "--init-frames must be >= 0"),
    (["--start", "init", "--init-frames", "1"], "--init-frames must be >= 3"),
    (["--seconds", "2", "--rate", "120", "--start", "init", "--init-frames", "240"],
     "leaves no unlabeled frame to measure: the run sends 240 frames"),
    (["--sim-seconds", "0"], "--sim-seconds must be a positive number"),
    (["--seconds", "nan"], "--seconds must be a positive number"),
]  # fmt: skip


@pytest.mark.parametrize(("argv", "why"), BENCH_REFUSED, ids=lambda a: str(a))
def test_bench_latency_refuses_a_run_that_measures_nothing(argv, why, capsys, monkeypatch):
    def no_run(*_a, **_k):
        raise AssertionError("the bench ran")

    monkeypatch.setattr(bench_latency, "bench", no_run)
    assert main(["bench", "latency", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and why in err and "Traceback" not in err


@pytest.mark.parametrize("command", [["bench", "latency", "--workdir"], ["demo", "--out"]])
def test_a_folder_that_cannot_be_used_is_refused_first(command, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bench_latency, "bench", lambda *_a, **_k: pytest.fail("the bench ran"))
    taken = tmp_path / "a_file"
    taken.write_text("x")
    assert main([*command, str(taken)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {taken}: cannot use as {command[-1]}") and "Traceback" not in err
    assert taken.read_text() == "x"


def test_demo_refuses_a_negative_speed_before_building_the_scene(tmp_path, capsys, monkeypatch):
    import labeler_service.cli.demo as demo

    monkeypatch.setattr(demo, "_scene", lambda *_a: pytest.fail("the scene was built"))
    assert main(["demo", "--speed", "-1", "--out", str(tmp_path / "d")]) == 2
    assert "--speed must be >= 0" in capsys.readouterr().err


@pytest.mark.parametrize(("drops", "code", "rc"), [(0, 0, 0), (3, 0, 1), (0, 1, 1)])
def test_bench_latency_exits_1_when_frames_were_lost(drops, code, rc, capsys, monkeypatch):
    """A lost frame or a service that did not exit cleanly is a failed run (it said so on
    stderr and exited 0); a measurement the run could not make is JSON ``null``, not NaN."""

    async def fake(_args, _workdir):
        return {"drops": drops, "service_exit_code": code, "latency_ms_p99": float("nan"),
                "legs": {"udp_ms": [1.0, math.inf]}}  # fmt: skip

    monkeypatch.setattr(bench_latency, "bench", fake)
    assert main(["bench", "latency", "--json", "--seconds", "1"]) == rc
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1], parse_constant=pytest.fail)
    assert out["latency_ms_p99"] is None and out["legs"] == {"udp_ms": [1.0, None]}
    assert out["drops"] == drops


def test_demo_report_of_a_run_that_received_nothing_is_strict_json(tmp_path, monkeypatch):
    """A demo whose service labeled nothing (it once took ``--init-frames 2`` and dropped every
    frame) wrote bare ``NaN`` latencies into ``report.json``; they are ``null`` now."""
    from types import SimpleNamespace

    import labeler_service.cli.demo as demo

    async def nothing(_args, _frames, _workdir):
        return SimpleNamespace(received=[], sent=60, drops_service={"no_model": 60})

    monkeypatch.setattr(demo, "_run_pipeline", nothing)
    out = tmp_path / "demo"
    main(["demo", "--frames", "60", "--init-frames", "10", "--out", str(out)])
    report = json.loads((out / "report.json").read_text(), parse_constant=pytest.fail)
    assert report["frames_received"] == 0
    assert report["latency_ms_p50"] is None and report["labeling_ms_p99"] is None
