"""The console's web side: a Starlette (ASGI) application, served by uvicorn on localhost.

======================================  =====================================================
route                                   what
======================================  =====================================================
``GET /``                               the page (``static/index.html``; its script and style
                                        beside it under ``/static/``)
``GET /api/daemons``                    every daemon's snapshot, a JSON list
                                        (:meth:`occ_console.model.DaemonView.snapshot`)
``GET /api/daemons/{id}``               one daemon's
``POST /api/daemons/{id}/{command}``    Enable, Run, Stop, EStop, Reset or Disable; answers
                                        ``{"command", "ok", "message"}`` with the daemon's
                                        reply: 200 done, 409 refused by the daemon, 503 not
                                        connected, 504 no answer in time
``GET /api/events``                     server-sent events: ``daemons`` (the list above) at
                                        every change, at most ``push_hz`` a second, and at
                                        least every ``refresh_s``
======================================  =====================================================

The daemons can be stopped from here, so the page is for this machine only: the server binds
a loopback address (the command refuses others), answers only requests whose ``Host`` is a
loopback name (a DNS-rebinding page cannot reach it), and takes commands only as
``Content-Type: application/json`` (which a page of another origin cannot send without a CORS
preflight, and none is granted).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from .link import COMMANDS, CommandTimeout, Console

STATIC = Path(__file__).with_name("static")

#: the Host header values the server answers (loopback names, any port)
LOOPBACK_HOSTS = ["127.0.0.1", "localhost", "::1", "[::1]"]


class Hub:
    """Hands the console's changes (I/O threads) to the event streams (the event loop)."""

    def __init__(self, console: Console, loop: asyncio.AbstractEventLoop) -> None:
        self.console = console
        self.loop = loop
        self.queues: set[asyncio.Queue[None]] = set()
        console.add_listener(self.changed)

    def changed(self) -> None:
        # any thread: only schedules; the loop fans out
        self.loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        for q in self.queues:
            if q.empty():
                q.put_nowait(None)

    def close(self) -> None:
        self.console.remove_listener(self.changed)


def begin_shutdown(app: Starlette) -> None:
    """End the event streams (any thread, a signal handler included): the server stops
    waiting for them at once instead of cancelling them after its graceful timeout."""
    app.state.stopping.set()
    hub: Hub | None = getattr(app.state, "hub", None)
    if hub is not None:
        hub.changed()


def create_app(console: Console, *, push_hz: float = 5.0, refresh_s: float = 1.0) -> Starlette:
    """The application for ``console`` (started and stopped with the application's
    lifespan)."""
    min_gap = 1.0 / push_hz

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        app.state.hub = Hub(console, asyncio.get_running_loop())
        console.start()
        try:
            yield
        finally:
            app.state.hub.close()
            # joins threads: off the event loop
            await asyncio.get_running_loop().run_in_executor(None, console.stop)

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def daemons(request: Request) -> Response:
        return JSONResponse(console.snapshot())

    async def daemon(request: Request) -> Response:
        link = console.link(request.path_params["ident"])
        if link is None:
            return JSONResponse({"error": "no such daemon"}, status_code=404)
        for snap in console.snapshot():
            if snap["id"] == link.view.id:
                return JSONResponse(snap)
        return JSONResponse({"error": "no such daemon"}, status_code=404)

    async def command(request: Request) -> Response:
        link = console.link(request.path_params["ident"])
        if link is None:
            return JSONResponse({"error": "no such daemon"}, status_code=404)
        wanted = request.path_params["command"].lower()
        name = next((c for c in COMMANDS if c.lower() == wanted), None)
        if name is None:
            return JSONResponse(
                {"error": f"unknown command; one of {', '.join(COMMANDS)}"}, status_code=404
            )
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return JSONResponse(
                {"error": "send commands with Content-Type: application/json"}, status_code=415
            )
        if not link.client.connected:
            return JSONResponse(
                {"command": name, "ok": False, "message": f"{link.view.address} not connected"},
                status_code=503,
            )
        try:
            reply: dict[str, Any] = await asyncio.wrap_future(link.command(name))
        except CommandTimeout as err:
            return JSONResponse({"command": name, "ok": False, "message": str(err)}, 504)
        return JSONResponse(reply, status_code=200 if reply["ok"] else 409)

    async def events(request: Request) -> Response:
        hub: Hub = request.app.state.hub
        queue: asyncio.Queue[None] = asyncio.Queue(maxsize=1)
        hub.queues.add(queue)

        stopping = request.app.state.stopping

        async def stream() -> AsyncIterator[str]:
            loop = asyncio.get_running_loop()
            try:
                yield "retry: 1000\n\n"
                while not stopping.is_set():
                    data = json.dumps(console.snapshot(), separators=(",", ":"))
                    yield f"event: daemons\ndata: {data}\n\n"
                    sent = loop.time()
                    try:
                        await asyncio.wait_for(queue.get(), refresh_s)
                    except TimeoutError:
                        # nothing new: the snapshot again all the same (the ages in it grow:
                        # a daemon that stopped answering shows it)
                        continue
                    if stopping.is_set():
                        break
                    # at most push_hz updates a second, however fast the daemons talk
                    await asyncio.sleep(max(0.0, sent + min_gap - loop.time()))
                    with contextlib.suppress(asyncio.QueueEmpty):
                        queue.get_nowait()
            finally:
                hub.queues.discard(queue)

        return StreamingResponse(
            stream(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )

    routes = [
        Route("/", index),
        Route("/api/daemons", daemons),
        Route("/api/daemons/{ident}", daemon),
        Route("/api/daemons/{ident}/{command}", command, methods=["POST"]),
        Route("/api/events", events),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    app = Starlette(
        routes=routes,
        lifespan=lifespan,
        middleware=[Middleware(TrustedHostMiddleware, allowed_hosts=LOOPBACK_HOSTS)],
    )
    app.state.stopping = threading.Event()
    return app
