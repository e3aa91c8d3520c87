"""Who may talk to the view server: Host and Origin against the bound address, the per-run token, the rate.

The view server binds one address (127.0.0.1 by default). :class:`Gate` (ASGI middleware) answers before
any route:

* ``Host`` must name this server (:class:`Addresses`): a web page elsewhere that points its own domain at
  127.0.0.1 (DNS rebinding) is refused, 403.
* ``Origin``, when a browser sends one, must be this server's own ``http://HOST:PORT``; a cross-site
  request is refused, 403. A command (POST) carries an Origin (browsers always send it on POST) or the
  token in the ``X-Passt-Token`` header (a script: browsers cannot set that header cross-site).
* The token (made per run, printed in the address ``?token=...``) is set by the first page load that
  carries it as an httponly, ``SameSite=Strict`` cookie (per port: two views on one machine keep theirs).
  Reading needs it unless the server is bound to loopback; commanding always needs it (cookie or header,
  never the query string, which ends up in logs and histories).
* Commands are rate-limited (:class:`RateLimit`): past the limit 429 with ``Retry-After``.

Every refusal is one line of text naming the reason, never a stack trace.
"""

from __future__ import annotations

import ipaddress
import secrets
import socket
import threading
import time
from collections import deque

__all__ = ["Addresses", "Gate", "RateLimit", "TOKEN_HEADER", "cookie_name", "is_loopback"]

TOKEN_HEADER = "x-passt-token"


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback IP literals (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def cookie_name(port: int) -> str:
    """The token cookie of the server on ``port`` (cookies are per host, not per port)."""
    return f"passt_view_{int(port)}"


def _split_hostport(text: str, default_port: int) -> tuple[str, int] | None:
    """``host[:port]`` or ``[v6][:port]`` -> (host lower-case without brackets, port); None if malformed."""
    text = text.strip().lower()
    if not text or any(c.isspace() for c in text) or "/" in text or "@" in text:
        return None
    if text.startswith("["):
        host, sep, rest = text[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            return None
        port_s = rest[1:] if rest else ""
    else:
        host, _, port_s = text.rpartition(":") if text.count(":") == 1 else (text, "", "")
        if text.count(":") > 1:
            return None  # a bare IPv6 address must be bracketed
    if port_s:
        if not port_s.isdigit() or len(port_s) > 5:
            return None
        port = int(port_s)
    else:
        port = default_port
    return (host, port) if host else None


class Addresses:
    """The names a request may use for a server bound to ``host``:``port`` (the ``Host`` and ``Origin`` check).

    Loopback: 127.0.0.1, localhost, ::1. A specific address: itself. A wildcard (0.0.0.0, ::): any IP literal
    (the machine's addresses are not known in advance), localhost, and the machine's host name (and
    ``NAME.local``): never another DNS name, which is what a rebinding attack uses.
    """

    def __init__(self, host: str, port: int):
        self.host, self.port = host.strip("[]").lower(), int(port)
        self.wildcard = self.host in ("0.0.0.0", "::", "")
        names = {self.host}
        if is_loopback(self.host) or self.wildcard:
            names |= {"127.0.0.1", "localhost", "::1"}
        if self.wildcard:
            hn = socket.gethostname().lower()
            names |= {hn, f"{hn}.local"}
        self.names = names

    def allows(self, hostport: str) -> bool:
        """True when ``hostport`` (a Host header, or an Origin's ``host:port``) names this server."""
        hp = _split_hostport(hostport, 80)
        if hp is None or hp[1] != self.port:
            return False
        host = hp[0]
        if host in self.names:
            return True
        if self.wildcard:
            try:
                ipaddress.ip_address(host)
                return True
            except ValueError:
                return False
        return False


class RateLimit:
    """At most ``n`` events in any ``window_s`` seconds (monotonic clock); thread-safe."""

    def __init__(self, n: int = 10, window_s: float = 10.0, clock=time.monotonic):
        self.n, self.window_s, self.clock = int(n), float(window_s), clock
        self._times: deque[float] = deque()
        self._lock = threading.Lock()

    def take(self) -> float:
        """0 when one more event is allowed now (and counts it), else the seconds to wait."""
        with self._lock:
            now = self.clock()
            while self._times and now - self._times[0] >= self.window_s:
                self._times.popleft()
            if len(self._times) >= self.n:
                return self.window_s - (now - self._times[0])
            self._times.append(now)
            return 0.0


def _headers(scope) -> dict[str, str]:
    """The request's headers, lower-case names; a repeated header -> "" (ambiguous: refused where it matters)."""
    out: dict[str, str] = {}
    for k, v in scope.get("headers") or []:
        name = k.decode("latin-1").lower()
        out[name] = "" if name in out else v.decode("latin-1")
    return out


def _cookie(headers: dict[str, str], name: str) -> str:
    from http.cookies import CookieError, SimpleCookie

    jar: SimpleCookie = SimpleCookie()
    try:
        jar.load(headers.get("cookie", ""))
    except CookieError:
        return ""
    m = jar.get(name)
    return m.value if m is not None else ""


def _query_token(scope) -> str:
    from urllib.parse import parse_qs

    try:
        q = parse_qs(scope.get("query_string", b"").decode("latin-1"), errors="strict")
    except (UnicodeDecodeError, ValueError):
        return ""
    vals = q.get("token") or [""]
    return vals[0] if len(vals) == 1 else ""


def _same(a: str, b: str) -> bool:
    return bool(a) and secrets.compare_digest(a.encode("utf-8", "replace"), b.encode("utf-8", "replace"))


class Gate:
    """ASGI middleware: the checks of the module docstring before ``app`` sees a request.

    ``token``: this run's token; ``addresses``: :class:`Addresses` of the bound socket; ``read_open``: reading
    needs no token (a loopback server). It puts ``scope["passt_auth"]`` = ``{"token": bool, "via": str}`` for
    the routes (a command needs ``token``).
    """

    def __init__(self, app, *, token: str, addresses: Addresses, read_open: bool, rate: RateLimit | None = None):
        self.app, self.token, self.addresses, self.read_open = app, token, addresses, read_open
        self.rate = rate or RateLimit()
        self.cookie = cookie_name(addresses.port)

    async def _refuse(self, scope, receive, send, code: int, text: str, headers: dict | None = None) -> None:
        from starlette.responses import PlainTextResponse

        await PlainTextResponse(f"passt-mav view: {text}", status_code=code, headers=headers)(scope, receive, send)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            if scope["type"] == "websocket":  # (no route uses one; refuse before any handshake)
                await send({"type": "websocket.close", "code": 1008})
                return
            await self.app(scope, receive, send)
            return
        h = _headers(scope)
        host = h.get("host", "")
        if not self.addresses.allows(host):
            await self._refuse(
                scope, receive, send, 403, f"Host {host[:80]!r} is not this server's address (DNS rebinding refused)"
            )
            return
        origin = h.get("origin")
        if origin is not None and not self._own_origin(origin, host):
            await self._refuse(scope, receive, send, 403, f"cross-site request from Origin {origin[:80]!r} refused")
            return
        via = ""
        if _same(h.get(TOKEN_HEADER, ""), self.token):
            via = "header"
        elif _same(_cookie(h, self.cookie), self.token):
            via = "cookie"
        elif _same(_query_token(scope), self.token):
            via = "query"
        method = scope.get("method", "GET").upper()
        if method not in ("GET", "HEAD"):
            if via not in ("header", "cookie"):
                await self._refuse(
                    scope, receive, send, 403, "a command needs this run's token (open the address the run printed)"
                )
                return
            if origin is None and via != "header":
                await self._refuse(scope, receive, send, 403, "a command by cookie needs the Origin header")
                return
            wait = self.rate.take()
            if wait > 0:
                await self._refuse(
                    scope,
                    receive,
                    send,
                    429,
                    f"too many commands: at most {self.rate.n} in {self.rate.window_s:g} s; try again in {wait:.0f} s",
                    headers={"Retry-After": str(max(1, round(wait)))},
                )
                return
        elif not via and not self.read_open:
            await self._refuse(scope, receive, send, 403, "token required (open the address the run printed)")
            return
        scope = dict(scope)
        scope["passt_auth"] = {"token": bool(via), "via": via, "cookie": self.cookie}
        await self.app(scope, receive, send)

    def _own_origin(self, origin: str, host: str) -> bool:
        """``origin`` is ``http://`` + the request's own (allowed) Host."""
        scheme, sep, rest = origin.partition("://")
        if scheme.lower() != "http" or not sep or "/" in rest:
            return False
        a, b = _split_hostport(rest, 80), _split_hostport(host, 80)
        return a is not None and a == b and self.addresses.allows(rest)
