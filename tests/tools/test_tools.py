"""replay/subscribe tools and several streams at once."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from service.helpers import moving_clusters, run, stream_payloads

from labeler_service.capture import read_capture, write_capture
from labeler_service.errors import ConfigError
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.service.protocol import FrameMsg, decode
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.service.transports.memory import MemoryTransport
from labeler_service.service.transports.url import parse_endpoint
from labeler_service.tools.replay import frame_order, loops_to_cover, replay
from labeler_service.tools.subscribe import Received, Recorder


def test_frame_order_ping_pongs_without_repeating_the_turning_frame():
    assert frame_order(4, 3).tolist() == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    assert frame_order(3, 1).tolist() == [0, 1, 2]
    assert frame_order(1, 3).tolist() == [0, 0, 0]


@pytest.mark.parametrize("n", [1, 2, 5, 17])
def test_loops_to_cover_is_the_fewest_passes_that_reach_the_total(n):
    for total in range(0, 60):
        loops = loops_to_cover(n, total)
        assert len(frame_order(n, loops)) >= total
        assert loops == 1 or len(frame_order(n, loops - 1)) < total


def test_replay_sends_labeled_init_frames_then_unlabeled_with_increasing_seq(rng):
    cap = moving_clusters(rng, frames=30)
    frames = corrupt(cap, CorruptionSpec(ghosts=1.0, protect_frames=0, seed=3))
    sent: list[FrameMsg] = []

    async def send(payload: bytes) -> bool:
        sent.append(decode(payload))
        return True

    stats = run(replay(frames, send, stream="s", init_frames=5, speed=0, loops=2, seq0=100,
                       max_frames=50))  # fmt: skip
    assert stats.sent == 50 and [m.seq for m in sent] == list(range(100, 150))
    assert all(m.labels is not None for m in sent[:5]) and all(m.labels is None for m in sent[5:])
    for m, f in zip(sent[:5], range(5), strict=True):
        want = [frames.marker_names[i] if i >= 0 else None for i in frames.truth[f]]
        assert list(m.labels) == want
        np.testing.assert_array_equal(m.points, frames.points[f])
    assert np.all(np.diff([m.t for m in sent]) > 0)  # time keeps going through the ping-pong
    np.testing.assert_array_equal(sent[30].points, frames.points[28])  # turned around


def test_replay_rejects_bad_speed_and_loops(rng):
    frames = corrupt(moving_clusters(rng, frames=5), CorruptionSpec())

    async def send(payload):
        return True

    with pytest.raises(ConfigError, match="speed"):
        run(replay(frames, send, speed=-1))
    with pytest.raises(ConfigError, match="loops"):
        run(replay(frames, send, loops=0))


def test_replay_goes_on_at_the_capture_rate_after_a_stall_instead_of_a_burst(rng):
    # a paused sender (SIGSTOP) or a frozen machine: every frame due meanwhile was late, and all
    # of them went out at once on resume, overflowing the service's queue
    frames = corrupt(moving_clusters(rng, frames=40), CorruptionSpec(protect_frames=0, seed=1))
    frames.rate = 100.0
    when: list[float] = []

    async def send(payload: bytes) -> bool:
        when.append(time.perf_counter())
        if len(when) == 10:
            time.sleep(0.8)  # (blocks the loop, as a stop signal would)
        return True

    stats = run(replay(frames, send, stream="s", init_frames=0, speed=1.0))
    assert stats.sent == 40 and stats.stalls == 1 and stats.stalled_s > 0.5
    # the 30 frames after the stall are paced at 10 ms (at least), not sent together
    assert when[-1] - when[10] >= 0.8 * 29 * 0.01


@pytest.mark.parametrize(
    ("url", "scheme", "host", "port", "stream"),
    [
        ("udp://127.0.0.1:9870", "udp", "127.0.0.1", 9870, None),
        ("udp://localhost:1/vol-1", "udp", "localhost", 1, "vol-1"),
        ("mqtt://broker/vol", "mqtt", "broker", 1883, "vol"),
        ("mqtts://u:p%40ss@broker:8883/vol", "mqtt", "broker", 8883, "vol"),
    ],
)
def test_endpoint_urls(url, scheme, host, port, stream):
    ep = parse_endpoint(url)
    assert (ep.scheme, ep.host, ep.port, ep.stream) == (scheme, host, port, stream)
    if url.startswith("mqtts"):
        assert ep.tls and ep.username == "u" and ep.password == "p@ss"


@pytest.mark.parametrize(
    "url",
    ["http://x:1", "udp://:9", "udp://h:99999", "mqtt://h:1/a/b", "udp://h:0/s", "mqtt://h:0/s"],
)
def test_bad_endpoint_urls_raise_config_error(url):
    with pytest.raises(ConfigError):
        parse_endpoint(url)


def test_several_streams_keep_separate_state(rng):
    a = moving_clusters(rng, subjects=2, markers=4, frames=40)
    b = moving_clusters(rng, subjects=3, markers=5, frames=40)
    pa = stream_payloads(a, rng, init=10, stream="a")
    pb = stream_payloads(b, rng, init=10, stream="b", seq0=7)

    async def go():
        mem = MemoryTransport()
        s = load_settings(labeler="baseline", metrics_port=None, queue_size=256)
        async with Server(s, [mem]) as srv:
            for x, y in zip(pa, pb, strict=True):
                mem.inject(x)
                mem.inject(y)
                await asyncio.sleep(0.001)
            got = []
            while len(got) < 60:
                got.append(decode(await mem.next_sent("labeled")))
            return srv, got

    srv, got = run(go())
    by = {s: [m for m in got if m.stream == s] for s in ("a", "b")}
    assert [m.seq for m in by["a"]] == list(range(10, 40))
    assert [m.seq for m in by["b"]] == list(range(17, 47))
    assert by["a"][0].positions.shape == (8, 3) and by["b"][0].positions.shape == (15, 3)
    assert srv.streams["a"].names == tuple(sorted(a.labels))
    assert srv.metrics.drops() == 0


def test_recorder_writes_the_labeled_frames_to_c3d(tmp_path, rng):
    from labeler_service.service.protocol import LabeledMsg

    names = ("A:m0", "A:m1")
    rec = Recorder()
    pos = rng.normal(scale=100, size=(3, 2, 3)).astype(np.float32)
    pos[1, 1] = np.nan
    for f in range(3):
        msg = LabeledMsg("s", 1, f, f / 100, pos[f], np.array([1, 1], np.uint8),
                         np.zeros((0, 3), np.float32), None, 0, 0, 0.0)  # fmt: skip
        rec.add(Received(msg, names, 0), 100.0)
    assert rec.write(tmp_path / "out.c3d") == 3
    cap = read_capture(tmp_path / "out.c3d")
    assert cap.labels == names and cap.n_frames == 3 and cap.rate == 100.0
    np.testing.assert_allclose(cap.positions, pos, atol=1e-3)


def test_recorder_keeps_the_stream_rate_and_the_time_of_frames_after_a_gap(tmp_path, rng):
    """A stream at 25 Hz labeled with a 50 Hz model (replay --downsample 2): the file says
    25 Hz; frames lost in a seq gap are written missing so later frames keep their time; a
    restart (seq back to 0) continues the file."""
    from labeler_service.service.protocol import LabeledMsg

    names = ("A:m0", "A:m1")
    rec = Recorder()
    seqs = [0, 1, 2, 5, 6, 0, 1]
    pos = rng.normal(scale=100, size=(len(seqs), 2, 3)).astype(np.float32)
    for k, seq in enumerate(seqs):
        msg = LabeledMsg("s", 1, seq, seq / 25, pos[k], np.array([1, 1], np.uint8),
                         np.zeros((0, 3), np.float32), None, 0, 0, 0.0)  # fmt: skip
        rec.add(Received(msg, names, 0), 50.0)
    assert rec.write(tmp_path / "out.c3d") == 9 and rec.filled == 2
    # a frame of another model (the stream's marker set changed) is not recorded: said
    other = LabeledMsg("s", 2, 2, 2 / 25, pos[0, :1], np.array([1], np.uint8),
                       np.zeros((0, 3), np.float32), None, 0, 0, 0.0)  # fmt: skip
    rec.add(Received(other, ("B:x",), 0), 50.0)
    line = rec.report(tmp_path / "out.c3d", 9)
    assert "wrote 9 frames" in line and "at 25 Hz" in line, line
    assert "2 frames lost in seq gaps written as missing" in line, line
    assert "1 frame of a later model" in line, line
    cap = read_capture(tmp_path / "out.c3d")
    assert cap.rate == 25.0 and cap.n_frames == 9
    assert np.isnan(cap.positions[3:5]).all()
    np.testing.assert_allclose(cap.positions[5], pos[3], atol=1e-3)
    np.testing.assert_allclose(cap.positions[7:], pos[5:], atol=1e-3)


def test_recorder_keeps_one_stream_and_names_the_others(tmp_path, rng):
    """``subscribe --from udp://HOST:PORT --out F`` (no stream in the URL) hears every stream:
    two streams' frames went into one file, interleaved, with the other's seq gaps filled as
    missing frames (a hostile run: 2,053 frames received, 70,452 written). The first stream
    heard is recorded; the others are counted and named."""
    from labeler_service.service.protocol import LabeledMsg

    names = ("A:m0", "A:m1")
    rec = Recorder()
    pos = rng.normal(scale=100, size=(6, 2, 3)).astype(np.float32)
    for f in range(6):
        for stream, seq in (("one", f), ("two", 5000 + 3 * f)):
            msg = LabeledMsg(stream, 1, seq, f / 100, pos[f], np.array([1, 1], np.uint8),
                             np.zeros((0, 3), np.float32), None, 0, 0, 0.0)  # fmt: skip
            rec.add(Received(msg, names, 0), 100.0)
    assert rec.write(tmp_path / "out.c3d") == 6 and rec.filled == 0
    line = rec.report(tmp_path / "out.c3d", 6)
    assert "wrote 6 frames of stream one" in line, line
    assert "6 frames of other streams (two) not recorded" in line, line
    cap = read_capture(tmp_path / "out.c3d")
    np.testing.assert_allclose(cap.positions, pos, atol=1e-3)


def test_replay_and_subscribe_commands_end_to_end(tmp_path, rng):
    cap = moving_clusters(rng, subjects=2, markers=5, frames=180, rate=120.0)
    write_capture(cap, tmp_path / "scene.npz")
    env = dict(os.environ, MOCAP_LABELER="baseline", MOCAP_UDP__PORT="0", MOCAP_METRICS_PORT="0")
    cli = [sys.executable, "-m", "labeler_service.cli.main"]
    serve = subprocess.Popen(cli + ["serve", "--log-level", "WARNING"], stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True, env=env)  # fmt: skip
    try:
        url = serve.stdout.readline().split()[1]
        out_c3d = str(tmp_path / "out.c3d")
        sub = subprocess.Popen(cli + ["subscribe", "--from", url, "--frames", "100", "--out",
                               out_c3d, "--seconds", "60"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
        # the subscriber may register a little after the first frames: four passes send 687
        # unlabeled frames over ~6 s (a slow start costs frames, not the test), it records the
        # first 100 it gets
        rep = subprocess.run(cli + ["replay", str(tmp_path / "scene.npz"), "--to", url,
                             "--init-frames", "30", "--ghosts", "0.5", "--loops", "4"],
                             capture_output=True, text=True, timeout=60)  # fmt: skip
        out, err = sub.communicate(timeout=60)
    finally:
        serve.terminate()
        serve.communicate(timeout=20)
    assert rep.returncode == 0, rep.stderr
    assert "sent 717 frames to stream default (0 failed)" in rep.stdout
    assert sub.returncode == 0, err
    assert "wrote 100 frames" in out
    got = read_capture(tmp_path / "out.c3d")
    assert got.n_frames == 100 and set(got.labels) == set(cap.labels)
