"""Accuracy of the service's window start by when its handover comes, in process.

Each two-take scene of the cross-take matrix (``generalization.matrix``; ``--every`` picks
every n-th) is composed as ``generalization.py`` composes it and corrupted as ``evaluate``
corrupts it (cells ``rate`` and ``quarter``, init window 0.4 s), then fed frame by frame to a
service stream (:class:`~labeler_service.service.stream.StreamState`, the server's path: the
plain labeler trained by ``train_staged``, boot and extension jobs run between frames) with:

- ``labeler``: ``labeled_start = "labeler"``;
- ``handover_1``: ``auto``, the window labeler's job run after the first frame (as good as the
  handover gets);
- ``handover_1s``: ``auto``, the job after 1 s of stream (the plain labeler labels until then;
  the window labeler catches up on that second, unlabeled).

Scored with ``evaluate``'s scorer; prints per-scene rows and, per group and cell, mean and
worst. Deterministic (no timing): the handover's delay is set, not measured.

    .venv/bin/python benchmarks/handover_delay.py [--every 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import types

import generalization as G
from _common import emit

from labeler_service.cli.demo import score
from labeler_service.scenes.corrupt import CorruptionSpec, StreamFrames, corrupt
from labeler_service.service.protocol import FrameMsg, decode
from labeler_service.service.settings import load_settings
from labeler_service.service.stream import StreamState


def _msg(frames: StreamFrames, f: int, labeled: bool = False) -> FrameMsg:
    labels = None
    if labeled:
        labels = tuple(frames.marker_names[m] if m >= 0 else None
                       for m in frames.truth[f].tolist())  # fmt: skip
    return FrameMsg("vol", f, float(frames.times[f]), frames.points[f], labels)


def through_stream(frames: StreamFrames, init: int, start: str, after: int) -> float:
    """Accuracy of one stream; the handover's job runs before frame ``init + after``."""
    settings = load_settings(labeler="online", metrics_port=None, warmup=False,
                             streams=[{"name": "vol", "labeled_start": start}])  # fmt: skip
    st = StreamState("vol", settings, settings.streams[0])
    for f in range(init):
        st.buffer_init(_msg(frames, f, labeled=True))
    first = _msg(frames, init)
    lab, rate, out, ns, h = st.train_staged(st.take_init(), first)
    o = st.install_trained(lab, rate, first, out, 0, ns, h)
    received = [types.SimpleNamespace(msg=decode(o.payload), names=st.names)]
    for f in range(init + 1, frames.n_frames):
        if h is not None and f == init + after:
            st.handover_job(h)
            while h.more:
                st.handover_job(h)
            st.handover_done(h, True)
        o = st.process(_msg(frames, f), 0)
        received.append(types.SimpleNamespace(msg=decode(o.payload), names=st.names))
        if st.boot_due():  # the server's boot and extension jobs, between frames
            req = st.boot_request()
            assert req is not None
            st.boot_done(req, StreamState.boot_job(req))
    return float(score(frames, received, init).summary()["accuracy"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=3, help="every n-th two-take scene")
    ap.add_argument("--out")
    args = ap.parse_args()
    scenes = [s for s in G.matrix("all", False) if len(s.takes) == 2][:: args.every]
    rows = []
    for scene in scenes:
        rate = scene.rate()
        cap = scene.compose(scene.frames(8.0, 1200))
        for cell, step in (("rate", 1), ("quarter", 4)):
            init = max(1, round(G.INIT_S * rate / step))
            frames = corrupt(cap, CorruptionSpec(downsample=step, protect_frames=init,
                                                 seed=scene.seed))  # fmt: skip
            second = max(2, int(round(rate / step)))
            row = {
                "scene": scene.name,
                "group": scene.group,
                "cell": cell,
                "labeler": through_stream(frames, init, "labeler", 0),
                "handover_1": through_stream(frames, init, "auto", 1),
                "handover_1s": through_stream(frames, init, "auto", second),
            }
            print(row, file=sys.stderr)
            rows.append(row)
    summary = {}
    for group in ("tune", "holdout"):
        for cell in ("rate", "quarter"):
            sel = [r for r in rows if r["group"] == group and r["cell"] == cell]
            if not sel:
                continue
            summary[f"{group}_{cell}"] = {
                k: {"mean": round(statistics.mean(r[k] for r in sel), 6),
                    "worst": round(min(r[k] for r in sel), 6)}
                for k in ("labeler", "handover_1", "handover_1s")
            }  # fmt: skip
    emit({"scenes": len(scenes), "summary": summary, "rows": rows}, args.out)


if __name__ == "__main__":
    main()
