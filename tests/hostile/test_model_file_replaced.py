"""A model file replaced, deleted or half-written on disk while the service runs.

The stream re-read its model file at every new labeled run (a second take replayed): the read
failed (one ``labeler_error``) and every later frame went out unlabeled until a restart, or
another marker set's model switched the stream's markers mid-session. The file is now read
once, at the stream's first start; a new run rebuilds from that model.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from hostile.helpers import collect, frames_of, run, settings
from synthetic import moving_clusters

from labeler_service.labeling.templates import LabelerModel, save_model
from labeler_service.labeling.training import train_subject
from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport

TRAIN = 60


def _model(scene, cols, names=None) -> LabelerModel:
    subjects = []
    for s in scene.subjects if names is None else names:
        c = scene.subject_columns(s) if names is None else cols
        markers = [scene.labels[i].split(":")[1] for i in c]
        subjects.append(train_subject(s, markers, scene.positions[:TRAIN, c], scene.rate))
    return LabelerModel(rate=scene.rate, subjects=subjects)


@pytest.mark.parametrize("change", ["garbage", "deleted", "another_marker_set"])
def test_a_model_file_changed_on_disk_does_not_break_the_next_run(tmp_path, change):
    scene = moving_clusters(np.random.default_rng(5), subjects=2, markers=6, frames=300)
    path = tmp_path / "model.json"
    save_model(_model(scene, None), path)
    frames = frames_of(scene, np.random.default_rng(1))

    def item(k: int, f: int, labeled: bool, seq0: int = 0) -> bytes:
        p, truth = frames[f]
        labels = [scene.labels[i] for i in truth] if labeled else None
        return encode_frame("vol", seq0 + k, (seq0 + k) / scene.rate, p, labels)

    async def go():
        mem = MemoryTransport()
        over = {"streams": [{"name": "vol", "model": str(path)}], "boot_worker": "thread"}
        async with Server(settings(**over), [mem]) as srv:
            for k in range(120):
                mem.inject(item(k, k, k < 3))
                await asyncio.sleep(0.0005)
            await collect(srv, mem, "vol")
            if change == "garbage":
                path.write_text('{"version": 1, "rate": 12')  # a copy cut short
            elif change == "deleted":
                path.unlink()
            else:
                save_model(_model(scene, list(range(4)), ["X"]), path)
            # a second take: a new run (seq restarts far away) with labeled init frames
            for k in range(150):
                mem.inject(item(k, 120 + k, k < 5, seq0=100_000))
                await asyncio.sleep(0.0005)
            msgs = await collect(srv, mem, "vol")
            return srv, msgs

    srv, msgs = run(go())
    st = srv.streams["vol"]
    assert srv.metrics.drops() == 2, srv.metrics.snapshot()["drops"]  # the 2 suspect frames
    assert len(st.names) == 12 and st.status == "online"
    second = [m for m in msgs if m.seq >= 100_000]
    assert len(second) == 150 - 2
    observed = np.mean([np.mean(m.state == 1) for m in second[-50:]])
    assert observed > 0.9, observed
