"""The live view without a browser: decimation and drop policy, the page's frame layout, the
model message's optional ``bodies``, and the viewer over a real UDP service with a scripted
WebSocket client standing in for a (slow) browser."""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from service.helpers import moving_clusters, run, stream_payloads

from labeler_service.errors import ConfigError, ProtocolError
from labeler_service.service.protocol import LabeledMsg, ModelMsg, decode, encode_model
from labeler_service.service.settings import load_settings
from labeler_service.service.stream import StreamState
from labeler_service.tools.subscribe import READY, Received
from labeler_service.tools.view import Viewer, is_loopback, refusal
from labeler_service.tools.view_frames import (
    Decimator,
    Outbox,
    Window,
    encode_view_frame,
    frame_counts,
    model_message,
)


# ----------------------------------------------------------------------------- decimation
def test_decimator_forwards_at_most_fps_and_always_the_newest():
    d: Decimator[int] = Decimator(60.0)
    released: list[tuple[float, int]] = []
    for i in range(720):  # 2 s at 360 Hz, take attempted at every arrival
        now = i / 360.0
        d.offer(i)
        got = d.take(now)
        if got is not None:
            assert got == i  # the newest offered, never an older one
            released.append((now, got))
    times = np.array([t for t, _ in released])
    assert 119 <= len(released) <= 121  # 60 a second
    # never two within one period (up to float rounding of the 1/360 grid)
    assert np.diff(times).min() >= 1 / 60 - 1e-6
    assert d.decimated == 720 - len(released) - int(d.pending)


def test_decimator_leading_and_trailing_edges():
    d: Decimator[str] = Decimator(10.0)
    d.offer("a")
    assert d.take(100.0) == "a"  # idle: forwarded at once
    d.offer("b")
    d.offer("c")
    assert d.take(100.05) is None and d.wait_s(100.05) == pytest.approx(0.05)
    assert d.take(100.1) == "c" and d.decimated == 1  # the last of a burst is not lost
    assert d.take(100.5) is None and not d.pending
    d.offer("d")
    assert d.take(105.0) == "d"  # after an idle spell the slot grid restarts


def test_decimator_never_exceeds_the_rate_in_any_window_with_irregular_arrivals(rng):
    d: Decimator[int] = Decimator(30.0)
    t = np.cumsum(rng.exponential(1 / 500.0, size=5000))
    out = []
    for i, now in enumerate(t):
        d.offer(i)
        if d.take(now) is not None:
            out.append(now)
    out = np.array(out)
    for start in np.arange(0, t[-1] - 1, 0.25):
        n = np.count_nonzero((out >= start) & (out < start + 1.0))
        assert n <= 31
    assert len(out) >= 0.9 * 30 * (t[-1] - t[0])


def test_decimator_rejects_a_bad_rate():
    with pytest.raises(ConfigError, match="fps"):
        Decimator(0.0)


# ----------------------------------------------------------------------------- per browser
def test_outbox_holds_one_in_flight_and_replaces_the_waiting_frame():
    box = Outbox()  # depth 1, window 1
    assert box.push(1, b"1") is None
    assert box.pop() == (1, b"1") and box.pop() is None  # waiting for the page's ack
    assert box.push(2, b"2") is None
    assert box.push(3, b"3") == 2  # the older waiting frame is dropped
    assert box.push(4, b"4") == 3
    assert box.dropped == 2 and box.queued == 1 and box.in_flight == 1
    assert box.pop() is None
    box.ack(1)
    assert box.pop() == (4, b"4")  # the newest
    assert box.sent == 2


def test_outbox_window_and_depth_two_ack_clears_up_to_the_drawn_seq():
    box = Outbox(depth=2, window=2)
    for s in range(5):
        box.push(s, b"")
    assert box.dropped == 3 and [box.pop()[0], box.pop()[0]] == [3, 4] and box.pop() is None
    box.push(5, b"")
    box.ack(4)  # the page drew 4 (and skipped 3): both leave the window
    assert box.in_flight == 0 and box.pop()[0] == 5
    with pytest.raises(ConfigError):
        Outbox(depth=0)


def test_window_rate_and_percentiles_forget_old_samples():
    w = Window(seconds=2.0)
    for i in range(200):
        w.add(i / 100.0, 10.0 if i < 100 else 20.0)
    assert w.rate(1.99) == pytest.approx(100.0, rel=0.02)
    assert w.percentiles(3.5)["p50"] == 20.0  # the first second is out of the window
    assert np.isnan(w.percentiles(10.0)["p50"]) and w.rate(10.0) == 0.0


def test_the_input_rate_falls_to_zero_within_a_second_of_the_last_frame():
    """The overlay's input rate after a stream stops (``idle``): it stayed above 0 for the 5 s
    of the latency window, falling slowly, as if frames still came; the latency window keeps
    its 5 s."""
    now = [0.0]
    v = Viewer("udp://127.0.0.1:9/v", port=0, clock=lambda: now[0])
    for i in range(600):  # 5 s at 120 Hz
        now[0] = i / 120.0
        v.rate_in.add(now[0])
        v.latency.add(now[0], 2.0)
    assert v.stats()["rate_in"] == pytest.approx(120.0, rel=0.02)
    last = now[0]
    now[0] = last + 0.5
    assert v.stats()["rate_in"] == pytest.approx(60.0, rel=0.05)
    now[0] = last + 1.01
    assert v.stats()["rate_in"] == 0.0
    assert v.stats()["lat_p50"] == 2.0  # (the latency window still holds the last 5 s)


# ----------------------------------------------------------------------------- encoding
def _received(rng, m=7, k=3) -> Received:
    pos = rng.normal(scale=500, size=(m, 3)).astype(np.float32)
    state = np.array([1, 2, 0, 1, 1, 0, 2][:m], dtype=np.uint8)
    pos[state == 0] = np.nan
    unl = rng.normal(size=(k, 3)).astype(np.float32)
    msg = LabeledMsg("s", 3, 41, 0.5, pos, state, unl, 1_000_000, 0, 0, 12.0)
    return Received(msg, tuple(f"{'AB'[i // 4]}:m{i}" for i in range(m)), recv_ns=3_500_000)


def test_view_frame_layout_matches_the_documented_one(rng):
    r = _received(rng)
    data = encode_view_frame(r)
    (h,) = struct.unpack_from("<I", data)
    assert (4 + h) % 4 == 0  # float arrays start aligned (the page's Float32Array views)
    head = json.loads(data[4 : 4 + h])
    assert head == {"seq": 41, "t": 0.5, "model": 3, "m": 7, "k": 3, "lat_ms": 2.5}
    off = 4 + h
    pos = np.frombuffer(data, "<f4", 21, off).reshape(7, 3)
    unl = np.frombuffer(data, "<f4", 9, off + 84).reshape(3, 3)
    st = np.frombuffer(data, "u1", 7, off + 120)
    assert off + 127 == len(data)
    np.testing.assert_array_equal(pos, r.msg.positions)
    np.testing.assert_array_equal(unl, r.msg.unlabeled)
    np.testing.assert_array_equal(st, r.msg.state)


def test_frame_counts_are_per_subject_drawn_recovered_unlabeled(rng):
    r = _received(rng)
    c = frame_counts(r, (("A", 0, 4), ("B", 4, 3)))
    assert c == {"drawn": {"A": 3, "B": 2}, "observed": 3, "recovered": 2, "unlabeled": 3}


# ----------------------------------------------------------------------------- bodies
def test_model_bodies_round_trip_and_stay_optional():
    names = ("A:a", "A:b", "A:c", "B:a")
    subjects = (("A", 0, 3), ("B", 3, 1))
    msg = decode(encode_model("s", 2, names, subjects, 120.0, bodies=[[0, 1, 2], [3]]))
    assert isinstance(msg, ModelMsg) and msg.bodies == ((0, 1, 2), (3,))
    plain = encode_model("s", 2, names, subjects, 120.0)
    assert "bodies" not in msgpack.unpackb(plain)  # omitted, not an empty list
    assert decode(plain).bodies == ()
    page = json.loads(model_message(msg))
    assert page["bodies"] == [[0, 1, 2], [3]] and page["names"] == list(names)


@pytest.mark.parametrize("bodies", [[[0, 9]], [[]], [["a"]], [[True, 1]], {"x": 1}])
def test_bad_model_bodies_are_rejected(bodies):
    raw = msgpack.unpackb(encode_model("s", 1, ("A:a", "A:b"), (("A", 0, 2),), 100.0))
    raw["bodies"] = bodies
    with pytest.raises(ProtocolError) as e:
        decode(msgpack.packb(raw))
    assert e.value.reason == "field"


def test_model_message_gains_the_bodies_once_the_labeler_trains(rng):
    cap = moving_clusters(rng, subjects=2, markers=5, frames=60)
    settings = load_settings(metrics_port=None)
    state = StreamState("s", settings)
    payloads = stream_payloads(cap, rng, init=30, stream="s")
    for p in payloads[:30]:
        assert state.process(decode(p), 0) is None
    assert state.model_payload is None
    state.process(decode(payloads[30]), 0)  # trains: the first unlabeled frame
    model = decode(state.model_payload)
    assert model.model == 1 and model.bodies and state.bodies == model.bodies
    names = model.names
    owners = [{names[i].split(":")[0] for i in body} for body in model.bodies]
    assert all(len(o) == 1 for o in owners)  # each body lies within one subject
    assert set().union(*owners) == {s for s, _, _ in model.subjects}  # every subject has some
    before = state.model_payload
    state.process(decode(payloads[31]), 0)
    assert state.model_payload is before  # encoded once


def test_baseline_model_has_no_bodies(rng):
    cap = moving_clusters(rng, subjects=1, markers=4, frames=12)
    state = StreamState("s", load_settings(metrics_port=None, labeler="baseline"))
    for p in stream_payloads(cap, rng, init=5, stream="s"):
        state.process(decode(p), 0)
    assert decode(state.model_payload).bodies == ()


# ----------------------------------------------------------------------------- viewer
def test_is_loopback():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.1")
    assert not is_loopback("example.org")


def test_refusal_of_cross_site_pages_and_foreign_host_names():
    assert refusal("127.0.0.1:8765", None, "127.0.0.1") is None  # curl, scripts
    assert refusal("localhost:8765", "http://localhost:8765", "127.0.0.1") is None  # the page
    assert refusal("[::1]:8765", "http://[::1]:8765", "::1") is None
    assert "another site" in refusal("127.0.0.1:8765", "http://evil.example", "127.0.0.1")
    assert "another site" in refusal("127.0.0.1:8765", "null", "127.0.0.1")  # a file:// page
    # DNS rebinding: a foreign name that resolves to the loopback viewer
    assert "not this viewer's address" in refusal("evil.example:8765", None, "127.0.0.1")
    # bound to every address on purpose: any host name, still same-site only
    assert refusal("mocap-lab.local:8765", None, "0.0.0.0") is None
    assert refusal("10.0.0.5:8765", "http://evil.example", "0.0.0.0") is not None


def test_the_viewer_refuses_a_cross_site_websocket_and_a_foreign_host(rng):
    """Any page open in the user's browser could read the live capture: its WebSocket to the
    loopback viewer was answered (101) and got the model and the frames; ``/api/state`` answered
    a foreign ``Host``. Both get 403 now; the viewer's own page and plain tools are served."""
    import aiohttp

    async def go():
        srv, _ = _service(rng, 10)
        async with srv:
            host, port = srv.transports[0].address
            async with Viewer(f"udp://{host}:{port}/v", port=0) as v, \
                    aiohttp.ClientSession() as http:  # fmt: skip
                base = f"http://127.0.0.1:{v.port}"
                with pytest.raises(aiohttp.WSServerHandshakeError) as cross:
                    await http.ws_connect(f"{base}/ws", origin="http://evil.example")
                foreign = await http.get(f"{base}/api/state", headers={"Host": "evil.example"})
                own = await http.ws_connect(f"{base}/ws", origin=base)
                first = await own.receive(timeout=5)
                await own.close()
                plain = await http.get(f"{base}/api/state")
                return cross.value.status, foreign.status, first.type, plain.status, v.refused

    cross, foreign, first, plain, refused = run(go())
    assert cross == 403 and foreign == 403 and refused == 2
    assert first == aiohttp.WSMsgType.TEXT and plain == 200


def _service(rng, frames: int):
    """A baseline UDP service (not started) and a stream's payloads for it."""
    from labeler_service.service.server import Server

    cap = moving_clusters(rng, subjects=2, markers=4, frames=frames, rate=120.0)
    settings = load_settings(labeler="baseline", metrics_port=None, udp={"port": 0},
                             streams=[{"name": "v", "rate": 120.0}], queue_size=4096)  # fmt: skip
    return Server(settings), stream_payloads(cap, rng, init=10, stream="v")


async def _send_all(host, port, payloads, every: int = 20):
    from labeler_service.service.transports.udp import UdpClient

    async with UdpClient(host, port) as c:
        for i, p in enumerate(payloads):
            c.send(p)
            if i % every == 0:
                await asyncio.sleep(0.002)


async def _settled(v: Viewer, at_least: int) -> None:
    """Waits until the viewer has received ``at_least`` frames and then nothing for 0.3 s."""
    last = -1
    while v.frames_in < at_least or v.frames_in != last:
        last = v.frames_in
        await asyncio.sleep(0.3)
    await asyncio.sleep(0.05)  # the broadcast task forwards the last pending frame


def test_a_browser_that_never_acks_costs_drops_in_the_viewer_not_in_the_service(rng):
    import aiohttp

    async def go():
        srv, payloads = _service(rng, 400)
        async with srv:
            host, port = srv.transports[0].address
            url = f"udp://{host}:{port}/v"
            async with Viewer(url, port=0, fps=1000.0) as v, aiohttp.ClientSession() as http:
                ws = await http.ws_connect(f"http://127.0.0.1:{v.port}/ws")
                first = await ws.receive()
                assert first.type == aiohttp.WSMsgType.TEXT
                texts: list[dict] = [json.loads(first.data)]
                binary: list[bytes] = []
                await _send_all(host, port, payloads)
                await _settled(v, 300)
                while True:  # drain what arrived, without acknowledging anything
                    try:
                        msg = await ws.receive(timeout=0.3)
                    except TimeoutError:
                        break
                    if msg.type == aiohttp.WSMsgType.BINARY:
                        binary.append(msg.data)
                    else:
                        texts.append(json.loads(msg.data))
                state = await (await http.get(f"http://127.0.0.1:{v.port}/api/state")).json()
                await ws.close()
                return v, srv, binary, texts, state

    v, srv, binary, texts, state = run(go())
    kinds = [t["type"] for t in texts]
    assert "history_end" in kinds
    assert len(binary) == 1  # one frame in flight, never acknowledged
    (browser,) = state["browsers"]
    assert browser["sent"] == 1 and browser["in_flight"] == 1 and browser["queued"] == 1
    # every forwarded frame but the one sent and the one waiting was dropped, and counted
    assert browser["dropped"] == v.frames_out - 2 > 0
    assert v.frames_in == v.frames_out + v.decimator.decimated + int(v.decimator.pending)
    assert state["dropped_total"] == browser["dropped"]
    assert srv.metrics.drops() == 0  # the service never noticed


def test_an_acking_browser_gets_the_model_then_frames_and_a_late_one_the_history(rng):
    import aiohttp

    async def go():
        srv, payloads = _service(rng, 200)
        async with srv:
            host, port = srv.transports[0].address
            url = f"udp://{host}:{port}/v"
            async with Viewer(url, port=0, fps=1000.0, history=50) as v, \
                    aiohttp.ClientSession() as http:  # fmt: skip
                ws = await http.ws_connect(f"http://127.0.0.1:{v.port}/ws")
                await ws.send_str("not json")  # ignored: the page can only acknowledge
                await ws.send_str(json.dumps({"ack": "x"}))
                sender = asyncio.create_task(_send_all(host, port, payloads))
                seqs, model = [], None
                while len(seqs) < 20:
                    msg = await ws.receive(timeout=10)
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        m = json.loads(msg.data)
                        if m["type"] == "model":
                            model = m
                        continue
                    assert model is not None, "a frame came before its model"
                    (h,) = struct.unpack_from("<I", msg.data)
                    seq = json.loads(msg.data[4 : 4 + h])["seq"]
                    seqs.append(seq)
                    await ws.send_str(json.dumps({"ack": seq}))
                await sender
                await ws.close()
                await _settled(v, 150)
                late = await http.ws_connect(f"http://127.0.0.1:{v.port}/ws")
                got = []
                while True:
                    msg = await late.receive(timeout=10)
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        m = json.loads(msg.data)
                        if m["type"] == "history_end":
                            break
                        continue
                    got.append(msg.data)
                await late.close()
                return v, seqs, model, got

    v, seqs, model, history = run(go())
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert len(model["names"]) == 8 and [s[1:] for s in model["subjects"]] == [[0, 4], [4, 4]]
    assert len(history) == min(50, v.frames_out)
    assert history[-1] == v.history[-1][1]  # the latest frame, as the viewer encoded it


def test_view_command_serves_and_warns_when_exposed():
    cli = [sys.executable, "-m", "labeler_service.cli.main", "view", "--from",
           "udp://127.0.0.1:9/none", "--seconds", "0.5", "--log-level", "WARNING"]  # fmt: skip
    local = subprocess.run(cli + ["--port", "0"], capture_output=True, text=True, timeout=60)
    assert local.returncode == 0, local.stderr
    assert local.stdout.startswith("view http://127.0.0.1:") and "warning" not in local.stderr
    exposed = subprocess.run(cli + ["--port", "0", "--host", "0.0.0.0"], capture_output=True,
                             text=True, timeout=60)  # fmt: skip
    assert exposed.returncode == 0, exposed.stderr
    assert "warning: the viewer listens on 0.0.0.0" in exposed.stderr


@pytest.mark.broker
def test_the_viewer_follows_an_mqtt_stream(tmp_path, rng):
    import aiohttp

    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.service.server import Server
    from labeler_service.testing.broker import LocalBroker, mosquitto_binary
    from labeler_service.tools.replay import open_sender, replay

    if mosquitto_binary() is None:
        pytest.skip("mosquitto binary not found (make test installs it; apt install mosquitto)")
    cap = moving_clusters(rng, subjects=2, markers=4, frames=240, rate=120.0)
    frames = corrupt(cap, CorruptionSpec(protect_frames=20, seed=3))

    async def go(broker):
        settings = load_settings(labeler="baseline", metrics_port=None, queue_size=256,
                                 udp={"enabled": False}, streams=[{"name": "vol"}],
                                 mqtt={"enabled": True, "host": broker.host,
                                       "port": broker.port})  # fmt: skip
        url = f"{broker.url}/vol"
        async with Server(settings), Viewer(url, port=0) as v, aiohttp.ClientSession() as http:
            assert await v.subscriber.wait_status("vol", READY, 10.0)
            ws = await http.ws_connect(f"http://127.0.0.1:{v.port}/ws")
            async with open_sender(url) as (send, stream):
                sender = asyncio.create_task(
                    replay(frames, send, stream=stream, init_frames=20, speed=1.0)
                )
                seqs, model = [], None
                while len(seqs) < 10:
                    msg = await ws.receive(timeout=10)
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        m = json.loads(msg.data)
                        model = m if m["type"] == "model" else model
                        continue
                    (h,) = struct.unpack_from("<I", msg.data)
                    seqs.append(json.loads(msg.data[4 : 4 + h])["seq"])
                    await ws.send_str(json.dumps({"ack": seqs[-1]}))
                await sender
            await ws.close()
            return v.stream, model, seqs

    with LocalBroker(tmp_path) as broker:
        stream, model, seqs = run(go(broker))
    assert stream == "vol" and model["stream"] == "vol" and len(model["names"]) == 8
    assert seqs == sorted(seqs) and seqs[0] >= 20


@pytest.mark.slow
def test_demo_view_keeps_serving_the_last_frames_until_ctrl_c(tmp_path):
    import signal
    import urllib.request

    cli = [sys.executable, "-m", "labeler_service.cli.main", "demo", "--view", "--view-port", "0",
           "--frames", "150", "--out", str(tmp_path)]  # fmt: skip
    with subprocess.Popen(
        cli, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    ) as demo:
        try:
            lines = []
            for line in demo.stdout:
                lines.append(line)
                if "Ctrl-C to stop" in line:
                    break
            url = next(x.split()[2] for x in lines if x.startswith("live view"))
            assert url.startswith("http://127.0.0.1:")
            with urllib.request.urlopen(url + "api/state", timeout=10) as r:
                state = json.loads(r.read())
            assert state["stream"] == "demo" and state["last_seq"] == 149  # the demo's last frame
            assert state["frames_out"] > 0 and state["status"] == "offline"
            with urllib.request.urlopen(url, timeout=10) as r:
                assert b"viewer.js" in r.read()
            demo.send_signal(signal.SIGINT)
            assert demo.wait(timeout=30) == 0
        except BaseException:
            demo.terminate()  # never leave it (and its viewer) serving
            raise
    with pytest.raises(OSError):  # the viewer is gone with the demo
        urllib.request.urlopen(url + "api/state", timeout=5)
