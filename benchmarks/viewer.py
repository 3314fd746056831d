"""The live view under load: the page's fps, the viewer's drops, and the service's labeling p99
with and without a viewer (and its browser) attached.

A simulated ``--subjects``-performer scene at ``--rate`` Hz streams for ``--seconds`` through
``mocap-labeler serve`` (a subprocess, started from a trained model) over loopback UDP; this
process subscribes and records each labeled frame's labeling time (``proc_us``, measured inside
the service) and end-to-end latency. Runs alternate
(``--repeats`` rounds of ``--modes``): *without* a viewer; *viewer*: ``mocap-labeler view`` (a
subprocess) with no page open; *browser*: the viewer and headless Chromium (Debian's package,
through Playwright, WebGL in SwiftShader) showing its page, driven from a child process run at
``--browser-priority`` (default ``idle``, SCHED_IDLE, as ``view`` itself), which samples
``viewerState`` every second. ``--view-fps`` is the viewer's ``--fps`` (default 60). Prints
one JSON object (last line):

- per mode: medians over its runs of ``labeling_ms_p50``/``p99`` (frames after the first
  second) and ``latency_ms_p50``/``p99``;
- ``page_fps_median``/``page_fps_min`` (samples after the first 2 s of each *browser* run),
  ``viewer_drops`` (``queue``: frames the viewer replaced before a slow page took them,
  ``subscriber``: frames its subscriber lost, ``page``: frames the page skipped), frames
  forwarded and decimated;
- ``runs``: every run.

The numbers depend on the machine's load (everything shares its cores): quote them with that.

    .venv/bin/python benchmarks/viewer.py --subjects 10 --rate 360 --seconds 20

``--demo-screenshot PNG`` instead runs ``mocap-labeler demo --view`` and saves a screenshot of
the page on the demo scene (``docs/plots/viewer.png``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import shutil
import signal
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
from _common import emit

from labeler_service.errors import MocapError
from labeler_service.testing.harness import (
    ServiceProcess,
    service_drops,
    service_settings,
    simulated_frames,
    train_model_file,
)
from labeler_service.tools.priority import PRIORITIES, lower_priority
from labeler_service.tools.replay import loops_to_cover, open_sender, replay
from labeler_service.tools.subscribe import Subscriber, percentiles

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: WebGL in software (SwiftShader); the page composited on the CPU rather than through
#: SwiftShader GL, which halves the GPU process's CPU time per frame (0.35 instead of 0.69 cores
#: at ~36 fps, 1280x720, docs/viewer.md).
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--enable-webgl",
                 "--ignore-gpu-blocklist", "--disable-gpu-compositing"]  # fmt: skip
STREAM = "bench"


async def _start_view(
    url: str, log_path: Path, fps: float = 60.0
) -> tuple[asyncio.subprocess.Process, str]:
    log = log_path.open("w")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "labeler_service.cli.main", "view", "--from", url, "--port", "0",
        "--fps", str(fps), stdout=asyncio.subprocess.PIPE, stderr=log,
    )  # fmt: skip
    assert proc.stdout is not None
    async with asyncio.timeout(60):
        line = (await proc.stdout.readline()).decode()
    if not line.startswith("view "):
        raise MocapError(f"the viewer did not start: {log_path.read_text()[-800:]}")
    return proc, line.split()[1]


async def _stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.send_signal(signal.SIGINT)
        try:
            async with asyncio.timeout(15):
                await proc.wait()
        except TimeoutError:
            proc.kill()
            await proc.wait()


def _get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=5) as r:  # noqa: S310 - loopback only
        return json.loads(r.read())


async def _start_page(view_url: str, args) -> asyncio.subprocess.Process:
    """Chromium on the page, driven from a child process (``--sample-page``): Playwright's
    traffic stays out of this measuring process, and the child and its browser run at
    ``--browser-priority``."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, __file__, "--sample-page", view_url, "--width", str(args.width),
        "--height", str(args.height), "--browser-priority", args.browser_priority,
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    async with asyncio.timeout(90):
        line = (await proc.stdout.readline()).decode()
    if not line.startswith("ready"):
        raise MocapError(f"the page did not open: {line!r}")
    return proc


async def _page_result(proc: asyncio.subprocess.Process) -> dict:
    """Asks the page process to stop (SIGINT) and reads its summary (one JSON line)."""
    assert proc.stdin is None and proc.stdout is not None
    proc.send_signal(signal.SIGINT)
    async with asyncio.timeout(60):
        line = (await proc.stdout.readline()).decode()
    return json.loads(line)


async def sample_page(url: str, width: int, height: int, priority: str) -> None:
    """The child of ``_start_page``: opens the page, prints ``ready``, samples ``viewerState``
    every second until SIGINT, then prints the summary as one JSON line."""
    from playwright.async_api import async_playwright

    lower_priority(priority)  # Chromium and Playwright's driver inherit it
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGINT, stop.set)
    async with async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = await browser.new_page(viewport={"width": width, "height": height})
        await page.goto(url)
        await page.wait_for_function("window.viewerState.connected", timeout=30_000)
        print("ready", flush=True)
        samples: list[dict] = []
        t0 = time.monotonic()
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0):
                    await stop.wait()
            s = await page.evaluate("window.viewerState")
            s["at_s"] = time.monotonic() - t0
            samples.append(s)
        await browser.close()
    final = samples[-1]
    # the page's rate while frames flowed: after its first 2 s, and not the idle tail
    fps = np.array([s["fps"] for s in samples[2:-2]])
    print(json.dumps({
        "page_fps_median": float(np.median(fps)) if fps.size else None,
        "page_fps_min": float(fps.min()) if fps.size else None,
        "page_frames_drawn": final["frames"],
        "viewer_drops": final["dropsDetail"],
        "viewer_drops_total": final["drops"],
        "page_error": final["error"],
    }), flush=True)  # fmt: skip


async def one_run(frames, model_path: Path, work: Path, args, mode: str) -> dict:
    """One stream; ``mode``: ``without`` a viewer, ``viewer`` alone (no page open) or
    ``browser`` (the viewer and Chromium showing its page)."""
    n_total = int(args.seconds * frames.rate)
    stream = {"name": STREAM, "model": str(model_path), "rate": frames.rate}
    out: dict = {"mode": mode}
    async with ServiceProcess(service_settings("udp", stream, 30.0), work) as svc:
        assert svc.udp is not None
        url = f"udp://{svc.udp[0]}:{svc.udp[1]}/{STREAM}"
        async with Subscriber(url) as sub:
            if not await sub.wait_status(STREAM, "online", 30.0):
                raise MocapError(f"no 'online' status from {url}")
            proc_ms: list[float] = []
            lat_ms: list[float] = []
            t_first: list[float] = []

            async def record() -> None:
                async for r in sub.frames():
                    now = time.monotonic()
                    if not t_first:
                        t_first.append(now)
                    if now - t_first[0] >= 1.0:  # after the first second
                        proc_ms.append(r.msg.proc_us / 1e3)
                        if r.latency_ms is not None:
                            lat_ms.append(r.latency_ms)

            rec = asyncio.create_task(record(), name="bench-record")
            view = page = None
            try:
                if mode != "without":
                    view, view_url = await _start_view(url, work / "view.log", args.view_fps)
                if mode == "browser":
                    page = await _start_page(view_url, args)
                async with open_sender(url) as (send, _):
                    st = await replay(frames, send, stream=STREAM, init_frames=5, speed=1.0,
                                      loops=loops_to_cover(frames.n_frames, n_total),
                                      max_frames=n_total)  # fmt: skip
                await asyncio.sleep(1.0)
                if mode != "without":
                    state = _get_json(view_url + "api/state")
                    out.update(
                        viewer_frames_in=state["frames_in"],
                        viewer_subscriber_dropped=state["subscriber_dropped"],
                        viewer_frames_forwarded=state["frames_out"],
                        viewer_decimated=state["decimated"],
                    )
                if page is not None:
                    out.update(await _page_result(page))
            finally:
                rec.cancel()
                await asyncio.gather(rec, return_exceptions=True)
                if page is not None:
                    await _stop(page)
                if view is not None:
                    await _stop(view)
        drops = service_drops(svc.scrape())
    lab, lat = percentiles(proc_ms, (50.0, 99.0)), percentiles(lat_ms, (50.0, 99.0))
    out.update(
        frames_sent=st.sent,
        frames_received=len(proc_ms),
        labeling_ms_p50=lab["p50"],
        labeling_ms_p99=lab["p99"],
        latency_ms_p50=lat["p50"],
        latency_ms_p99=lat["p99"],
        service_drops=drops,
    )
    return out


def _median(runs: list[dict], key: str) -> float | None:
    v = [r[key] for r in runs if r.get(key) is not None]
    return float(np.median(v)) if v else None


async def bench(args) -> dict:
    frames = simulated_frames(args.subjects, args.sim_seconds, args.rate, args.seed)
    runs = []
    with tempfile.TemporaryDirectory(prefix="mocap-viewer-bench-") as d:
        work = Path(d)
        model = train_model_file(frames, 50, work / "model.json")
        for i in range(args.repeats):
            for mode in args.modes.split(","):
                r = await one_run(frames, model, work / f"run{i}-{mode}", args, mode)
                print(json.dumps(r), file=sys.stderr, flush=True)
                runs.append(r)
    keys = ("labeling_ms_p50", "labeling_ms_p99", "latency_ms_p50", "latency_ms_p99")
    modes = args.modes.split(",")
    summary = {m: {k: _median([r for r in runs if r["mode"] == m], k) for k in keys}
               for m in modes}  # fmt: skip
    with_runs = [r for r in runs if r["mode"] == "browser"]
    return {
        "subjects": args.subjects,
        "rate": frames.rate,
        "seconds": args.seconds,
        "viewport": [args.width, args.height],
        "browser_priority": args.browser_priority,
        "view_fps": args.view_fps,
        **summary,
        "page_fps_median": _median(with_runs, "page_fps_median"),
        "page_fps_min": min(
            (r["page_fps_min"] for r in with_runs if r["page_fps_min"]), default=None
        ),  # fmt: skip
        "viewer_drops_total": [r["viewer_drops_total"] for r in with_runs],
        "runs": runs,
    }


async def demo_screenshot(path: Path, width: int, height: int, frames: int) -> dict:
    """``demo --view``: waits until the page has drawn ``frames`` frames, saves a screenshot."""
    from playwright.async_api import async_playwright

    with tempfile.TemporaryDirectory(prefix="mocap-viewer-demo-") as d:
        demo = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "labeler_service.cli.main", "demo", "--view", "--view-port",
            "0", "--out", d, stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert demo.stdout is not None
        try:
            async with asyncio.timeout(300):
                while not (line := (await demo.stdout.readline()).decode()).startswith("live"):
                    if not line:
                        raise MocapError("demo --view ended without printing its view URL")
            url = line.split()[2]
            async with async_playwright() as pw:
                browser = await pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                page = await browser.new_page(viewport={"width": width, "height": height})
                await page.goto(url)
                # a moment with a recovered marker on screen (the demo hides some for a while)
                # whose panels are up to date; it stays on screen (not drawing, no pause label)
                hold = (f"s.frames >= {frames} && s.recovered > 0 && s.panelSeq === s.seq"
                        " && (s.paused = true)")  # fmt: skip
                await page.wait_for_function(f"(s => {hold})(window.viewerState)",
                                             timeout=300_000, polling="raf")  # fmt: skip
                state = await page.evaluate("window.viewerState")
                path.parent.mkdir(parents=True, exist_ok=True)
                await page.screenshot(path=str(path))
                await browser.close()
        finally:
            await _stop(demo)
    return {"screenshot": str(path), "seq": state["seq"], "drawn": state["drawn"],
            "recovered": state["recovered"], "unlabeled": state["unlabeled"]}  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--subjects", type=int, default=10)
    p.add_argument("--rate", type=float, default=360.0)
    p.add_argument("--seconds", type=float, default=20.0, help="streaming time per run")
    p.add_argument("--sim-seconds", type=float, default=5.0, help="simulated scene (looped)")
    p.add_argument("--repeats", type=int, default=2, help="rounds of --modes")
    p.add_argument("--modes", default="without,viewer,browser",
                   help="runs of a round, in order: without (no viewer), viewer (no page), "
                        "browser (viewer + headless Chromium on its page)")  # fmt: skip
    p.add_argument("--view-fps", type=float, default=60.0, help="the viewer's --fps")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--browser-priority", choices=PRIORITIES, default="idle",
                   help="CPU priority of Chromium and its driver (idle: SCHED_IDLE; low: "
                        "nice 10; normal: as is)")  # fmt: skip
    p.add_argument("--out", default=None, help="also write the JSON line here")
    p.add_argument("--demo-screenshot", type=Path, default=None, metavar="PNG",
                   help="screenshot the page on `demo --view` instead of benchmarking")  # fmt: skip
    p.add_argument("--demo-frames", type=int, default=150, help="frames drawn before the shot")
    p.add_argument("--sample-page", default=None, metavar="URL", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.sample_page is not None:
        asyncio.run(sample_page(args.sample_page, args.width, args.height, args.browser_priority))
        return 0
    if args.demo_screenshot is not None:
        result = asyncio.run(demo_screenshot(args.demo_screenshot, args.width, args.height,
                                             args.demo_frames))  # fmt: skip
    else:
        result = asyncio.run(bench(args))
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
