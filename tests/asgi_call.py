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


async def _call(app, method: str, path: str, query: bytes, headers: list[tuple[str, str]], body: bytes) -> Reply:
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

    scope = {
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
        "client": ("127.0.0.1", 50000),
        "server": ("127.0.0.1", 80),
    }
    await asyncio.wait_for(app(scope, receive, send), timeout=60.0)
    return reply


def call(loop, app, method: str, path: str, *, query: str = "", headers=(), body: bytes = b"") -> Reply:
    """``method path?query`` with ``headers`` ((name, value) pairs, Latin-1) and ``body`` on ``app``, run on
    the event loop ``loop``."""
    return loop.run_until_complete(_call(app, method, path, query.encode("latin-1"), list(headers), body))
