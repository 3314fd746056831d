"""Frame-path CPU of a booting stream in the service: results installed in the next frame's
labeling, or between frames (``StreamState.install_pending``, what the server does when no
frame waits).

The ``bench latency --start boot`` scene (simulated hug, model trained on the
``--train-seconds`` before the streamed part) goes through two :class:`StreamState`s of a
``boot = true`` model stream, frame by frame, as the server drives them: after a frame a due
attempt's snapshot (``boot_request``); its job (``boot_job``: the step, then the catch-up over
the frames recorded since the snapshot) runs when its result would come back, ``--attempt-s``
(a boot) or ``--extend-s`` (an extension) of stream after the snapshot, in this thread (the
service runs it in the boot worker); then ``next`` installs the result in its next
``process``, ``between`` at once. No clock decides anything: both streams see the same frames
and results at the same frame boundaries, and must publish the same labels (checked: the
``labels_sha256`` of every published frame).

Reported per mode, from ``--skip-s`` on: the CPU time (``thread_time``) of each frame's
``process`` (p50, p99, p99.9, max; ``next``: installs included), of the installs done between
frames (``between``), the number of installs, and the frames whose labeling carried one.

    .venv/bin/python benchmarks/boot_install_cost.py [--seconds 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import hashlib
import time

import numpy as np
from _common import add_hug_args, booting_streams, emit, hug_scene

from labeler_service.service.protocol import decode, encode_frame
from labeler_service.service.stream import StreamState


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hug_args(ap, seconds=5.0)
    ap.add_argument(
        "--skip-s",
        type=float,
        default=0.1,
        help="seconds not counted at the start (the first frame pays first calls)",
    )
    ap.add_argument("--attempt-s", type=float, default=1.0, help="a boot attempt's delay (s)")
    ap.add_argument("--extend-s", type=float, default=0.1, help="an extension's delay (s)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    model, frames = hug_scene(a)
    states = dict(zip(("next", "between"), booting_streams(model, "bench", 2, rate=a.rate),
                      strict=True))  # fmt: skip
    tt = time.thread_time
    cpu: dict[str, list[float]] = {m: [] for m in states}
    carried = {m: 0 for m in states}
    installs_between: list[float] = []
    digest = {m: hashlib.sha256() for m in states}
    pending: dict[str, tuple[int, object]] = {}
    skip = int(round(a.skip_s * a.rate))
    for f in range(frames.n_frames):
        msg = decode(encode_frame("bench", f, float(frames.times[f]), frames.points[f]))
        for mode, st in states.items():
            due = st.install_due
            c0 = tt()
            out = st.process(msg, 0)
            c = tt() - c0
            assert out is not None
            lab = decode(out.payload)
            digest[mode].update(np.ascontiguousarray(lab.state).tobytes())
            digest[mode].update(np.ascontiguousarray(lab.positions).tobytes())
            if f >= skip:
                cpu[mode].append(c * 1e3)
                carried[mode] += int(due)
            job = pending.get(mode)
            delivered = job is not None and f >= job[0]
            if delivered:  # the result comes back now
                req = job[1]  # type: ignore[index]
                st.boot_done(req, StreamState.boot_job(req))  # type: ignore[arg-type]
                del pending[mode]
                if mode == "between":
                    c0 = tt()
                    st.install_pending()
                    if f >= skip:
                        installs_between.append((tt() - c0) * 1e3)
            # (as the server: the next snapshot is taken after a frame, never right after an
            # install between frames)
            if not delivered and mode not in pending and st.boot_due():
                req = st.boot_request()
                assert req is not None
                delay = a.attempt_s if req.snapshot.subjects else a.extend_s
                pending[mode] = (f + max(1, int(round(delay * a.rate))), req)
    runs = {}
    for mode in states:
        p = np.array(cpu[mode])
        q50, q99, q999 = np.percentile(p, [50, 99, 99.9])
        runs[mode] = {
            "process_ms_p50": round(float(q50), 3),
            "process_ms_p99": round(float(q99), 3),
            "process_ms_p99_9": round(float(q999), 3),
            "process_ms_max": round(float(p.max()), 3),
            "frames_over_period": int(np.count_nonzero(p > 1e3 / a.rate)),
            "frames_carrying_an_install": carried[mode],
            "boots": len(states[mode].boots),
            "subjects_booted": len(states[mode].subjects_booted),
            "labels_sha256": digest[mode].hexdigest()[:16],
        }
    b = np.array(installs_between) if installs_between else np.zeros(1)
    runs["between"].update(
        install_ms_p50=round(float(np.median(b)), 3), install_ms_max=round(float(b.max()), 3),
        installs_between_frames=len(installs_between),
    )  # fmt: skip
    emit(
        {"subjects": a.subjects, "rate": a.rate, "seconds": a.seconds, "attempt_s": a.attempt_s,
         "extend_s": a.extend_s, "frames_timed": len(cpu["next"]), **runs},
        a.out,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
