"""The live view's web server: Starlette (ASGI) under uvicorn, pushing snapshots by server-sent events.

Routes (described for clients in :mod:`passt_mav.view.openapi`, served at ``/api/openapi.json``): ``/`` the
page; ``/static/...`` its files (Leaflet vendored, no CDN); ``/api/state`` one snapshot (JSON);
``/api/stream`` server-sent events, one ``data:`` line with a snapshot whenever a file of the run changes
(polled every :data:`POLL_S` once for all the streams open); ``/api/raster/{what}.png?leg=N`` the rasters (:meth:`RunState.raster`);
``POST /api/command`` the operator's command to the controller, appended to the run's command channel
(:mod:`passt_mav.runs.commands`). Every request passes :class:`~passt_mav.view.gate.Gate` first (Host, Origin,
token, rate; docs/console.md). A bad parameter is a 4xx with one line naming it, never a 500.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from passt_mav.view.gate import Addresses, FailureLimit, Gate, OpenLimit, RateLimit, is_loopback
from passt_mav.view.state import RunState, signature

__all__ = ["make_app", "serve", "POLL_S", "MAX_BODY", "is_loopback"]

STATIC = Path(__file__).resolve().parent / "static"
POLL_S = 0.4
#: bytes a command's body may have
MAX_BODY = 4096
#: the largest leg index a raster request may name (a run has far fewer legs)
MAX_LEG = 100_000


def _control(request, state: RunState, snap: dict | None = None) -> dict:
    """What the page may do for this request: ``token`` (it holds the run's token: it may command) and
    ``finished`` (the run is over: nothing to command)."""
    auth = request.scope.get("passt_auth") or {}
    finished = bool(snap["finished"]) if snap is not None else state.finished()
    return {"token": bool(auth.get("token")), "finished": finished}


def make_app(
    root: str | Path,
    *,
    token: str,
    host: str = "127.0.0.1",
    port: int = 0,
    rate: RateLimit | None = None,
    failures: FailureLimit | None = None,
    reads: FailureLimit | None = None,
    streams: OpenLimit | None = None,
):
    """The ASGI app serving the run in ``root``, bound to ``host``:``port`` (the names it answers to), with
    this run's ``token`` (reading without it only on loopback; commanding never). ``rate``/``failures``/
    ``reads``/``streams``: the :class:`~passt_mav.view.gate.Gate`'s limits of commands, of failed
    authentications per client, of reads without the token per client and of open event streams per client."""
    from starlette.applications import Starlette
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response, StreamingResponse
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles

    from passt_mav import __version__
    from passt_mav.runs.commands import CommandError, append_command, validate
    from passt_mav.runs.rundir import RunDirError
    from passt_mav.view.openapi import RASTERS, openapi

    state = RunState(root)
    spec = openapi(__version__)

    def bad(code: int, text: str) -> Response:
        return PlainTextResponse(f"passt-mav view: {text}", status_code=code)

    async def index(request):
        # no cookie: the page keeps the address's token in sessionStorage (per port; passt_mav/view/gate.py)
        return FileResponse(
            STATIC / "index.html", headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"}
        )

    async def api_state(request):
        snap = await run_in_threadpool(state.snapshot)
        snap["control"] = _control(request, state, snap)
        return JSONResponse(snap, headers={"Cache-Control": "no-store"})

    # one poll of the run directory every POLL_S for all the open streams (not one each: a hundred open streams
    # once kept the thread pool busy with signatures and starved every other request)
    feed = {"t": -1e9, "sig": None, "snap": None}
    feed_lock = asyncio.Lock()

    async def latest():
        async with feed_lock:
            now = asyncio.get_running_loop().time()
            if now - feed["t"] >= POLL_S * 0.9:
                sig = await run_in_threadpool(signature, state.root)
                if sig != feed["sig"] or feed["snap"] is None:
                    feed["snap"] = await run_in_threadpool(state.snapshot)
                    feed["sig"] = sig
                feed["t"] = asyncio.get_running_loop().time()
            return feed["sig"], feed["snap"]

    async def stream(request):
        async def events():
            last, quiet = None, 0.0
            while True:
                sig, shared = await latest()
                if sig != last:
                    snap = dict(shared)
                    snap["control"] = _control(request, state, snap)
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
        if what not in RASTERS:
            return bad(404, f"no raster {what[:40]!r}; one of {', '.join(RASTERS)}")
        leg = request.query_params.get("leg")
        try:
            leg_i = None if leg in (None, "", "null") else int(leg)
        except ValueError:
            return bad(400, f"leg must be an integer, got {leg[:40]!r}")
        if leg_i is not None and not 0 <= leg_i <= MAX_LEG:
            return bad(400, f"leg must be 0..{MAX_LEG}, got {leg_i}")
        try:
            png = await run_in_threadpool(state.raster, what, leg_i)
        except RunDirError as exc:
            return bad(404, str(exc))
        if png is None:
            return bad(404, f"no {what} raster for leg {leg_i} (yet)")
        return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    async def command(request):
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return bad(415, "a command is a JSON body (Content-Type: application/json)")
        size = request.headers.get("content-length", "")
        if size and (not size.isdigit() or int(size) > MAX_BODY):
            return bad(413, f"a command's body is at most {MAX_BODY} bytes")
        body = b""
        async for chunk in request.stream():
            body += chunk
            if len(body) > MAX_BODY:
                return bad(413, f"a command's body is at most {MAX_BODY} bytes")
        try:
            data = json.loads(body.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            return bad(400, "the body is not valid JSON")
        except RecursionError:  # arrays or objects nested deeper than the parser goes (2,048 '[' fit in 4 KiB)
            return bad(400, "the body is not valid JSON: nested too deep")
        try:
            cmd = validate(data, state.n_boats())
        except CommandError as exc:
            return bad(400, str(exc))
        if state.finished():
            return bad(409, "the run has finished: there is nothing to command")
        client = request.client.host if request.client else "?"
        rec = await run_in_threadpool(append_command, state.root, cmd, source=f"view {client}")
        return JSONResponse(rec, status_code=202)

    async def api_openapi(request):
        return JSONResponse(spec)

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/state", api_state),
            Route("/api/stream", stream),
            Route("/api/raster/{what}.png", raster),
            Route("/api/command", command, methods=["POST"]),
            Route("/api/openapi.json", api_openapi),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ]
    )
    return Gate(
        app,
        token=token,
        addresses=Addresses(host, port),
        read_open=is_loopback(host),
        rate=rate,
        failures=failures,
        reads=reads,
        streams=streams,
    )


def serve(root: str | Path, *, host: str = "127.0.0.1", port: int = 0, token: str, on_ready=None) -> None:
    """Serve the run in ``root`` until interrupted (blocking). ``port`` 0 picks a free one;
    ``on_ready(port)`` is called once it listens."""
    import socket

    import uvicorn

    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, int(port)))
    sock.listen(64)
    bound = sock.getsockname()[1]
    app = make_app(root, token=token, host=host, port=bound)
    # an open event stream never ends by itself: a stop (SIGTERM, Ctrl-C) closes it after 2 s rather than wait
    config = uvicorn.Config(
        app, log_level="warning", access_log=False, lifespan="off", server_header=False, timeout_graceful_shutdown=2
    )
    server = uvicorn.Server(config)
    if on_ready is not None:
        on_ready(bound)
    server.run(sockets=[sock])
