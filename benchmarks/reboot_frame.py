"""Labeling time of the frame that reboots a ``boot = true`` model stream (a new run whose ``t``
jumped: a restarted sender), with the spare booting labeler built off the frame path at the
stream's start (``spare``) and without one (``built``: the frame builds it, as before).

A :class:`~labeler_service.service.stream.StreamState` of the simulated hug (the service
bench's scene, a model trained on the ``--train-seconds`` before the streamed part) is fed the
streamed frames in process, its boot attempts run at once in the thread; then the same frames
again with ``seq`` and ``t`` jumping back, and the labeling time of that first frame (the
``label_s`` the service publishes, the new run's reboot included) is recorded, with the largest
of the next 29 frames'. Each ``--mode`` value is one run, in order, so ``--mode built spare
built spare`` interleaves them.

    .venv/bin/python benchmarks/reboot_frame.py --mode built spare built spare [--out FILE]
"""

from __future__ import annotations

import argparse

from _common import add_hug_args, booting_streams, emit, hug_scene

from labeler_service.service.continuity import Verdict
from labeler_service.service.protocol import decode, encode_frame
from labeler_service.service.stream import StreamState


def run(frames, model, mode: str, feed_s: float, rate: float) -> dict:
    (st,) = booting_streams(model, "vol")  # (its spare built, as the server's start does)
    n = min(frames.n_frames, int(round(feed_s * rate)))

    def frame(seq: int, f: int, verdict: Verdict) -> float:
        msg = decode(encode_frame("vol", seq, float(frames.times[f]), frames.points[f]))
        out = st.process(msg, 0, verdict)
        assert out is not None
        if st.boot_due():
            req = st.boot_request()
            assert req is not None
            st.boot_done(req, StreamState.boot_job(req))
        return out.label_s

    for f in range(n):
        frame(f, f, Verdict())
    booted = len(st.subjects_booted)
    if mode == "built":
        st._spare = None  # (as a stream without one: the frame builds the fresh labeler)
    jump_s = frame(100_000, 0, Verdict(new_run=True, time_jumped=True))
    after = [frame(100_001 + f, f, Verdict()) for f in range(1, 30)]
    assert st.reboots == 1
    return {
        "mode": mode,
        "subjects_booted_before": booted,
        "jump_frame_ms": round(jump_s * 1e3, 3),
        "next_frames_ms_max": round(max(after) * 1e3, 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hug_args(ap, seconds=2.0)
    ap.add_argument("--feed-s", type=float, default=1.5, help="seconds fed before the jump")
    ap.add_argument("--mode", nargs="+", choices=["built", "spare"], default=["built", "spare"])
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    model, frames = hug_scene(a)
    runs = [run(frames, model, m, a.feed_s, a.rate) for m in a.mode]
    emit({"subjects": a.subjects, "rate": a.rate, "runs": runs}, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
