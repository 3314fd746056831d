"""Boot results installed late, as the service installs them (prints one JSON object).

The kneeling performer of ``kneel_to_prone_62markers_240hz.c3d``, booted from a model of the
take's first 900 frames (no labeled frame), from ``--start`` on, through a
:class:`~labeler_service.service.stream.StreamState` of a ``boot = true`` model stream: each
boot attempt or extension is run when the stream asks for it and its result handed back a
random ``--hold-min``..``--hold-max`` frames later (a job that takes 20-330 ms at 240 Hz),
then installed between frames (``install_pending``), points shuffled in every frame. One run
per seed; per run the wrong labels (a published marker on another marker's point) and the
first few wrong pairs ``(true, given, frame)``; a label given to a point of the other side
(left for right) is counted apart in ``crossed``.

    .venv/bin/python benchmarks/late_install.py --seeds 20-80 --out late.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import booting_streams, emit, real_args


def _seeds(spec: str) -> list[int]:
    lo, _, hi = spec.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main(argv: list[str] | None = None) -> int:
    from labeler_service.capture import split_label
    from labeler_service.capture.io import read_capture
    from labeler_service.service.continuity import ACCEPT
    from labeler_service.service.protocol import decode, encode_frame
    from labeler_service.service.stream import StreamState
    from offline.structure import StructureTrainer

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--start", type=int, default=900)
    ap.add_argument("--frames", type=int, default=820)
    ap.add_argument("--seeds", default="20-80", help="A-B (inclusive) or one seed")
    ap.add_argument("--hold-min", type=int, default=5)
    ap.add_argument("--hold-max", type=int, default=80)
    a, root = real_args(ap, argv)
    if root is None:
        return 0
    take = read_capture(root / "kneel_to_prone_62markers_240hz.c3d")
    model = StructureTrainer().fit([take.frames(0, 900)]).model_
    truth = [split_label(n)[1] for n in take.labels]
    runs = []
    t0 = time.perf_counter()
    for seed in _seeds(a.seeds):
        (st,) = booting_streams(model, "kneel")
        names = [split_label(n)[1] for n in st.labeler.marker_names]
        rng = np.random.default_rng(seed)
        held: list = []
        wrong = crossed = 0
        first: dict[tuple[str, str], int] = {}
        stop = min(a.start + a.frames, take.n_frames)
        for k in range(a.start, stop):
            f = k - a.start
            while held and held[0][0] <= f:
                _, req, done = held.pop(0)
                st.boot_done(req, done)
                st.install_pending()
            p = take.positions[k]
            vis = np.flatnonzero(np.isfinite(p).all(axis=1))
            vis = vis[rng.permutation(vis.size)]
            out = st.process(decode(encode_frame("kneel", f, f / take.rate, p[vis])), 0, ACCEPT)
            assert out is not None
            lab = decode(out.payload)
            for m in np.flatnonzero(lab.state == 1):
                j = int(np.nanargmin(np.linalg.norm(p - lab.positions[m], axis=1)))
                if truth[j] != names[m]:
                    wrong += 1
                    crossed += {truth[j][0], names[m][0]} == {"L", "R"}
                    first.setdefault((truth[j], names[m]), f)
            if st.boot_due():
                req = st.boot_request()
                assert req is not None
                hold = int(rng.integers(a.hold_min, a.hold_max + 1))
                held.append((f + hold, req, StreamState.boot_job(req)))
        pairs = sorted(first.items(), key=lambda x: x[1])[:4]
        runs.append({"seed": seed, "wrong": wrong, "crossed": crossed,
                     "first": [[t, g, f] for (t, g), f in pairs]})  # fmt: skip
    emit(
        {
            "start": a.start,
            "frames": a.frames,
            "hold": [a.hold_min, a.hold_max],
            "runs": len(runs),
            "runs_wrong": sum(r["wrong"] > 10 for r in runs),
            "runs_crossed": sum(r["crossed"] > 0 for r in runs),
            "wrong": sum(r["wrong"] for r in runs),
            "crossed": sum(r["crossed"] for r in runs),
            "worst": max((r["wrong"] for r in runs), default=0),
            "seconds": round(time.perf_counter() - t0, 1),
            "per_run": runs,
        },
        a.out,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
