"""Who may talk to the view server: Host and Origin against the bound address, the per-run token, the rate.

The view server binds one address (127.0.0.1 by default). :class:`Gate` (ASGI middleware) answers before
any route:

* ``Host`` must name this server (:class:`Addresses`): a web page elsewhere that points its own domain at
  127.0.0.1 (DNS rebinding) is refused, 403.
* ``Origin``, when a browser sends one, must be this server's own ``http://HOST:PORT``; a cross-site
  request is refused, 403. A command (POST) needs the token in the ``X-Passt-Token`` header, which only
  this server's own page (and a script) can set: browsers refuse a custom header cross-site.
* The token (made per run, printed in the address ``?token=...``) is never put in a cookie: browsers send a
  cookie of 127.0.0.1 to every port of 127.0.0.1, so another local server would receive it. The page keeps it
  in ``sessionStorage`` (per origin: scheme, host *and* port) and sends it in the ``X-Passt-Token`` header on
  commands and in the query string of its reads. A cookie is never accepted as a credential.
  Reading run data needs the token unless the server is bound to loopback (the page's shell, ``/`` and
  ``/static/...``, holds no run data and is open); commanding always needs it in the header (never the query
  string, which ends up in logs and histories).
* Commands are rate-limited (:class:`RateLimit`): past the limit 429 with ``Retry-After``.
* Reads without the token are rate-limited per client address (:data:`READS` in :data:`READS_WINDOW_S` s) and
  so are open event streams (:data:`MAX_STREAMS` at a time per client address; streams with the token are
  counted apart, so that a local process cannot crowd the operator's page out): past either, 429.
* Failed authentication is rate-limited per client address (:class:`FailureLimit`): after
  :data:`AUTH_FAILURES` requests without the right token in :data:`AUTH_WINDOW_S` seconds, every request of that
  client that needs the token is answered 429 with ``Retry-After`` until the window has passed, the right
  token included (a guess that would have been right cannot be told from a wrong one).

Every refusal is one line of text naming the reason, never a stack trace.
"""

from __future__ import annotations

import ipaddress
import secrets
import socket
import threading
import time
from collections import deque

__all__ = [
    "Addresses",
    "AUTH_FAILURES",
    "AUTH_WINDOW_S",
    "FailureLimit",
    "Gate",
    "MAX_STREAMS",
    "OpenLimit",
    "READS",
    "READS_WINDOW_S",
    "RateLimit",
    "TOKEN_HEADER",
    "is_loopback",
]

TOKEN_HEADER = "x-passt-token"
#: requests without the right token one client may make in :data:`AUTH_WINDOW_S` seconds before it is answered 429
AUTH_FAILURES = 20
AUTH_WINDOW_S = 60.0
#: reads without the token one client may make in :data:`READS_WINDOW_S` seconds before it is answered 429
READS = 600
READS_WINDOW_S = 60.0
#: event streams (``/api/stream``) one client may hold open at a time without the token (and, apart, with it)
MAX_STREAMS = 16


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback IP literals (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


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


class FailureLimit:
    """Failed authentications per client: at most ``n`` in any ``window_s`` seconds (monotonic clock), remembered
    for at most ``max_clients`` clients (the oldest forgotten first); thread-safe."""

    def __init__(
        self, n: int = AUTH_FAILURES, window_s: float = AUTH_WINDOW_S, clock=time.monotonic, max_clients: int = 4096
    ):
        self.n, self.window_s, self.clock, self.max_clients = int(n), float(window_s), clock, int(max_clients)
        self._fails: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> deque[float]:
        q = self._fails.get(client)
        if q is None:
            return deque()
        while q and now - q[0] >= self.window_s:
            q.popleft()
        if not q:
            del self._fails[client]
        return q

    def wait(self, client: str) -> float:
        """0 when ``client`` may try its token now, else the seconds until it may."""
        with self._lock:
            now = self.clock()
            q = self._recent(client, now)
            return self.window_s - (now - q[0]) if len(q) >= self.n else 0.0

    def fail(self, client: str) -> None:
        """Count one failed authentication of ``client``."""
        with self._lock:
            self._count(client, self.clock())

    def _count(self, client: str, now: float) -> None:
        q = self._recent(client, now)
        if client not in self._fails:
            if len(self._fails) >= self.max_clients:
                self._fails.pop(next(iter(self._fails)))
            self._fails[client] = q
        q.append(now)
        while len(q) > self.n:
            q.popleft()

    def take(self, client: str) -> float:
        """One more event of ``client`` (a read without the token): 0 when allowed now (and counted), else the
        seconds until it is (not counted)."""
        with self._lock:
            now = self.clock()
            q = self._recent(client, now)
            if len(q) >= self.n:
                return self.window_s - (now - q[0])
            self._count(client, now)
            return 0.0


class OpenLimit:
    """At most ``n`` things (event streams) open at a time per client; thread-safe."""

    def __init__(self, n: int = MAX_STREAMS):
        self.n = int(n)
        self._open: dict[str, int] = {}
        self._lock = threading.Lock()

    def open(self, client: str) -> bool:
        """Count one more open by ``client``; False (and not counted) when it already holds ``n``."""
        with self._lock:
            k = self._open.get(client, 0)
            if k >= self.n:
                return False
            self._open[client] = k + 1
            return True

    def close(self, client: str) -> None:
        """One of ``client``'s has closed."""
        with self._lock:
            k = self._open.get(client, 0) - 1
            if k > 0:
                self._open[client] = k
            else:
                self._open.pop(client, None)

    def count(self, client: str) -> int:
        with self._lock:
            return self._open.get(client, 0)


def _headers(scope) -> dict[str, str]:
    """The request's headers, lower-case names; a repeated header -> "" (ambiguous: refused where it matters)."""
    out: dict[str, str] = {}
    for k, v in scope.get("headers") or []:
        name = k.decode("latin-1").lower()
        out[name] = "" if name in out else v.decode("latin-1")
    return out


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
    the routes (a command needs ``token``). ``rate``: the commands' :class:`RateLimit`; ``failures``: the
    failed authentications' :class:`FailureLimit` (per client); ``reads``: the reads without the token
    (a :class:`FailureLimit` counting every one, per client); ``streams``: the open event streams per client
    (:class:`OpenLimit`).
    """

    def __init__(
        self,
        app,
        *,
        token: str,
        addresses: Addresses,
        read_open: bool,
        rate: RateLimit | None = None,
        failures: FailureLimit | None = None,
        reads: FailureLimit | None = None,
        streams: OpenLimit | None = None,
    ):
        self.app, self.token, self.addresses, self.read_open = app, token, addresses, read_open
        self.rate = rate or RateLimit()
        self.failures = failures or FailureLimit()
        self.reads = reads or FailureLimit(READS, READS_WINDOW_S)
        self.streams = streams or OpenLimit()

    async def _auth_failed(self, scope, receive, send, client: str, text: str) -> None:
        """403 naming the reason, counted against ``client`` (:class:`FailureLimit`)."""
        self.failures.fail(client)
        await self._refuse(scope, receive, send, 403, text)

    async def _locked_out(self, scope, receive, send, client: str) -> bool:
        """429 (and True) while ``client`` has failed authentication too often."""
        wait = self.failures.wait(client)
        if wait <= 0:
            return False
        await self._refuse(
            scope,
            receive,
            send,
            429,
            f"too many requests without the right token: at most {self.failures.n} in {self.failures.window_s:g} s; "
            f"try again in {wait:.0f} s",
            headers={"Retry-After": str(max(1, round(wait)))},
        )
        return True

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
        via = ""  # (a cookie is never a credential: other ports of this host receive it too)
        if _same(h.get(TOKEN_HEADER, ""), self.token):
            via = "header"
        elif _same(_query_token(scope), self.token):
            via = "query"
        method = scope.get("method", "GET").upper()
        client = str((scope.get("client") or ("?",))[0])
        path = scope.get("path", "")
        reading = method in ("GET", "HEAD")
        shell = reading and (path == "/" or path.startswith("/static/"))  # the page's files: no run data
        needs_token = not reading or not (self.read_open or shell)
        if needs_token and await self._locked_out(scope, receive, send, client):
            return
        if not reading:
            if via != "header":
                await self._auth_failed(
                    scope,
                    receive,
                    send,
                    client,
                    "a command needs this run's token in the X-Passt-Token header (open the address the run printed)",
                )
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
        elif not via:
            if needs_token:
                await self._auth_failed(
                    scope, receive, send, client, "token required (open the address the run printed)"
                )
                return
            wait = self.reads.take(client)
            if wait > 0:
                await self._refuse(
                    scope,
                    receive,
                    send,
                    429,
                    f"too many reads without the token: at most {self.reads.n} in {self.reads.window_s:g} s; "
                    f"try again in {wait:.0f} s",
                    headers={"Retry-After": str(max(1, round(wait)))},
                )
                return
        scope = dict(scope)
        scope["passt_auth"] = {"token": bool(via), "via": via}
        if not (reading and path == "/api/stream"):
            await self.app(scope, receive, send)
            return
        key = f"{client} token" if via else client  # the operator's page is not crowded out by tokenless ones
        if not self.streams.open(key):
            await self._refuse(
                scope,
                receive,
                send,
                429,
                f"too many open event streams from {client[:60]}: at most {self.streams.n} at a time",
                headers={"Retry-After": "10"},
            )
            return
        try:
            await self.app(scope, receive, send)
        finally:
            self.streams.close(key)

    def _own_origin(self, origin: str, host: str) -> bool:
        """``origin`` is ``http://`` + the request's own (allowed) Host."""
        scheme, sep, rest = origin.partition("://")
        if scheme.lower() != "http" or not sep or "/" in rest:
            return False
        a, b = _split_hostport(rest, 80), _split_hostport(host, 80)
        return a is not None and a == b and self.addresses.allows(rest)
