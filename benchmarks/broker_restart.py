"""Kill Mosquitto during a run and measure how fast labeled frames resume over MQTT.

The service (``mocap-labeler serve``, a subprocess) takes frames over UDP and publishes over
UDP and MQTT; a subscriber listens on MQTT. After ``--before`` seconds the broker is killed
(SIGKILL), restarted after ``--down`` seconds on the same port, and the time from the restart
to the first labeled frame received over MQTT is reported (acceptance: < 5 s). UDP output is
counted while the broker is down (it must keep flowing). Prints one JSON object.

    .venv/bin/python benchmarks/broker_restart.py
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import tempfile
import time
from pathlib import Path

from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.service.transports.base import cancel_and_wait
from labeler_service.testing.broker import LocalBroker
from labeler_service.testing.harness import ServiceProcess, service_drops
from labeler_service.tools.replay import open_sender, replay
from labeler_service.tools.subscribe import Subscriber


async def run(args, work: Path) -> dict:
    cap = simulate_scene(performers=args.subjects, seconds=5.0, scenario="hug", seed=0,
                         rate=args.rate)  # fmt: skip
    frames = corrupt(cap, CorruptionSpec(protect_frames=50, seed=0))
    broker = LocalBroker(work)
    broker.start()
    settings = {
        "metrics_port": 0, "udp": {"port": 0}, "streams": [{"name": "vol", "rate": args.rate}],
        "mqtt": {"enabled": True, "host": broker.host, "port": broker.port,
                 "reconnect_min_s": 0.2, "reconnect_max_s": 2.0},
    }  # fmt: skip
    try:
        async with ServiceProcess(settings, work) as svc:
            host, port = svc.udp
            async with (
                Subscriber(f"{broker.url}/vol") as mq,
                Subscriber(f"udp://{host}:{port}/vol") as ud,
                open_sender(f"udp://{host}:{port}/vol") as (send, _),
            ):
                feeder = asyncio.create_task(replay(frames, send, stream="vol", init_frames=50,
                                                    loops=1000))  # fmt: skip
                await asyncio.sleep(args.before)
                mqtt_before = mq.stats.frames
                broker.proc.send_signal(signal.SIGKILL)
                broker.proc.wait()
                udp0, mq0 = ud.stats.frames, mq.stats.frames
                await asyncio.sleep(args.down)
                udp_down = ud.stats.frames - udp0
                mq_down = mq.stats.frames - mq0
                broker.start()
                t0 = time.monotonic()
                resumed = None
                at_restart = mq.stats.frames
                while time.monotonic() - t0 < 30:
                    if mq.stats.frames > at_restart:
                        resumed = time.monotonic() - t0
                        break
                    await asyncio.sleep(0.005)
                await asyncio.sleep(1.0)
                await cancel_and_wait([feeder])
                drops = service_drops(svc.scrape())
    finally:
        broker.close()
    return {
        "subjects": args.subjects,
        "rate": args.rate,
        "broker_down_s": args.down,
        "mqtt_frames_before_kill": mqtt_before,
        "mqtt_frames_while_down": mq_down,
        "udp_frames_while_down": udp_down,
        "udp_frames_expected_while_down": int(args.down * args.rate),
        "resume_after_restart_s": resumed,
        "service_drops": drops,
        "service_exit_code": svc.returncode,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--subjects", type=int, default=3)
    p.add_argument("--rate", type=float, default=120.0)
    p.add_argument("--before", type=float, default=3.0, help="seconds before the kill")
    p.add_argument("--down", type=float, default=2.0, help="seconds the broker stays down")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="mocap-restart-") as d:
        out = asyncio.run(run(args, Path(d)))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
