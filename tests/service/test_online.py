"""The labeler we ship (``labeler = "online"``) through the whole server, over UDP and MQTT.

A simulated two-person scene (:func:`labeler_service.scenes.simulate.simulate_scene`) is
replayed unlabeled into a real server; a subscriber decodes the labeled output, which is scored
against the scene's truth (an observed marker's position is exactly one input point). Both
start-ups are covered -- labeled init frames in the stream (the rate is inferred from their
times) and a model file from ``train structure`` (one labeled frame, then unlabeled) -- with
labeling inline and in a labeling thread. The subscriber's C3D recording must carry the rate.
"""

from __future__ import annotations

import numpy as np
import pytest
from service.helpers import all_handled, run, until

from labeler_service.capture import Capture, read_capture
from labeler_service.labeling.templates import save_model
from labeler_service.scenes.corrupt import CorruptionSpec, StreamFrames, corrupt
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import READY, Recorder, Subscriber
from offline.structure import StructureTrainer

RATE = 120.0
INIT = 40  # labeled frames of the in-stream start
TRAIN = 360  # frames the model file is trained on (the first three seconds)


@pytest.fixture(scope="module")
def scene() -> Capture:
    return simulate_scene(2, 6.0, "walk", seed=7, rate=RATE, ghosts=0.5)


@pytest.fixture(scope="module")
def model_path(scene, tmp_path_factory):
    train = Capture(scene.positions[:TRAIN], scene.labels, scene.rate, source="train")
    model = StructureTrainer().fit([train]).model_
    assert model.rate == RATE
    path = tmp_path_factory.mktemp("online") / "model.json"
    save_model(model, path)
    return path


def _score(frames: StreamFrames, got) -> tuple[float, int, int]:
    """(accuracy over visible true markers, ghost points labeled, scored frames)."""
    correct = total = ghosts_labeled = 0
    for r in got:
        f = r.msg.seq
        pts, truth = frames.points[f], frames.truth[f]
        index = {n: j for j, n in enumerate(r.names)}
        observed = r.msg.state == 1
        for i, m in enumerate(truth.tolist()):
            hit = observed & (r.msg.positions == pts[i]).all(axis=1)
            if m < 0:
                ghosts_labeled += int(hit.any())
                continue
            total += 1
            correct += int(hit[index[frames.marker_names[m]]])
    return correct / total, ghosts_labeled, len(got)


def _settings(transport: str, broker, thread: bool, model) -> object:
    stream = {"name": "vol"} if model is None else {"name": "vol", "model": str(model)}
    base = {"labeler": "online", "metrics_port": None, "queue_size": 2048,
            "labeling_thread": thread, "streams": [stream], "udp": {"port": 0}}  # fmt: skip
    if transport == "mqtt":
        base["udp"] = {"enabled": False}
        base["mqtt"] = {"enabled": True, "host": broker.host, "port": broker.port,
                        "reconnect_min_s": 0.1, "reconnect_max_s": 0.5}  # fmt: skip
    return load_settings(**base)


def _through_server(transport, broker, thread, model, frames: StreamFrames, init: int, out):
    """Replays ``frames`` (``init`` labeled) into a server; returns what a subscriber got,
    the model message it decoded with, the server's metrics and the recorded C3D's frames."""

    async def go():
        async with Server(_settings(transport, broker, thread, model)) as srv:
            if transport == "udp":
                host, port = srv.transports[0].address
                url = f"udp://{host}:{port}/vol"
            else:
                url = f"{broker.url}/vol"
            async with Subscriber(url) as sub:
                if transport == "udp":
                    await until(lambda: srv.transports[0].subscribers, "the registration")
                else:
                    assert await sub.wait_status("vol", READY, 30.0)
                async with open_sender(url) as (send, stream):
                    stats = await replay(frames, send, stream=stream, init_frames=init, speed=2.0)
                assert stats.failed == 0
                out_total = frames.n_frames - (0 if model is not None else init)

                await until(
                    all_handled(srv, sub, "vol", out_total),
                    "every frame labeled and received",
                    timeout=120.0,
                )
                got = sub.drain()
                recorder = Recorder()
                for r in got:
                    recorder.add(r, sub.models["vol"].rate)
                n = recorder.write(out)
                return got, sub.models["vol"], srv.metrics, n

    return run(go(), timeout=240.0)


@pytest.mark.parametrize("thread", [False, True], ids=["inline", "labeling-thread"])
@pytest.mark.parametrize("start", ["init-frames", "model-file"])
@pytest.mark.parametrize("transport", ["udp", pytest.param("mqtt", marks=pytest.mark.broker)])
def test_online_labeler_through_the_server(request, scene, transport, start, thread, tmp_path):
    broker = request.getfixturevalue("broker") if transport == "mqtt" else None
    model = request.getfixturevalue("model_path") if start == "model-file" else None
    # the model-file start needs one labeled frame (the initial assignment), not a training set
    init = INIT if model is None else 1
    frames = corrupt(scene, CorruptionSpec(protect_frames=INIT, seed=11))
    out = tmp_path / "recorded.c3d"
    got, model_msg, metrics, n = _through_server(
        transport, broker, thread, model, frames, init, out
    )

    # the rate: inferred from the init frames' times, or the model file's
    assert model_msg.rate == pytest.approx(RATE, rel=1e-6)
    assert metrics.drops("queue_full") <= 0.05 * frames.n_frames
    assert metrics.drops() == metrics.drops("queue_full")  # nothing else went wrong
    assert len(got) >= 0.95 * (frames.n_frames - init)
    acc, ghosts_labeled, scored = _score(frames, got)
    assert acc >= 0.99, acc
    assert ghosts_labeled <= 0.02 * scored
    assert sorted(model_msg.names) == sorted(frames.marker_names)

    # the subscriber's recording: every received frame, at the stream's rate
    rec = read_capture(out)
    assert n == len(got) and rec.n_frames == n
    assert rec.rate == pytest.approx(RATE, rel=1e-6)
    assert rec.labels == model_msg.names
    first = got[0].msg
    np.testing.assert_allclose(rec.positions[0], first.positions, atol=1e-3)
