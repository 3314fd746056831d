"""The service over real UDP on loopback: replay -> server -> subscriber, bad datagrams,
late subscribers, and the serve command's graceful shutdown."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from service.helpers import moving_clusters, run, until

from labeler_service.errors import ProtocolError
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.service.server import Server
from labeler_service.service.settings import UDP_MAX_PAYLOAD, UdpSettings, load_settings
from labeler_service.service.transports.udp import UdpTransport
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import Subscriber


def _settings(**over):
    base = {"labeler": "baseline", "metrics_port": None, "queue_size": 256,
            "udp": {"port": 0}}  # fmt: skip
    base.update(over)
    return load_settings(**base)


async def _collect(sub: Subscriber, n: int, timeout: float = 30.0):
    out = []
    async with asyncio.timeout(timeout):
        async for r in sub.frames():
            out.append(r)
            if len(out) >= n:
                return out
    return out


def test_replay_to_service_to_subscriber_over_loopback_udp(rng):
    cap = moving_clusters(rng, subjects=3, markers=6, frames=240, rate=240.0)
    frames = corrupt(cap, CorruptionSpec(ghosts=0.5, protect_frames=40, seed=5))

    async def go():
        async with Server(_settings()) as srv:
            host, port = srv.transports[0].address
            url = f"udp://{host}:{port}/vol"
            udp = srv.transports[0]
            async with Subscriber(f"udp://{host}:{port}") as sub:
                await until(lambda: udp.subscribers, "the subscriber's registration")
                async with open_sender(url) as (send, stream):
                    stats = await replay(frames, send, stream=stream, init_frames=40, speed=1.0)
                got = await _collect(sub, 200)
            return srv.metrics, stats, got

    metrics, stats, got = run(go())
    assert stats.sent == 240 and stats.failed == 0
    assert [r.msg.seq for r in got] == list(range(40, 240))
    assert metrics.drops() == 0
    correct = total = 0
    for r in got:
        pts, truth = frames.points[r.msg.seq], frames.truth[r.msg.seq]
        for j in np.flatnonzero(r.msg.state == 1):
            i = np.flatnonzero((pts == r.msg.positions[j]).all(axis=1))
            assert i.size == 1  # an observed marker's position is exactly an input point
            correct += int(truth[i[0]] >= 0 and frames.marker_names[truth[i[0]]] == r.names[j])
        total += int((truth >= 0).sum())
    assert correct / total > 0.95
    # latency is measured on every frame (its size is a benchmark: bench latency, BENCHMARKS.md)
    lat = np.array([r.latency_ms for r in got])
    assert np.isfinite(lat).all() and (lat > 0).all()


def test_bad_datagrams_are_counted_and_the_service_keeps_labeling(rng):
    cap = moving_clusters(rng, frames=60)
    frames = corrupt(cap, CorruptionSpec(protect_frames=10, seed=1))

    async def go():
        async with Server(_settings(max_points=100)) as srv:
            host, port = srv.transports[0].address
            raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for junk in (b"\xc1", b"\x93\x01\x02\x03", b"\x81\xa1v\x02"):
                raw.sendto(junk, (host, port))
            raw.close()
            async with Subscriber(f"udp://{host}:{port}") as sub:
                await until(lambda: srv.transports[0].subscribers, "the registration")
                async with open_sender(f"udp://{host}:{port}") as (send, stream):
                    await replay(frames, send, stream=stream, init_frames=10, speed=4.0)
                got = await _collect(sub, 50)
            return srv.metrics, got

    metrics, got = run(go())
    assert metrics.drops("not_msgpack") == 1
    assert metrics.drops("not_map") == 1
    assert metrics.drops("version") == 1
    assert got[-1].msg.seq == 59


def test_a_late_subscriber_decodes_at_once_from_the_retained_model(rng):
    cap = moving_clusters(rng, frames=600, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=10, seed=2))

    async def go():
        async with Server(_settings()) as srv:
            host, port = srv.transports[0].address
            async with open_sender(f"udp://{host}:{port}") as (send, stream):
                task = asyncio.create_task(replay(frames, send, init_frames=10, speed=1.0))
                await asyncio.sleep(1.5)  # the stream is running; now a subscriber joins
                async with Subscriber(f"udp://{host}:{port}/default") as sub:
                    got = await _collect(sub, 30, timeout=30.0)
                    undecodable = sub.stats.undecodable
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            return got, undecodable

    got, undecodable = run(go())
    assert len(got) == 30 and undecodable == 0


def test_udp_transport_refuses_oversize_output_and_expires_silent_subscribers():
    async def go():
        t = UdpTransport(UdpSettings(port=0, subscriber_ttl_s=0.2))
        async with t:
            with pytest.raises(ProtocolError) as info:
                await t.send("s", "labeled", b"\x00" * (UDP_MAX_PAYLOAD + 1))
            t.subscribe(("127.0.0.1", 9), "*", t.token_for(("127.0.0.1", 9), "*"))
            assert len(t.subscribers) == 1
            await asyncio.sleep(0.3)
            await t.send("s", "model", b"x", retain=True)  # model sends expire old entries
            return info.value.reason, len(t.subscribers)

    reason, left = run(go())
    assert reason == "oversize" and left == 0


# SIGHUP (the terminal closed) killed it: exit 129, no "stopped", no ``offline`` status
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_serve_command_reports_ready_and_shuts_down_on_sigterm(tmp_path, sig):
    env = dict(os.environ, MOCAP_LABELER="baseline", MOCAP_UDP__PORT="0", MOCAP_METRICS_PORT="0")
    proc = subprocess.Popen(
        [sys.executable, "-m", "labeler_service.cli.main", "serve", "--log-level", "INFO"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
        # (a test run under nohup passes SIGHUP on ignored, which the service rightly keeps)
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL),
    )  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert line.startswith("ready udp://127.0.0.1:"), line
        assert "metrics http://127.0.0.1:" in line
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert "stopped" in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_serve_command_rejects_bad_settings_with_a_clear_message(tmp_path):
    bad = tmp_path / "s.toml"
    bad.write_text("queue_size = -1\n")
    proc = subprocess.run(
        [sys.executable, "-m", "labeler_service.cli.main", "serve", "--config", str(bad)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "queue_size" in proc.stderr and "Traceback" not in proc.stderr


def test_datagrams_the_kernel_refuses_are_counted_as_send_error():
    # a broadcast destination without SO_BROADCAST: every sendto fails (EACCES)
    async def go():
        s = _settings(udp={"port": 0, "publish_to": ["255.255.255.255:9"]}, warmup=False)
        async with Server(s) as srv:
            pass
        return srv.metrics

    metrics = run(go())
    assert metrics.drops("send_error", stream="default") == 3  # starting, online, offline


# SIGINT raised by the process itself while ``serve`` imports the server (most of a second):
# before the signal handlers were installed first, asyncio.run's own handler took it
# (KeyboardInterrupt, "interrupted", exit 130, where docs/service.md promises 0)
_SIGINT_DURING_IMPORT = """
import importlib.abc, os, signal, sys
from labeler_service.cli.main import main

class Interrupt(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "labeler_service.service.server":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None

sys.meta_path.insert(0, Interrupt())
sys.exit(main(["serve"]))
"""


def test_serve_command_stopped_while_it_imports_the_server_exits_0(tmp_path):
    env = dict(os.environ, MOCAP_UDP__PORT="0")
    proc = subprocess.run(
        [sys.executable, "-c", _SIGINT_DURING_IMPORT],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "stopped during the start" in proc.stderr and "interrupted" not in proc.stderr
    assert "ready" not in proc.stdout


def test_serve_command_stops_at_once_when_signalled_during_a_cold_warm_up(tmp_path):
    # an empty numba cache: the warm-up compiles the kernels (minutes); SIGTERM during it used
    # to wait for the compilation to end
    env = dict(
        os.environ, MOCAP_UDP__PORT="0", NUMBA_CACHE_DIR=str(tmp_path / "cache"),
    )  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "labeler_service.cli.main", "serve"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
    )  # fmt: skip
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if "warming up the kernels" in line:
                break
        assert seen and "warming up" in seen[-1], "".join(seen)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)  # the compilation alone takes minutes
        assert proc.returncode == 0, err
        assert "stopped during the start" in err and "Traceback" not in err, err
        assert "ready" not in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_a_sighup_ignored_at_start_stays_ignored():
    """``nohup mocap-labeler serve``: the service must outlive the terminal, so a SIGHUP it was
    started ignoring does not stop it (only one it would die of does)."""
    from labeler_service.cli.stopping import _signals

    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        assert signal.SIGHUP not in _signals()
    finally:
        signal.signal(signal.SIGHUP, old)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        assert set(_signals()) == {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    finally:
        signal.signal(signal.SIGHUP, old)
