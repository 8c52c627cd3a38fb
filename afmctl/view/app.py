"""The web side of ``afmctl view``: a starlette app served by uvicorn.

``GET /`` the page, ``GET /static/...`` its script and style (shipped in the package),
``GET /api/snapshot`` the current picture as JSON (for scripts), ``WS /ws`` the live feed:
the server sends a JSON frame holding only what that page has not seen (decimated rows,
bounded by the server's rings), the image every ``image_every`` frames, and the next one
when the page has answered the last with any text message, at most every
``1/frame_rate_Hz`` s (flow control: a page that cannot keep up never falls behind, it
gets fewer frames)."""
from __future__ import annotations

import asyncio
import logging
import socket
from importlib import resources
from typing import Any

from starlette.applications import Starlette
from starlette.responses import FileResponse, JSONResponse
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from .feed import ViewFeed

log = logging.getLogger(__name__)


def static_dir() -> str:
    """The folder of the page's files inside the installed package."""
    return str(resources.files("afmctl.view") / "static")


def build_frame(feed: ViewFeed, cursors: dict[str, dict[str, int]], with_image: bool) -> dict[str, Any]:
    """One websocket frame: per scanner, what this page has not seen yet."""
    scanners = {}
    for name, f in sorted(feed.feeds().items()):
        scanners[name] = f.frame(cursors.setdefault(name, {}), with_image)
    return {"scanners": scanners, "history_s": feed.history_s, "display_rate_Hz": feed.display_rate_Hz,
            "max_rows": feed.max_rows}


def make_app(feed: ViewFeed, *, frame_rate_Hz: float = 10.0, image_every: int = 5) -> Starlette:
    """The starlette application serving ``feed``."""
    period_s = 1.0 / frame_rate_Hz

    async def index(request: Any) -> FileResponse:
        return FileResponse(f"{static_dir()}/index.html", headers={"Cache-Control": "no-store"})

    async def snapshot(request: Any) -> JSONResponse:
        return JSONResponse(build_frame(feed, {}, True))

    async def live(ws: WebSocket) -> None:
        await ws.accept()
        cursors: dict[str, dict[str, int]] = {}
        clock = asyncio.get_running_loop().time
        n = 0
        try:
            while True:
                t0 = clock()
                await ws.send_json(build_frame(feed, cursors, n % image_every == 0))
                n += 1
                # the next frame once the page took this one: a slow page gets fewer, larger
                # frames instead of a queue that grows (its view would fall seconds behind)
                await ws.receive_text()
                await asyncio.sleep(max(0.0, period_s - (clock() - t0)))
        except (WebSocketDisconnect, RuntimeError, OSError):
            log.debug("page left")

    routes = [Route("/", index), Route("/api/snapshot", snapshot), WebSocketRoute("/ws", live),
              Mount("/static", StaticFiles(directory=static_dir()), name="static")]
    return Starlette(routes=routes)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: any free port)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    sock.listen(64)
    return sock


def serve(app: Starlette, sock: socket.socket, early: Any = None) -> None:
    """Serve ``app`` on ``sock`` until Ctrl-C / SIGTERM (uvicorn handles both while it runs;
    ``early.attach(server)`` hands it a stop that came before)."""
    import uvicorn
    config = uvicorn.Config(app, log_level="warning", ws="websockets-sansio", lifespan="off")
    server = uvicorn.Server(config)
    if early is not None:
        early.attach(server)
    server.run(sockets=[sock])
