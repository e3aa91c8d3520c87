"""The live view's web server: Starlette (ASGI) under uvicorn, pushing snapshots by server-sent events.

Routes: ``/`` the page; ``/static/...`` its files (Leaflet vendored, no CDN); ``/api/state`` one
snapshot (JSON); ``/api/stream`` server-sent events, one ``data:`` line with a snapshot whenever a
file of the run changes (polled every :data:`POLL_S`); ``/api/raster/{what}.png?leg=N`` the
rasters (:meth:`RunState.raster`). With a token (any host but loopback) every request must carry
it: ``?token=...`` once (the page's address), then the cookie set by that answer.
"""

from __future__ import annotations

import asyncio
import json
import secrets
from pathlib import Path

from passt_mav.view.state import RunState, signature

__all__ = ["make_app", "serve", "POLL_S"]

STATIC = Path(__file__).resolve().parent / "static"
POLL_S = 0.4
COOKIE = "passt_view_token"


class _TokenGate:
    """ASGI middleware: 403 for any request without the token (query ``token`` or the cookie)."""

    def __init__(self, app, token: str):
        self.app, self.token = app, token

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            from starlette.requests import Request
            from starlette.responses import PlainTextResponse

            req = Request(scope)
            got = req.query_params.get("token") or req.cookies.get(COOKIE) or ""
            if not secrets.compare_digest(got.encode(), self.token.encode()):
                await PlainTextResponse("passt-mav view: token required", status_code=403)(scope, receive, send)
                return
        await self.app(scope, receive, send)


def make_app(root: str | Path, *, token: str | None = None):
    """The ASGI app serving the run in ``root``."""
    from starlette.applications import Starlette
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles

    state = RunState(root)

    async def index(request):
        resp = FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})
        if token:
            resp.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        return resp

    async def api_state(request):
        return JSONResponse(await run_in_threadpool(state.snapshot))

    async def stream(request):
        async def events():
            last, quiet = None, 0.0
            while True:
                sig = await run_in_threadpool(signature, state.root)
                if sig != last:
                    snap = await run_in_threadpool(state.snapshot)
                    last, quiet = sig, 0.0
                    yield f"data: {json.dumps(snap, allow_nan=False, default=str)}\n\n"
                elif quiet > 10.0:
                    quiet = 0.0
                    yield ": keep-alive\n\n"
                await asyncio.sleep(POLL_S)
                quiet += POLL_S

        return StreamingResponse(
            events(), media_type="text/event-stream", headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
        )

    async def raster(request):
        what = request.path_params["what"]
        leg = request.query_params.get("leg")
        try:
            leg_i = None if leg in (None, "", "null") else int(leg)
        except ValueError:
            return Response("leg must be an integer", status_code=400)
        png = await run_in_threadpool(state.raster, what, leg_i)
        if png is None:
            return Response(status_code=404)
        return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/state", api_state),
            Route("/api/stream", stream),
            Route("/api/raster/{what}.png", raster),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ]
    )
    return _TokenGate(app, token) if token else app


def is_loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def serve(root: str | Path, *, host: str = "127.0.0.1", port: int = 0, token: str | None = None, on_ready=None) -> None:
    """Serve the run in ``root`` until interrupted (blocking). ``port`` 0 picks a free one;
    ``on_ready(port)`` is called once it listens."""
    import socket

    import uvicorn

    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, int(port)))
    sock.listen(64)
    config = uvicorn.Config(make_app(root, token=token), log_level="warning", access_log=False, lifespan="off")
    server = uvicorn.Server(config)
    if on_ready is not None:
        on_ready(sock.getsockname()[1])
    server.run(sockets=[sock])
