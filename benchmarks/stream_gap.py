"""A booting model stream that loses frames: wrong labels after the gap (one JSON line).

A model is trained on one segment of a labeled take (``--train``), a stream that boots from it
(``boot = true``, no labeled frame) is fed another segment (``--test``, every visible point,
anonymous, shuffled) with ``--gap-frames`` frames left out from ``--gap-at`` (a stall, shorter
than the new-run rule's 1 s, so the labeler keeps its tracks across it). Boot attempts run at
once after the frame that makes them due (a thread, no worker process), so the run is
reproducible. Counts observed markers published on another marker's point ("wrong"), over the
whole run and after the gap::

    T=../shared/data/real/tennis_serve_pig_39markers_50hz.c3d
    python benchmarks/stream_gap.py --take $T --train 0:550 --test 550:1092 --gap-at 200 \\
        --gap-frames 25
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from _common import booting_streams, emit


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--take", required=True, help="a labeled capture")
    ap.add_argument("--train", default="0:550", help="start:stop frames the model trains on")
    ap.add_argument("--test", default="550:1092", help="start:stop frames streamed")
    ap.add_argument("--gap-at", type=int, default=200, help="first streamed frame left out")
    ap.add_argument("--gap-frames", type=int, default=25, help="frames left out (0: none)")
    ap.add_argument("--seed", type=int, default=0, help="point order")
    ap.add_argument(
        "--continuity",
        action="store_true",
        help="frames go through the service's restart rule (a gap over 1 s is a new run: the "
        "stream boots again; its first two frames are dropped)",
    )
    ap.add_argument(
        "--keep-tracks",
        action="store_true",
        help="compare: a new run keeps the booting labeler (as before StreamState.reboot)",
    )
    ap.add_argument("--out", help="also write the JSON here")
    a = ap.parse_args(argv)

    from labeler_service.capture.io import read_segment
    from labeler_service.labeling.frame import MarkerState
    from labeler_service.service.continuity import ACCEPT
    from labeler_service.service.protocol import decode, encode_frame
    from labeler_service.service.stream import StreamState
    from offline.structure import StructureTrainer

    test = read_segment(f"{a.take}:{a.test}")
    model = StructureTrainer().fit([read_segment(f"{a.take}:{a.train}")]).model_
    (st,) = booting_streams(model, "vol")
    if a.keep_tracks:
        st.reboot = lambda why: False  # type: ignore[method-assign]
    rng = np.random.default_rng(a.seed)
    column = {n: i for i, n in enumerate(test.labels)}
    own = np.array([column[n] for n in st.names])
    gap = range(a.gap_at, a.gap_at + a.gap_frames)
    wrong = observed = wrong_after = observed_after = 0
    for f in range(test.n_frames):
        if f in gap:
            continue
        pos = test.positions[f]
        vis = rng.permutation(np.flatnonzero(~np.isnan(pos[:, 0])))
        msg = decode(encode_frame("vol", f, f / test.rate, pos[vis]))
        verdict = st.check_frame(msg) if a.continuity else ACCEPT
        if verdict.reason is not None:
            continue  # dropped by the restart rule (a new run's first frames)
        out = st.process(msg, 0, verdict)
        assert out is not None
        lab = decode(out.payload)
        seen = lab.state == MarkerState.OBSERVED
        bad = seen & ~np.all(np.abs(lab.positions - pos[own]) < 1e-3, axis=1)
        wrong, observed = wrong + int(bad.sum()), observed + int(seen.sum())
        if f >= gap.stop:  # (with no gap: from --gap-at on)
            wrong_after += int(bad.sum())
            observed_after += int(seen.sum())
        if st.boot_due():
            req = st.boot_request()
            assert req is not None
            st.boot_done(req, StreamState.boot_job(req))
    emit(
        {
            "take": a.take,
            "train": a.train,
            "test": a.test,
            "gap_at": a.gap_at,
            "gap_frames": a.gap_frames,
            "wrong": wrong,
            "observed": observed,
            "wrong_after_gap": wrong_after,
            "observed_after_gap": observed_after,
            "continuity": a.continuity,
            "keep_tracks": a.keep_tracks,
            "reboots": st.reboots,
        },
        a.out,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
