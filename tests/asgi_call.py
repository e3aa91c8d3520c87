"""One HTTP request to an ASGI app, in-process: the view server's security tests and its fuzz.

Hand-written (~40 lines) because Starlette's TestClient needs httpx, which the project does not depend on,
and because ``/api/stream`` never ends: here the client disconnects once the first chunk of a body arrives.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field


@dataclass
class Reply:
    status: int
    headers: dict[str, str] = field(default_factory=dict)
    body: bytes = b""
    set_cookies: list[str] = field(default_factory=list)


async def _call(
    app, method: str, path: str, query: bytes, headers: list[tuple[str, str]], body: bytes, client=("127.0.0.1", 50000)
) -> Reply:
    got_body = asyncio.Event()
    sent = False
    reply = Reply(0)

    async def receive():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        await got_body.wait()  # a streaming response: disconnect after its first chunk
        return {"type": "http.disconnect"}

    async def send(msg):
        if msg["type"] == "http.response.start":
            reply.status = msg["status"]
            for k, v in msg.get("headers") or []:
                name, val = k.decode("latin-1").lower(), v.decode("latin-1")
                if name == "set-cookie":
                    reply.set_cookies.append(val)
                reply.headers[name] = val
        elif msg["type"] == "http.response.body":
            reply.body += msg.get("body", b"")
            if reply.body or not msg.get("more_body"):
                got_body.set()

    await asyncio.wait_for(app(_scope(method, path, query, headers, client), receive, send), timeout=60.0)
    return reply


def _scope(method: str, path: str, query: bytes, headers: list[tuple[str, str]], client) -> dict:
    return {
        "type": "http",
        "asgi": {"version": "3.0", "spec_version": "2.3"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode("utf-8", "surrogateescape"),
        "root_path": "",
        "query_string": query,
        "headers": [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in headers],
        "client": client,
        "server": ("127.0.0.1", 80),
    }


async def hold(app, path: str, *, release: asyncio.Event, query: str = "", headers=(), client=("127.0.0.1", 50000)):
    """A GET of ``path`` (an event stream) held open until ``release`` is set: (status, first body chunk, the task
    serving it), returned once the first chunk has arrived (a refusal's task is done by then)."""
    first: asyncio.Future = asyncio.get_running_loop().create_future()
    status = [0]
    sent = False

    async def receive():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": b"", "more_body": False}
        await release.wait()
        return {"type": "http.disconnect"}

    async def send(msg):
        if msg["type"] == "http.response.start":
            status[0] = msg["status"]
        elif msg["type"] == "http.response.body" and not first.done():
            first.set_result(msg.get("body", b""))

    scope = _scope("GET", path, query.encode("latin-1"), list(headers), client)
    task = asyncio.ensure_future(app(scope, receive, send))
    body = await asyncio.wait_for(first, timeout=60.0)
    return status[0], body, task


def call(
    loop, app, method: str, path: str, *, query: str = "", headers=(), body: bytes = b"", client=("127.0.0.1", 50000)
) -> Reply:
    """``method path?query`` with ``headers`` ((name, value) pairs, Latin-1) and ``body`` on ``app``, run on
    the event loop ``loop``, from ``client`` (host, port)."""
    return loop.run_until_complete(_call(app, method, path, query.encode("latin-1"), list(headers), body, client))
