"""Shared by ``bench latency``, ``demo`` and ``benchmarks/soak.py``: run the real pipeline.

scene -> corrupt -> replay (this process) -> ``mocap-labeler serve`` (a subprocess, over a
real transport) -> subscriber (this process). The service runs as a separate process so its
latency includes a real socket hop each way; its Prometheus endpoint is scraped at the end.
:func:`simulated_frames` and :func:`service_settings` are the benchmarks' common set-up.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import gc
import json
import os
import signal
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO
from urllib.parse import urlsplit

from labeler_service.errors import MocapError
from labeler_service.scenes.corrupt import StreamFrames
from labeler_service.service.settings import resolve_file_paths


def simulated_frames(
    subjects: int, seconds: float, rate: float, seed: int, scenario: str = "hug"
) -> StreamFrames:
    """A simulated scene, shuffled, its first 50 frames kept whole (the training window)."""
    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.scenes.simulate import simulate_scene

    cap = simulate_scene(performers=subjects, seconds=seconds, scenario=scenario, seed=seed,
                         rate=rate)  # fmt: skip
    return corrupt(cap, CorruptionSpec(protect_frames=50, seed=seed))


def service_settings(transport: str, stream: dict, log_interval_s: float, **extra) -> dict:
    """``serve`` settings for one stream (``run_pipeline`` adds the broker for MQTT)."""
    return {
        "metrics_port": 0, "log_interval_s": log_interval_s, "max_points": 4000,
        "udp": {"enabled": transport == "udp", "port": 0}, "streams": [stream], **extra,
    }  # fmt: skip


def train_model_file(frames: StreamFrames, init_frames: int, path: Path, config=None) -> Path:
    """A subject model (``train structure`` schema) from the labeled init window of a stream."""
    from labeler_service.labeling.registry import make_labeler
    from labeler_service.labeling.templates import save_model

    lab = make_labeler("online", marker_names=frames.marker_names, rate=frames.rate, config=config)
    for f in range(min(init_frames, frames.n_frames)):
        lab.process(frames.points[f], float(frames.times[f]), frames.truth[f])
    save_model(lab.train_model(), path)
    return path


#: seconds between the notes a slow service start prints while :class:`ServiceProcess` waits
READY_NOTE_S = 60.0


class ServiceProcess:
    """``mocap-labeler serve`` in a subprocess with the given settings (a dict, written as JSON).

    Waits for its ``ready`` line; ``udp`` is its bound ``(host, port)`` when UDP is enabled,
    ``metrics_port`` its Prometheus port. Leaving sends SIGTERM and waits for a clean exit.
    """

    def __init__(self, settings: dict, workdir: Path, ready_timeout: float = 900.0) -> None:
        self.settings = settings
        self.workdir = Path(workdir)
        self.ready_timeout = ready_timeout
        self.proc: asyncio.subprocess.Process | None = None
        self.udp: tuple[str, int] | None = None
        self.metrics_port: int | None = None
        self.returncode: int | None = None
        self.log_path = self.workdir / "service.log"
        self._log: IO[str] | None = None

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    async def __aenter__(self) -> ServiceProcess:
        self.workdir.mkdir(parents=True, exist_ok=True)
        cfg = self.workdir / "service.json"
        # file paths as the caller meant them (its working folder): the service reads a
        # settings file's relative paths from the file's folder
        settings = copy.deepcopy(self.settings)
        resolve_file_paths(settings, Path.cwd())
        cfg.write_text(json.dumps(settings, indent=1, default=str))
        self._log = self.log_path.open("w")
        env = {k: v for k, v in os.environ.items() if not k.startswith("MOCAP_")}
        if "MOCAP_DATA_DIR" in os.environ:
            env["MOCAP_DATA_DIR"] = os.environ["MOCAP_DATA_DIR"]
        self.proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "labeler_service.cli.main", "serve", "--config", str(cfg),
            "--log-level", "INFO", stdout=asyncio.subprocess.PIPE, stderr=self._log, env=env,
        )  # fmt: skip
        assert self.proc.stdout is not None
        # a first start compiles the kernels: minutes on a slow or busy machine; say so while
        # waiting rather than give up early (a loaded 2-core machine passed 180 s)
        ready = asyncio.ensure_future(self.proc.stdout.readline())
        waited = 0.0
        while not ready.done() and waited < self.ready_timeout:
            step = min(READY_NOTE_S, self.ready_timeout - waited)
            await asyncio.wait({ready}, timeout=step)
            waited += step
            if not ready.done() and waited < self.ready_timeout:
                print(f"still waiting for the service to start ({waited:.0f} s; a first start "
                      "compiles its kernels)", file=sys.stderr, flush=True)  # fmt: skip
        if not ready.done():
            ready.cancel()
            await self._stop()
            raise MocapError(f"the service did not become ready within {self.ready_timeout} s "
                             f"(log: {self.log_path})") from None  # fmt: skip
        line = ready.result().decode()
        if not line.startswith("ready"):
            await self._stop()
            raise MocapError(f"the service failed to start (log: {self.log_path}): "
                             f"{self.log_path.read_text()[-2000:]}")  # fmt: skip
        for word in line.split():
            url = urlsplit(word)
            if url.scheme == "udp" and url.hostname and url.port:
                self.udp = (url.hostname, url.port)
            if url.scheme == "http" and url.port:
                self.metrics_port = url.port
        return self

    async def _stop(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(20):
                    await self.proc.wait()
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        if self.proc is not None:
            self.returncode = self.proc.returncode
        if self._log is not None:
            self._log.close()
            self._log = None

    async def __aexit__(self, *exc: object) -> None:
        await self._stop()

    def scrape(self) -> dict[str, float]:
        """The service's Prometheus samples as ``{"name{label=value,...}": value}``."""
        from prometheus_client.parser import text_string_to_metric_families

        if self.metrics_port is None:
            return {}
        url = f"http://127.0.0.1:{self.metrics_port}/metrics"
        with urllib.request.urlopen(url, timeout=5) as r:  # noqa: S310 - loopback only
            text = r.read().decode()
        out: dict[str, float] = {}
        for fam in text_string_to_metric_families(text):
            for s in fam.samples:
                labels = ",".join(f"{k}={v}" for k, v in sorted(s.labels.items()))
                out[f"{s.name}{{{labels}}}"] = float(s.value)
        return out


def rss_bytes(pid: int) -> int:
    """Resident memory of a process (Linux ``/proc``)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise MocapError(f"no VmRSS for process {pid}")


def service_drops(samples: dict[str, float]) -> dict[str, int]:
    out: dict[str, int] = {}
    for key, v in samples.items():
        if key.startswith("mocap_dropped_total{") and v:
            reason = key.split("reason=")[1].split(",")[0].rstrip("}")
            out[reason] = out.get(reason, 0) + int(v)
    return out


@dataclass
class PipelineResult:
    sent: int = 0
    received: list = field(default_factory=list)
    stats: object = None
    service: dict[str, float] = field(default_factory=dict)
    drops_service: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    rss: list[tuple[float, int]] = field(default_factory=list)
    max_payload: int = 0
    service_returncode: int | None = None


#: after the replay: the wait ends when the frames stop coming for this long ...
DRAIN_QUIET_S = 0.5
#: ... or after this long in all
DRAIN_MAX_S = 10.0


async def _drain(count: list[int], expected: int) -> None:
    """Waits until ``count[0]`` reaches ``expected``, or no frame came for
    :data:`DRAIN_QUIET_S` once frames came (before the first, a stream may still be training),
    or :data:`DRAIN_MAX_S` passed."""
    start = quiet = time.monotonic()
    last = count[0]
    while count[0] < expected:
        await asyncio.sleep(0.02)
        now = time.monotonic()
        if count[0] != last:
            last, quiet = count[0], now
        elif (last and now - quiet >= DRAIN_QUIET_S) or now - start >= DRAIN_MAX_S:
            return


async def run_pipeline(
    frames: StreamFrames,
    settings: dict,
    workdir: Path,
    transport: str = "udp",
    stream: str = "bench",
    init_frames: int = 50,
    speed: float = 1.0,
    loops: int = 1,
    broker_url: str | None = None,
    keep_frames: bool = True,
    rss_every_s: float | None = None,
    progress=None,
    max_frames: int | None = None,
    init_published: bool | None = None,
) -> PipelineResult:
    """Runs replay -> service subprocess -> subscriber once; see the module docstring.

    ``init_published``: the service publishes the labeled init frames too (a stream with a
    model labels its labeled first frames), so the run waits for every frame sent; None: True
    when the stream's settings give it a model. Without it the wait ended ``init_frames`` short
    and the last frame of a model-started bench arrived after the subscriber stopped (480 sent,
    479 received, one "drop" no counter named).

    Over MQTT the service is pointed at ``broker_url`` (its host and port go into the
    settings); without one, a throw-away Mosquitto (:class:`LocalBroker` in ``workdir``) runs
    for the duration of the call.
    """
    from labeler_service.service.transports.base import cancel_and_wait
    from labeler_service.service.transports.url import parse_endpoint
    from labeler_service.testing.broker import LocalBroker
    from labeler_service.tools.replay import open_sender, replay
    from labeler_service.tools.subscribe import READY, Subscriber

    res = PipelineResult()
    if init_published is None:
        cfgs = settings.get("streams") or []
        init_published = any(c.get("name") == stream and c.get("model") for c in cfgs)
    with contextlib.ExitStack() as broker:
        if transport == "mqtt":
            if broker_url is None:
                broker_url = broker.enter_context(LocalBroker(workdir)).url
            ep = parse_endpoint(broker_url)
            mqtt = {**settings.get("mqtt", {}), "enabled": True, "host": ep.host, "port": ep.port}
            settings = {**settings, "mqtt": mqtt}
        async with ServiceProcess(settings, workdir) as svc:
            if transport == "udp":
                assert svc.udp is not None
                url = f"udp://{svc.udp[0]}:{svc.udp[1]}/{stream}"
            else:
                url = f"{broker_url}/{stream}"
            async with Subscriber(url) as sub:
                if not await sub.wait_status(stream, READY, 30.0):
                    raise MocapError(f"no 'online' or 'booting' status for stream {stream} from "
                                     f"{url}")  # fmt: skip
                received = res.received
                count = [0]  # frames received (kept or not)

                async def consume() -> None:
                    async for r in sub.frames():
                        count[0] += 1
                        if keep_frames:
                            received.append(r)
                        res.max_payload = max(res.max_payload, r.nbytes)

                async def sample_rss() -> None:
                    t0 = time.monotonic()
                    while rss_every_s is not None:
                        res.rss.append((time.monotonic() - t0, rss_bytes(svc.pid)))
                        await asyncio.sleep(rss_every_s)

                tasks = [asyncio.create_task(consume(), name="pipeline-consume"),
                         asyncio.create_task(sample_rss(), name="pipeline-rss")]  # fmt: skip
                t0 = time.perf_counter()
                # no cyclic-GC pauses in this (measuring) process while frames flow: what it
                # allocates per frame is acyclic and freed by reference counting
                gc_was_enabled = gc.isenabled()
                gc.disable()
                try:
                    async with open_sender(url) as (send, _):
                        st = await replay(frames, send, stream=stream, init_frames=init_frames,
                                          speed=speed, loops=loops, on_frame=progress,
                                          max_frames=max_frames)  # fmt: skip
                    res.sent = st.sent
                    # let the last frames arrive: a backlog (a training stall at the first
                    # unlabeled frame) drains rather than being counted lost
                    await _drain(count, st.sent - (0 if init_published else init_frames * loops))
                finally:
                    if gc_was_enabled:
                        gc.enable()
                    await cancel_and_wait(tasks)
                res.seconds = time.perf_counter() - t0
                res.stats = sub.stats
            with contextlib.suppress(OSError):
                res.service = svc.scrape()
            res.drops_service = service_drops(res.service)
    res.service_returncode = svc.returncode
    return res
