"""The live view in a real browser: simulated stream -> service -> viewer -> headless Chromium.

Chromium is Debian's package (``make test`` installs it with scripts/ensure-chromium.sh),
driven by Playwright through ``executable_path`` (no browser download), WebGL in software
(SwiftShader). The test subscribes to the service itself and checks, for the frames the page
says it drew, that the spheres it placed per subject and its recovered / unlabeled counts are
the labeled frame's.
"""

from __future__ import annotations

import asyncio
import os
import shutil

import numpy as np
import pytest

from labeler_service.tools.view_frames import frame_counts

pytestmark = [pytest.mark.browser, pytest.mark.slow]

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: WebGL in software (SwiftShader); the page composited on the CPU rather than through
#: SwiftShader GL, which halves the GPU process's CPU time per frame (0.35 instead of 0.69 cores
#: at ~36 fps, 1280x720, docs/viewer.md).
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--enable-webgl",
                 "--ignore-gpu-blocklist", "--disable-gpu-compositing"]  # fmt: skip


@pytest.fixture(scope="module")
def chromium() -> str:
    pytest.importorskip("playwright.async_api", reason="pip install -e '.[test]' brings playwright")
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip("chromium not found (make test installs it: scripts/ensure-chromium.sh)")
    return CHROMIUM


def _scene():
    from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
    from labeler_service.scenes.simulate import simulate_scene

    cap = simulate_scene(performers=3, seconds=8.0, scenario="hug", seed=5, rate=120.0)
    # gaps give recovered markers, ghosts unlabeled points: every kind of thing the page draws
    spec = CorruptionSpec(gaps=2, gap_frames=40, ghosts=2.0, protect_frames=50, seed=5)
    return corrupt(cap, spec)


def _ball_pixels(png: bytes, count: int = 5) -> list[tuple[int, int]]:
    """The centres of up to ``count`` 5x5 blocks of saturated (subject-coloured) pixels in a
    screenshot, 10+ pixels apart: marker balls, not one-pixel sticks; the nearest to the middle
    of the page first (the legend's colour swatches sit at the edge)."""
    import io

    import matplotlib.image as mpimg

    img = mpimg.imread(io.BytesIO(png))[..., :3]
    sat = (img.max(axis=2) - img.min(axis=2)) > 0.35
    h, w = sat.shape
    block = np.ones((h - 4, w - 4), dtype=bool)
    for dy in range(5):
        for dx in range(5):
            block &= sat[dy : dy + h - 4, dx : dx + w - 4]
    ys, xs = np.nonzero(block)
    assert ys.size, "no marker ball on screen"
    out: list[tuple[int, int]] = []
    for i in np.argsort((ys + 2 - h / 2) ** 2 + (xs + 2 - w / 2) ** 2):
        x, y = int(xs[i]) + 2, int(ys[i]) + 2
        if all((x - a) ** 2 + (y - b) ** 2 >= 100 for a, b in out):
            out.append((x, y))
            if len(out) == count:
                break
    return out


async def _run(chromium: str, out_png) -> tuple:
    from playwright.async_api import async_playwright

    from labeler_service.service.server import Server
    from labeler_service.service.settings import load_settings
    from labeler_service.service.transports.base import cancel_and_wait
    from labeler_service.tools.replay import open_sender, replay
    from labeler_service.tools.subscribe import Subscriber
    from labeler_service.tools.view import Viewer

    frames = _scene()
    settings = load_settings(metrics_port=None, udp={"port": 0}, queue_size=256,
                             streams=[{"name": "view", "rate": frames.rate}])  # fmt: skip
    labeled: dict[int, object] = {}
    async with Server(settings) as srv:
        host, port = srv.transports[0].address
        url = f"udp://{host}:{port}/view"
        async with Subscriber(url) as sub, Viewer(url, port=0) as viewer:

            async def record() -> None:
                async for r in sub.frames():
                    labeled[r.msg.seq] = r

            async def stream() -> None:
                async with open_sender(url) as (send, _):
                    await replay(frames, send, stream="view", init_frames=50, loops=40)

            tasks = [asyncio.create_task(record(), name="test-record"),
                     asyncio.create_task(stream(), name="test-replay")]  # fmt: skip
            try:
                async with async_playwright() as pw:
                    browser = await pw.chromium.launch(executable_path=chromium,
                                                       args=CHROMIUM_ARGS)  # fmt: skip
                    page = await browser.new_page(viewport={"width": 960, "height": 600})
                    errors: list[str] = []
                    page.on("pageerror", lambda e: errors.append(str(e)))
                    await page.goto(viewer.url)
                    await page.wait_for_function(
                        "window.viewerState && (window.viewerState.error !== null"
                        " || window.viewerState.frames >= 100)",
                        timeout=120_000,
                    )
                    snapshots = []
                    # 3 s of snapshots 0.3 s apart: each subject has a 40-frame (0.33 s) gap
                    # every 160 frames, so recovered markers are on screen in some of them
                    for _ in range(10):
                        snapshots.append(await page.evaluate("window.viewerState"))
                        await asyncio.sleep(0.3)
                    await page.screenshot(path=str(out_png))
                    # pause, then single-step back and forth through the page's buffer
                    steps = []
                    for key in (" ", "ArrowLeft", "ArrowLeft", "ArrowRight"):
                        await page.keyboard.press(key)
                        await asyncio.sleep(0.3)
                        steps.append(await page.evaluate("window.viewerState"))
                    # hover over a drawn ball (paused, so it stays put): its name shows. A
                    # ghost (unlabeled, drawn grey) can lie nearer the pointer than the ball it
                    # sits on (CI, once): the next ball is tried, up to five
                    for x, y in _ball_pixels(await page.screenshot()):
                        await page.mouse.move(x, y)
                        await page.wait_for_selector("#tooltip", state="visible", timeout=5000)
                        tooltip = await page.inner_text("#tooltip")
                        if not tooltip.startswith("unlabeled"):
                            break
                        await page.mouse.move(0, 0)
                    await browser.close()
            finally:
                await cancel_and_wait(tasks)
            assert not errors, errors
            model = sub.models["view"]
            expected = [(s["seq"], frame_counts(labeled[s["seq"]], model.subjects))
                        for s in snapshots + steps if s["seq"] in labeled]  # fmt: skip
            return snapshots, steps, viewer.stats(), expected, (tooltip, model.names)


def test_the_page_draws_what_the_service_labeled(chromium, tmp_path):
    png = tmp_path / "view.png"

    async def bounded():
        async with asyncio.timeout(240):
            return await _run(chromium, png)

    snapshots, steps, stats, expected, (tooltip, names) = asyncio.run(bounded())
    name = tooltip.split()[0]
    assert name in names and "mm" in tooltip, tooltip  # e.g. "P1:LASI (observed)  12, 3, 950 mm"
    first = snapshots[0]
    assert first["error"] is None, first["error"]
    assert first["frames"] >= 100 and first["connected"]
    drawn = snapshots + steps
    assert len(expected) == len(drawn), "the test's own subscriber missed a drawn frame"
    for snap, (seq, want) in zip(drawn, expected, strict=True):
        assert snap["seq"] == seq
        assert snap["drawn"] == want["drawn"], seq
        got = (snap["observed"], snap["recovered"], snap["unlabeled"])
        assert got == (want["observed"], want["recovered"], want["unlabeled"]), seq
    assert len(first["drawn"]) == 3 and all(n > 0 for n in first["drawn"].values())
    # the comparisons above covered recovered markers and unlabeled points, not only zeros
    assert any(s["recovered"] > 0 for s in snapshots)
    assert any(s["unlabeled"] > 0 for s in snapshots)
    assert stats["frames_in"] > 0 and first["fps"] > 0
    assert snapshots[-1]["seq"] > first["seq"]  # live: the page kept drawing new frames
    assert isinstance(first["drops"], int) and first["drops"] >= 0
    paused, back1, back2, fwd = steps
    assert paused["paused"] and all(s["paused"] for s in steps)
    assert back2["seq"] < back1["seq"] < paused["seq"]  # the frames drawn before
    assert fwd["seq"] == back1["seq"]

    import matplotlib.image as mpimg

    img = mpimg.imread(png)[..., :3]
    assert img.shape[:2] == (600, 960)
    assert float(img.std()) > 0.02, "the screenshot is blank"
    # the canvas shows saturated subject colours, not only the dark background and grey grid
    rgb = img.reshape(-1, 3)
    saturated = rgb[(rgb.max(axis=1) - rgb.min(axis=1)) > 0.35]
    assert len(saturated) > 50
    hues = {tuple(np.round(p * 4)) for p in saturated}
    assert len(hues) >= 3
