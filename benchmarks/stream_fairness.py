"""One stream that costs more than its frame period beside a light one: what the light stream
keeps (BENCHMARKS.md, "One heavy stream beside a light one").

One ``mocap-labeler serve`` subprocess on loopback UDP with two configured streams, both
started from 50 labeled frames: ``light`` (``--light`` simulated hugging performers at
``--light-rate`` Hz) and ``heavy`` (``--heavy`` performers at ``--heavy-rate`` Hz with
``--heavy-junk`` random points added to every unlabeled frame, a broken or hostile sender's
reflections). Phase ``alone`` replays the light stream by itself; phase ``beside`` replays
both at once. Per phase and stream: frames sent and received, end-to-end latency (sender's
clock to our subscriber) p50 / p99 / p99.9 over the frames after the first ``--settle-s``
seconds, and the service's drops by stream and reason.

    .venv/bin/python benchmarks/stream_fairness.py --json
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import emit

from labeler_service.testing.harness import (
    ServiceProcess,
    service_drops,
    service_settings,
    simulated_frames,
)
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import READY, Subscriber

INIT = 50


def _pct(lat: np.ndarray) -> dict[str, float | None]:
    if lat.size == 0:
        return {"p50": None, "p99": None, "p99_9": None}
    return {
        "p50": round(float(np.percentile(lat, 50)), 2),
        "p99": round(float(np.percentile(lat, 99)), 2),
        "p99_9": round(float(np.percentile(lat, 99.9)), 2),
    }


async def _run(streams: dict, settle_s: float, workdir: Path, extra: dict) -> dict:
    """Replays every stream of ``streams`` (name -> frames) at once through one service
    (``extra``: more service settings)."""
    settings = service_settings("udp", {"name": "light"}, log_interval_s=5.0, **extra)
    settings["streams"] = [{"name": name} for name in streams]
    async with ServiceProcess(settings, workdir) as svc:
        assert svc.udp is not None
        host, port = svc.udp
        subs = {name: Subscriber(f"udp://{host}:{port}/{name}") for name in streams}
        for sub in subs.values():
            await sub.__aenter__()
        try:
            for name, sub in subs.items():
                if not await sub.wait_status(name, READY, 30.0):
                    raise RuntimeError(f"no status for stream {name}")
            got: dict[str, list] = {name: [] for name in streams}

            async def consume(name: str) -> None:
                async for r in subs[name].frames():
                    got[name].append(r)

            async def send(name: str) -> int:
                async with open_sender(f"udp://{host}:{port}/{name}") as (fn, _):
                    st = await replay(streams[name], fn, stream=name, init_frames=INIT)
                return st.sent

            readers = [asyncio.create_task(consume(n)) for n in streams]
            counts = await asyncio.gather(*(send(n) for n in streams))
            sent = dict(zip(streams, counts, strict=True))
            await asyncio.sleep(2.0)  # (the last frames of a backlog)
            for task in readers:
                task.cancel()
            await asyncio.gather(*readers, return_exceptions=True)
        finally:
            for sub in subs.values():
                await sub.__aexit__(None, None, None)
        samples = svc.scrape()
    out = {}
    for name, frames in streams.items():
        received = got[name]
        t_first = min((r.recv_ns for r in received), default=0)
        lat = np.array([
            r.latency_ms for r in received
            if r.latency_ms is not None and r.recv_ns - t_first >= settle_s * 1e9
        ])  # fmt: skip
        drops = {}
        for k, v in samples.items():
            if k.startswith("mocap_dropped_total{") and v:
                labels = dict(kv.split("=", 1) for kv in k[k.index("{") + 1 : -1].split(","))
                if labels.get("stream") == name:
                    drops[labels["reason"]] = int(v)
        out[name] = {
            "rate_hz": frames.rate,
            "points_per_frame": round(float(np.mean([len(p) for p in frames.points])), 1),
            "sent": sent[name],
            "received": len(received),
            "latency_ms": _pct(lat),
            "drops": drops,
        }
    out["drops_all"] = service_drops(samples)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--light", type=int, default=2, help="light stream's performers")
    ap.add_argument("--light-rate", type=float, default=120.0)
    ap.add_argument("--heavy", type=int, default=10, help="heavy stream's performers")
    ap.add_argument("--heavy-rate", type=float, default=360.0)
    ap.add_argument("--heavy-junk", type=int, default=1200, help="random points a frame")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--settle-s", type=float, default=2.0, help="latency after this (s)")
    ap.add_argument("--workdir", default=None, help="keep the services' logs here")
    ap.add_argument("--jump-fraction", type=float, default=None, help="boot_config's (0: off)")
    ap.add_argument("--json", action="store_true", help="(the output is JSON either way)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    light = simulated_frames(a.light, a.seconds, a.light_rate, seed=1)
    heavy = simulated_frames(a.heavy, a.seconds, a.heavy_rate, seed=2)
    rng = np.random.default_rng(3)
    lo, hi = (
        np.min([p.min(axis=0) for p in heavy.points], axis=0),
        np.max([p.max(axis=0) for p in heavy.points], axis=0),
    )
    for f in range(INIT, heavy.n_frames):  # (the labeled window stays clean: it trains)
        junk = rng.uniform(lo, hi, (a.heavy_junk, 3)).astype(np.float32)
        heavy.points[f] = np.concatenate([heavy.points[f], junk])
        heavy.truth[f] = np.concatenate([heavy.truth[f], np.full(a.heavy_junk, -1)])
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.workdir or tmp)
        extra = (
            {} if a.jump_fraction is None else {"boot_config": {"jump_fraction": a.jump_fraction}}
        )
        alone = asyncio.run(_run({"light": light}, a.settle_s, work / "alone", extra))
        both = {"light": light, "heavy": heavy}
        beside = asyncio.run(_run(both, a.settle_s, work / "beside", extra))
    emit({"alone": alone, "beside": beside, "wall_s": round(time.perf_counter() - t0, 1)}, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
