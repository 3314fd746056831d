"""The live 3D view: one more subscriber that serves a web page and pushes frames to it.

::

    Subscriber (UDP/MQTT, tools.subscribe) --every frame--> rate + latency windows
          |                                                  (input rate, p50/p99 of the last s)
          +--newest frame--> Decimator (<= fps, keeps the newest) --encode once--> history
                                   |
                                   +--> per browser: Outbox (drop-oldest queue, ack window)
                                              --WebSocket (aiohttp)--> page (three.js)
                                              <-- {"ack": seq} once the page has drawn it

The viewer is a client of the service like ``subscribe``: it never sends the service anything
but the subscribe handshake, so however slow a browser is the service does not wait. Work is
bounded twice (policy and formats: :mod:`labeler_service.tools.view_frames`). The
:class:`Decimator` forwards at most ``fps`` frames a second (the newest one
at each slot; the rest are *decimated*, by design). Each browser connection has an
:class:`Outbox`: at most ``window`` frames in flight (sent, not yet acknowledged as drawn) and
at most ``depth`` waiting (both 1 by default: the page gets the next frame when it has drawn
the last, and it is the newest); a new frame arriving at a full queue pushes out the oldest
waiting one, which is *dropped* (counted per connection, logged at most every 5 s, shown in the
page's overlay). What the subscriber itself had to drop (the viewer's event loop fell behind
the stream) is counted too.

WebSocket messages to the page: text (JSON) ``{"type": "model", ...}`` (marker names, subject
slices, rigid bodies) and ``{"type": "stats", ...}`` twice a second; binary frames, laid out by
:func:`encode_view_frame`. The page exposes ``window.viewerState`` for tests and scripts
(``docs/viewer.md``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from labeler_service.errors import ConfigError
from labeler_service.service.metrics import RateLimitedLog
from labeler_service.service.protocol import ModelMsg
from labeler_service.tools.subscribe import Received, Subscriber
from labeler_service.tools.view_frames import (
    Decimator,
    Outbox,
    Window,
    encode_view_frame,
    model_message,
)
from labeler_service.wording import plural

log = logging.getLogger(__name__)

STATIC_DIR = Path(str(resources.files("labeler_service.tools") / "static"))


# ----------------------------------------------------------------------------- server
def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


@dataclass(eq=False)
class Connection:
    """One browser: its outbox, the control messages to send first, a wake-up event."""

    id: int
    outbox: Outbox
    control: deque[str] = field(default_factory=deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def refusal(host_header: str, origin: str | None, bound: str) -> str | None:
    """Why the viewer refuses a request, or None. Any web page open in the user's browser could
    read the live capture from a viewer on 127.0.0.1 (its scripts may open a WebSocket to any
    address), and a page whose domain name resolves to 127.0.0.1 (DNS rebinding) could also
    read ``/api/state``. So: a request whose ``Origin`` is another site than the one it asks
    (a cross-site page) is refused; and a viewer on a loopback address answers only requests
    that name a loopback host (``localhost``, ``127.0.0.1``, ``[::1]``). Tools that send no
    ``Origin`` (curl, the tests) are served."""
    name = urlsplit("//" + host_header).hostname or ""
    if is_loopback(bound) and not (is_loopback(name) or name == bound):
        return f"host {host_header!r} is not this viewer's address (a loopback viewer)"
    if origin is not None and urlsplit(origin).netloc.lower() != host_header.lower():
        return f"origin {origin!r} is another site than {host_header!r}"
    return None


#: the window of the input rate the page shows (s)
RATE_WINDOW_S = 1.0


class Viewer:
    """``async with Viewer("udp://127.0.0.1:9870/demo") as v: print(v.url)``

    Subscribes to ``source`` (a URL as for ``subscribe``), follows one stream (the URL's, else
    the first that sends a labeled frame) and serves the page on ``http://host:port/``
    (``port=0``: a free port; :attr:`port` tells which). Read-only: the page can only
    acknowledge frames.
    """

    def __init__(
        self,
        source: str,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        fps: float = 60.0,
        depth: int = 1,
        window: int = 1,
        history: int = 300,
        stats_every_s: float = 0.5,
        window_s: float = 5.0,
        log_every_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.depth, self.window = depth, window
        self.stats_every_s = stats_every_s
        self.log_every_s = log_every_s
        self.clock = clock
        self.decimator: Decimator[Received] = Decimator(fps)
        self.history: deque[tuple[int, bytes]] = deque(maxlen=history)
        # the input rate over the last second: a stream that stops reads 0 within a second
        # (over the 5 s of the latency window it lingered, falling for 4 s after `idle`)
        self.rate_in = Window(min(window_s, RATE_WINDOW_S))
        self.latency = Window(window_s)
        self.stream: str | None = None
        self.model: ModelMsg | None = None
        self.frames_in = 0
        self.refused = 0  # requests refused by refusal(): cross-site, foreign Host
        self.frames_out = 0
        self.dropped = 0  # outbox drops, every connection, ever
        self.last_seq: int | None = None
        self.connections: set[Connection] = set()
        self._next_id = 0
        self._model_text: str | None = None
        self._new = asyncio.Event()
        self._rlog = RateLimitedLog(log, log_every_s)
        self._tasks: list[asyncio.Task] = []
        self._stack = contextlib.AsyncExitStack()
        self.subscriber: Subscriber | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def subscriber_dropped(self) -> int:
        return self.subscriber.dropped if self.subscriber is not None else 0

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> Viewer:
        from aiohttp import web

        try:
            self.subscriber = await self._stack.enter_async_context(Subscriber(self.source))
            app = web.Application(middlewares=[self._guard])
            app.router.add_get("/", self._index)
            app.router.add_get("/ws", self._ws)
            app.router.add_get("/api/state", self._state)
            app.router.add_get("/favicon.ico", self._no_content)
            app.router.add_static("/static/", STATIC_DIR, follow_symlinks=False)
            runner = web.AppRunner(app, handle_signals=False, access_log=None, shutdown_timeout=1.0)
            await runner.setup()
            self._stack.push_async_callback(runner.cleanup)
            site = web.TCPSite(runner, self.host, self.port)
            try:
                await site.start()
            except OSError as exc:
                msg = f"viewer cannot listen on {self.host}:{self.port}: {exc}"
                raise ConfigError(msg) from exc
            self.port = int(runner.addresses[0][1])
        except BaseException:
            await self._stack.aclose()
            raise
        self._tasks += [
            asyncio.create_task(self._pump(), name="view-pump"),
            asyncio.create_task(self._broadcast(), name="view-broadcast"),
            asyncio.create_task(self._stats_loop(), name="view-stats"),
        ]
        return self

    async def __aexit__(self, *exc: object) -> None:
        from labeler_service.service.transports.base import cancel_and_wait

        tasks, self._tasks = self._tasks, []
        await cancel_and_wait(tasks)
        await self._stack.aclose()

    # ------------------------------------------------------------------ subscriber side
    async def _pump(self) -> None:
        assert self.subscriber is not None
        sub = self.subscriber
        want = sub.stream
        async for r in sub.frames():
            s = r.msg.stream
            if self.stream is None and (want is None or s == want):
                self.stream = s
                log.info("viewer: showing stream %s", s)
            if s != self.stream:
                continue
            now = self.clock()
            self.frames_in += 1
            self.last_seq = r.msg.seq
            self.rate_in.add(now)
            if r.latency_ms is not None:
                self.latency.add(now, r.latency_ms)
            model = sub.models.get(s)
            if model is not None and model is not self.model:
                self._set_model(model)
            self.decimator.offer(r)
            self._new.set()

    def _set_model(self, model: ModelMsg) -> None:
        old = self.model
        self.model = model
        same = old is not None and (old.model, old.names, old.bodies, old.rate) == (
            model.model, model.names, model.bodies, model.rate)  # fmt: skip
        if same:
            return  # the once-a-second repeat
        if old is not None and old.model != model.model:
            self.history.clear()  # older frames no longer decode with the new names
        self._model_text = model_message(model)
        for c in self.connections:
            c.control.append(self._model_text)
            c.wake.set()

    async def _broadcast(self) -> None:
        while True:
            await self._new.wait()
            self._new.clear()
            delay = self.decimator.wait_s(self.clock())
            if delay > 0:
                await asyncio.sleep(delay)
            r = self.decimator.take(self.clock())
            if r is None:
                continue
            if self.decimator.pending:
                self._new.set()
            data = encode_view_frame(r)
            seq = r.msg.seq
            self.history.append((seq, data))
            self.frames_out += 1
            for c in self.connections:
                if c.outbox.push(seq, data) is not None:
                    self.dropped += 1
                    self._rlog.warning(f"drop-{c.id}", "viewer: browser %d is slow, dropped "
                                       "its oldest queued frame (%d so far)", c.id,
                                       c.outbox.dropped)  # fmt: skip
                c.wake.set()

    # ------------------------------------------------------------------ browser side
    @property
    def _guard(self):
        from aiohttp import web

        @web.middleware
        async def guard(request, handler):
            why = refusal(request.host, request.headers.get("Origin"), self.host)
            if why is not None:
                self.refused += 1
                if self.refused == 1 or self.refused % 100 == 0:  # (a page may retry forever)
                    log.warning("viewer: refused %s %s from %s: %s (%s so far)", request.method,
                                request.path, request.remote, why, self.refused)  # fmt: skip
                return web.Response(status=403, text=f"refused: {why}\n")
            return await handler(request)

        return guard

    async def _no_content(self, request):
        from aiohttp import web

        return web.Response(status=204)

    async def _index(self, request):
        from aiohttp import web

        return web.FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-store"})

    def stats(self, c: Connection | None = None) -> dict:
        now = self.clock()
        lat = self.latency.percentiles(now)
        out = {
            "type": "stats",
            "stream": self.stream,
            "source": self.source,
            "rate_in": self.rate_in.rate(now),
            "lat_p50": lat["p50"],
            "lat_p99": lat["p99"],
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "last_seq": self.last_seq,
            "decimated": self.decimator.decimated,
            "subscriber_dropped": self.subscriber_dropped,
            "dropped_total": self.dropped,
            "connections": len(self.connections),
            "status": None if self.subscriber is None or self.stream is None
            else self.subscriber.status.get(self.stream),
        }  # fmt: skip
        if c is not None:
            out.update(id=c.id, dropped=c.outbox.dropped, sent=c.outbox.sent)
        # JSON has no NaN: an empty window reads as null
        return {k: None if isinstance(v, float) and not np.isfinite(v) else v
                for k, v in out.items()}  # fmt: skip

    async def _state(self, request):
        from aiohttp import web

        body = self.stats()
        body["browsers"] = [
            {
                "id": c.id,
                "dropped": c.outbox.dropped,
                "sent": c.outbox.sent,
                "queued": c.outbox.queued,
                "in_flight": c.outbox.in_flight,
            }  # fmt: skip
            for c in self.connections
        ]
        return web.json_response(body)

    async def _ws(self, request):
        from aiohttp import WSMsgType, web

        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=4096)
        await ws.prepare(request)
        self._next_id += 1
        c = Connection(self._next_id, Outbox(self.depth, self.window))
        log.info("viewer: browser %d connected (%s)", c.id, request.remote)
        if self._model_text is not None:
            c.control.append(self._model_text)
        # the last frames (the page can step back through them; after the stream ended it
        # still shows the end)
        hist = list(self.history)
        self.connections.add(c)
        sender = asyncio.create_task(self._send_loop(ws, c, hist), name=f"view-send-{c.id}")
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    self._on_text(c, msg.data)
        finally:
            self.connections.discard(c)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await sender
            log.info("viewer: browser %d left (sent %s, dropped %d)", c.id,
                     plural(c.outbox.sent, "frame"), c.outbox.dropped)  # fmt: skip
        return ws

    def _on_text(self, c: Connection, data: str) -> None:
        try:
            msg = json.loads(data)
            seq = int(msg["ack"])
        except (ValueError, KeyError, TypeError):
            return  # the page only acknowledges; anything else is ignored
        c.outbox.ack(seq)
        c.wake.set()

    async def _send_loop(self, ws, c: Connection, hist: list[tuple[int, bytes]]) -> None:
        while c.control:
            await ws.send_str(c.control.popleft())
        for _, data in hist:  # history frames are not acknowledged
            await ws.send_bytes(data)
        await ws.send_str(json.dumps({"type": "history_end", "frames": len(hist)}))
        while not ws.closed:
            await c.wake.wait()
            c.wake.clear()
            while c.control:
                await ws.send_str(c.control.popleft())
            while (item := c.outbox.pop()) is not None:
                await ws.send_bytes(item[1])

    async def _stats_loop(self) -> None:
        last_log = self.clock()
        while True:
            await asyncio.sleep(self.stats_every_s)
            for c in list(self.connections):
                c.control.append(json.dumps(self.stats(c)))
                c.wake.set()
            now = self.clock()
            if now - last_log >= self.log_every_s:
                last_log = now
                s = self.stats()
                log.info("viewer: in %.0f/s (seq %s), latency p50 %s ms p99 %s ms, "
                         "%d browser(s), %d frames sent, dropped %d (browsers) + %d (subscriber)",
                         s["rate_in"], s["last_seq"], _ms(s["lat_p50"]), _ms(s["lat_p99"]),
                         s["connections"], s["frames_out"], s["dropped_total"],
                         s["subscriber_dropped"])  # fmt: skip
