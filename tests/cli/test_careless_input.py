"""Careless and hostile command lines end with one clear error line and exit 2, before any
long work: unwritable outputs, impossible --init-frames, a closed stdout pipe."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main

UNWRITABLE = "/proc/self/no-such-dir/out"


@pytest.fixture
def take(rng, tmp_path):
    truth, names = articulated(rng, subjects=1, frames=80)
    path = tmp_path / "take.c3d"
    write_capture(Capture(truth, names, 120.0, source="take"), path)
    return path


def _one_error_line(err: str, *needles: str) -> None:
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for n in needles:
        assert n in lines[0], (n, err)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_label_to_a_full_disk_fails(take, tmp_path, capsys):
    full = tmp_path / "full.c3d"
    full.symlink_to("/dev/full")
    assert main(["label", str(take), str(full), "--init-frames", "20", "--no-progress"]) == 2
    out, err = capsys.readouterr()
    assert "frames labeled" not in out  # no success line for a file that was not written
    _one_error_line(err, "full.c3d: cannot write: [Errno 28]")


def test_label_checks_the_output_before_reading_the_input(tmp_path, capsys):
    # the input does not exist either: the output is refused first, before any work
    assert main(["label", str(tmp_path / "missing.c3d"), UNWRITABLE + ".c3d"]) == 2
    _one_error_line(capsys.readouterr().err, "out.c3d: cannot write")


def test_replay_refuses_more_init_frames_than_the_capture_has(take, capsys):
    # the port is never contacted: the check comes before the sender is opened
    code = main(["replay", str(take), "--to", "udp://127.0.0.1:9/x", "--init-frames", "99999"])
    assert code == 2
    _one_error_line(capsys.readouterr().err, "80 frames", "99999 init frames")


def test_replay_refuses_negative_init_frames_by_their_flag(take, capsys):
    # it said "invalid corruption setting: protect_frames=-1", a name no flag has
    code = main(["replay", str(take), "--to", "udp://127.0.0.1:9/x", "--init-frames", "-1"])
    assert code == 2
    _one_error_line(capsys.readouterr().err, "--init-frames must be >= 0", "got -1")


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--stream", "b c"], "--stream 'b c': bad stream name"),
        (["--speed", "-1"], "--speed must be >= 0"),
        (["--loops", "0"], "--loops must be >= 1"),
    ],
)
def test_replay_refuses_bad_arguments_before_its_start_up_line(take, capsys, extra, needle):
    """A ``--stream`` the service cannot take was sent anyway (every frame refused there, the
    replay said 0 failed), and a bad speed or loop count failed after the start-up line."""
    assert main(["replay", str(take), "--to", "udp://127.0.0.1:9/x", *extra]) == 2
    _one_error_line(capsys.readouterr().err, needle)


def test_replay_of_a_frame_range_counts_the_range(take, capsys):
    # FILE:start:stop replays that segment only: 30 frames cannot hold 50 init frames
    code = main(["replay", f"{take}:20:50", "--to", "udp://127.0.0.1:9/x", "--init-frames", "50"])
    assert code == 2
    _one_error_line(capsys.readouterr().err, "30 frames", "50 init frames")
    code = main(["replay", f"{take}:90", "--to", "udp://127.0.0.1:9/x"])
    assert code == 2
    _one_error_line(capsys.readouterr().err, "start 90 is past the capture's 80 frames")


def test_replay_of_a_take_without_labels_needs_init_frames_0(take, tmp_path, capsys):
    # a raw capture (only *N tracks) cannot give the training window: said before sending
    from labeler_service.capture import read_capture

    cap = read_capture(take)
    raw = tmp_path / "raw.c3d"
    write_capture(Capture(cap.positions, tuple(f"*{i}" for i in range(cap.n_markers)), 120.0), raw)
    assert main(["replay", str(raw), "--to", "udp://127.0.0.1:9/x"]) == 2
    _one_error_line(capsys.readouterr().err, "no labeled markers", "--init-frames 0")


def test_label_and_compose_refuse_to_write_over_their_input(take, tmp_path, capsys):
    # `label take.c3d take.c3d` replaced the take (its labels: the truth) with the output
    before = take.read_bytes()
    link = tmp_path / "link.c3d"
    link.symlink_to(take)
    for out in (str(take), str(link)):
        assert main(["label", f"{take}:10", out, "--init-frames", "5", "--no-progress"]) == 2
        _one_error_line(capsys.readouterr().err, "is the input", "choose another output")
    args = ["compose", str(take), f"{take}:0", "--radius", "0", "--frames", "20", "--seed", "1"]
    assert main(args) == 2
    _one_error_line(capsys.readouterr().err, "is the input")
    assert take.read_bytes() == before


def test_subscribe_checks_out_before_connecting(capsys):
    t0 = time.monotonic()
    code = main(["subscribe", "--from", "udp://127.0.0.1:9/x", "--out", UNWRITABLE + ".c3d",
                 "--seconds", "30"])  # fmt: skip
    assert code == 2
    assert time.monotonic() - t0 < 20  # refused at start-up, not after the 30 s session
    _one_error_line(capsys.readouterr().err, "out.c3d: cannot write")


def test_subscribe_to_a_folder_says_so(tmp_path, capsys):
    code = main(["subscribe", "--from", "udp://127.0.0.1:9/x", "--out", str(tmp_path)])
    assert code == 2  # (it said: unknown capture format '')
    _one_error_line(capsys.readouterr().err, "cannot write: is a directory")


@pytest.mark.parametrize(
    "argv",
    [
        ["evaluate", "{f}", "--json"],
        ["label", "{f}", "{out}", "--init-frames", "0", "--model", "{model}"],
        ["replay", "{f}", "--to", "udp://127.0.0.1:9", "--init-frames", "0"],
    ],
)
def test_a_capture_with_no_frames_says_so(take, tmp_path, capsys, argv):
    """(``evaluate`` said "no frames left after down-sampling" with no --downsample, after the
    numba compile; ``label``: "give fewer --init-frames" than 0.)"""
    empty = tmp_path / "zero.npz"
    write_capture(Capture(np.zeros((0, 2, 3)), ("S:a", "S:b"), 120.0, source="zero"), empty)
    model = tmp_path / "m.json"
    if "{model}" in argv:
        assert main(["train", "structure", str(take), "--out", str(model)]) == 0
        capsys.readouterr()
    fill = {"f": str(empty), "out": str(tmp_path / "out.c3d"), "model": str(model)}
    assert main([a.format(**fill) for a in argv]) == 2
    _one_error_line(capsys.readouterr().err, "zero.npz: no frames")


def test_subscribe_without_frames_says_so(tmp_path, capsys):
    out = tmp_path / "rec.c3d"
    code = main(["subscribe", "--from", "udp://127.0.0.1:9/x", "--out", str(out),
                 "--seconds", "0.2"])  # fmt: skip
    assert code == 1  # a script sees that nothing came (it exited 0)
    stdout = capsys.readouterr().out
    assert "no frames received" in stdout and "wrote 0 frames" not in stdout
    assert "latency p50 - p99 - p99.9 -" in stdout and "nan" not in stdout  # (it said nan ms)
    assert not out.exists()


def test_evaluate_checks_the_plot_path_before_the_run(take, capsys):
    code = main(["evaluate", str(take), "--plot", UNWRITABLE + ".png", "--json", "--no-progress"])
    assert code == 2
    out, err = capsys.readouterr()
    assert out == ""
    _one_error_line(err, "out.png: cannot write")


def test_closed_stdout_pipe_ends_quietly(take):
    """``mocap-labeler info FILE | head -c 1``: the reader leaves; no BrokenPipeError trace."""
    code = (
        "import os, sys\n"
        "r, w = os.pipe(); os.close(r); os.dup2(w, 1)\n"
        "from labeler_service.cli.main import main\n"
        f"sys.exit(main(['info', {str(take)!r}]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
    assert proc.returncode == 1


def test_truncated_input_warns_on_stderr(take, tmp_path):
    data = take.read_bytes()
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(data[: len(data) // 2])
    proc = subprocess.run([sys.executable, "-m", "labeler_service.cli.main", "info", str(cut)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 0
    assert "cut.c3d: truncated:" in proc.stderr and "of 80 frames" in proc.stderr
    assert "note: truncated:" in proc.stdout


def test_replay_leave_makes_a_performer_vanish_and_come_back(rng, tmp_path, capsys):
    """``replay --leave 1``: one performer's points are absent for --leave-seconds, then back
    (the service's re-identification can be tried through the stream); said on stderr."""
    import contextlib
    import socket

    from labeler_service.service.protocol import decode

    truth, names = articulated(rng, subjects=2, frames=360)
    path = tmp_path / "two.c3d"
    write_capture(Capture(truth, names, 120.0, source="two"), path)
    import threading

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(5)
    port = rx.getsockname()[1]
    counts: list[int] = []

    def receive() -> None:  # concurrently: the kernel buffer does not hold 360 datagrams
        with contextlib.suppress(OSError):
            while len(counts) < 360:
                counts.append(len(decode(rx.recv(65536)).points))

    reader = threading.Thread(target=receive)
    reader.start()
    try:
        args = ["replay", str(path), "--to", f"udp://127.0.0.1:{port}/x", "--init-frames",
                "0", "--speed", "4", "--leave", "1", "--leave-seconds", "0.5"]  # fmt: skip
        assert main(args) == 0
        reader.join(10)
    finally:
        rx.close()
    err = capsys.readouterr().err
    assert "leaves at frame" in err and "is back at frame" in err, err
    per = len(names) // 2
    gone = [k for k, n in enumerate(counts) if n <= per]
    assert 55 <= len(gone) <= 65, counts  # 0.5 s at 120 Hz
    assert counts[-1] == len(names)


def test_train_structure_refuses_an_output_that_would_replace_a_capture(take, tmp_path, capsys):
    # `train structure take.c3d --out take.c3d` wrote the model's JSON over the take
    before = take.read_bytes()
    other = tmp_path / "other.trc"
    other.write_bytes(b"kept")
    for out, needle in ((str(take), "a model is JSON"), (str(other), "a model is JSON")):
        assert main(["train", "structure", str(take), "--out", out]) == 2
        _one_error_line(capsys.readouterr().err, needle)
    # a JSON-named link to the take is still the take
    link = tmp_path / "link.json"
    link.symlink_to(take)
    assert main(["train", "structure", f"{take}:0:40", "--out", str(link)]) == 2
    _one_error_line(capsys.readouterr().err, "is the input")
    assert take.read_bytes() == before and other.read_bytes() == b"kept"


def test_train_structure_checks_its_output_before_training(tmp_path, capsys):
    # the input does not exist either: the output is refused first, before any work
    for out in (UNWRITABLE + ".json", str(tmp_path)):
        assert main(["train", "structure", str(tmp_path / "missing.c3d"), "--out", out]) == 2
        _one_error_line(capsys.readouterr().err, "cannot write")


def test_a_model_write_cut_short_leaves_the_old_model_whole(take, tmp_path):
    # a write that stops part-way (here the file size limit: EFBIG, as a full disk would) used
    # to leave the model truncated: the next `serve` refused it, a running one kept the old
    out = tmp_path / "m.json"
    assert main(["train", "structure", str(take), "--out", str(out)]) == 0
    before = out.read_bytes()
    code = (
        "import resource, signal, sys\n"
        "from labeler_service.labeling.templates import load_model, save_model\n"
        "m = load_model(sys.argv[1])\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000))\n"
        "save_model(m, sys.argv[1])\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True)
    assert r.returncode != 0 and "cannot write model" in r.stderr, r.stderr
    assert out.read_bytes() == before  # untouched, and no temporary file left beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "take.c3d"]


def test_info_says_when_a_take_looks_y_up(rng, tmp_path, capsys):
    """A Y-up take (BTS's) read Z up said nothing of it in ``info``: now a note gives the
    detected axis and ``--up y``; read with ``--up y``, or Z up, it says nothing."""
    truth, names = articulated(rng, subjects=1, frames=80)
    zup = tmp_path / "zup.c3d"
    write_capture(Capture(truth, names, 120.0, source="zup"), zup)
    yup = tmp_path / "yup.c3d"
    turned = np.stack([truth[..., 0], truth[..., 2], -truth[..., 1]], axis=-1)
    write_capture(Capture(turned, names, 120.0, source="yup"), yup)
    for argv, said in (([str(yup)], True), ([str(yup), "--up", "y"], False), ([str(zup)], False)):
        assert main(["info", *argv]) == 0
        out = capsys.readouterr().out
        assert ("note: looks Y-up" in out) == said, (argv, out)
        if said:
            assert "--up y" in out


@pytest.mark.parametrize("command", ["label", "evaluate"])
@pytest.mark.parametrize("init", ["0", "1"])
def test_too_few_init_frames_name_the_minimum_that_works(take, tmp_path, capsys, command, init):
    """``--init-frames 0`` said 'must be >= 1', and 1 then said 'must be >= 3'."""
    argv = [command, str(take)] + ([str(tmp_path / "out.c3d")] if command == "label" else [])
    assert main([*argv, "--init-frames", init, "--no-progress"]) == 2
    _one_error_line(capsys.readouterr().err, "must be >= 3 without", "or 0 with")


def test_evaluate_of_a_scene_empty_after_its_init_window_is_refused(take, tmp_path, capsys):
    # composed takes that all ended inside the init window: `evaluate` printed a table of
    # dashes, "visible": 0, accuracy null, and exited 0
    from labeler_service.capture import read_capture

    cap = read_capture(take)
    pos = cap.positions.copy()
    pos[30:] = np.nan  # the performer leaves at frame 30, before the 50-frame window ends
    empty = tmp_path / "left.c3d"
    write_capture(Capture(pos, cap.labels, cap.rate), empty)
    assert main(["evaluate", str(empty), "--init-frames", "50", "--json"]) == 2
    _one_error_line(capsys.readouterr().err, "no marker is visible after the 50-frame", "init")
    # with a window that ends while he is there, it scores
    assert main(["evaluate", str(empty), "--init-frames", "20", "--json"]) == 0
