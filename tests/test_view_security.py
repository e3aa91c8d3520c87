"""Issue 44, "nobody else can": the view server's gate (Host, Origin, token, rate), its 4xx for bad parameters,
its OpenAPI description, and a property-based fuzz of every operation it describes.

In-process (tests/asgi_call.py) except where the real server (uvicorn on loopback) or the command line is
the point. The fuzz prints its figures (requests, operations, failures); ``PASST_FUZZ_EXAMPLES=N`` runs N
examples per operation (3 N for the command; default 40).
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from asgi_call import call, hold
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_view import _get, make_live_run

from passt_mav.runs.commands import COMMANDS, CommandReader, read_commands
from passt_mav.view.gate import AUTH_FAILURES, MAX_STREAMS, FailureLimit, OpenLimit, RateLimit
from passt_mav.view.server import make_app

REPO = Path(__file__).resolve().parents[1]
TOKEN = "tok-" + "x" * 20
PORT = 8765
HOST = f"127.0.0.1:{PORT}"
ORIGIN = f"http://{HOST}"
#: the cookie the view once kept the token in: browsers send it to every port of 127.0.0.1 (issue 55)
OLD_COOKIE = f"passt_view_{PORT}"


@pytest.fixture(scope="module")
def loop():
    lp = asyncio.new_event_loop()
    yield lp
    lp.close()


@pytest.fixture(scope="module")
def run_root(tmp_path_factory):
    return make_live_run(tmp_path_factory.mktemp("sec") / "run").root


def _app(root, host="127.0.0.1", rate=None, failures=None, reads=None, streams=None):
    return make_app(
        root,
        token=TOKEN,
        host=host,
        port=PORT,
        rate=rate or RateLimit(10_000, 1.0),
        failures=failures or FailureLimit(10_000, 1.0),
        reads=reads or FailureLimit(100_000, 1.0),
        streams=streams,
    )


def _headers(host: str, origin: str | None, token_via: str | None) -> list[tuple[str, str]]:
    """Host, Origin (None: none) and the token by ``token_via``: cookie (the token in the cookie the view once
    set: never a credential), header, wrong (the header with another token), anything else: none."""
    h = [("host", host)]
    if origin is not None:
        h.append(("origin", origin))
    if token_via == "cookie":
        h.append(("cookie", f"{OLD_COOKIE}={TOKEN}"))
    elif token_via == "header":
        h.append(("x-passt-token", TOKEN))
    elif token_via == "wrong":
        h.append(("x-passt-token", TOKEN[:-1]))
    return h


def _post(
    loop, app, body, *, host=HOST, origin=ORIGIN, token_via="header", ctype="application/json", client=("127.0.0.1", 1)
):
    h = [*_headers(host, origin, token_via), ("content-type", ctype)]
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    return call(loop, app, "POST", "/api/command", headers=h, body=data, client=client)


# -- the gate, case by case --------------------------------------------------------------------------------
def test_foreign_host_is_refused_and_loopback_names_pass(loop, run_root):
    app = _app(run_root)
    for host in ("evil.example", f"evil.example:{PORT}", "127.0.0.1:1", "", "127.0.0.1:x", f"10.0.0.1:{PORT}"):
        r = call(loop, app, "GET", "/api/state", headers=[("host", host)])
        assert r.status == 403 and b"not this server's address" in r.body, (host, r.status)
    for host in (HOST, f"localhost:{PORT}", f"[::1]:{PORT}"):
        r = call(loop, app, "GET", "/api/state", headers=[("host", host)])
        assert r.status == 200, host
        assert json.loads(r.body)["control"] == {"token": False, "finished": False}  # reading needs no token here


def test_foreign_origin_is_refused_even_with_the_token(loop, run_root):
    app = _app(run_root)
    for origin in ("http://evil.example", "null", f"https://{HOST}", f"http://localhost:{PORT}", "http://127.0.0.1"):
        r = call(loop, app, "GET", "/api/state", headers=[("host", HOST), ("origin", origin)])
        assert r.status == 403 and b"cross-site" in r.body, origin
        r = _post(loop, app, {"action": "pause"}, origin=origin, token_via="header")
        assert r.status == 403, origin
    assert call(loop, app, "GET", "/api/state", headers=[("host", HOST), ("origin", ORIGIN)]).status == 200


def test_a_command_needs_the_token_in_the_header_never_a_cookie(loop, tmp_path):
    """Issue 55: a server on another port of 127.0.0.1 received the cookie ``passt_view_PORT=<token>`` (browsers
    send a host's cookies to all its ports) and a command carrying it was accepted. A cookie is no credential
    now, whatever its name, Origin or value: only the X-Passt-Token header commands."""
    root = make_live_run(tmp_path / "run").root
    app = _app(root)
    assert _post(loop, app, {"action": "pause"}, token_via=None).status == 403
    assert _post(loop, app, {"action": "pause"}, token_via="wrong").status == 403
    for origin in (ORIGIN, None):
        r = _post(loop, app, {"action": "pause"}, token_via="cookie", origin=origin)
        assert r.status == 403 and b"X-Passt-Token header" in r.body, (origin, r.status, r.body)
    h = [("host", HOST), ("origin", ORIGIN), ("content-type", "application/json"), ("cookie", f"token={TOKEN}")]
    assert call(loop, app, "POST", "/api/command", headers=h, body=b'{"action": "pause"}').status == 403
    # the query string never commands (it ends up in logs and histories)
    h = [("host", HOST), ("origin", ORIGIN), ("content-type", "application/json")]
    r = call(loop, app, "POST", "/api/command", query=f"token={TOKEN}", headers=h, body=b'{"action": "pause"}')
    assert r.status == 403
    assert read_commands(root) == ([], 0)  # nothing written by any refusal
    reader = CommandReader(root, 0)
    ok = _post(loop, app, {"action": "pause"}, token_via="header")  # the page: its own Origin and the header
    assert ok.status == 202
    ok2 = _post(loop, app, {"boat": 0, "action": "end", "end_mode": "RTL"}, token_via="header", origin=None)
    assert ok2.status == 202
    got = reader.poll()
    assert [(c["action"], c.get("end_mode")) for c in got] == [("pause", None), ("end", "RTL")]
    assert got[0]["id"] == json.loads(ok.body)["id"] and got[0]["source"] == "view 127.0.0.1"
    assert reader.poll() == []  # each command once
    # the page sees them, pending until the controller answers
    s = json.loads(call(loop, app, "GET", "/api/state", headers=[("host", HOST)]).body)
    assert [c["action"] for c in s["commands"]] == ["pause", "end"] and s["commands"][0]["result"] is None


def test_bad_commands_are_4xx_with_the_reason(loop, tmp_path):
    root = make_live_run(tmp_path / "run").root
    app = _app(root)
    cases = [
        ({"action": "fly"}, 400, b"action must be one of"),
        ({"action": "pause", "boat": 1}, 400, b"the run has 1 boat"),
        ({"action": "pause", "boat": -1}, 400, b"boat must be"),
        ({"action": "pause", "boat": True}, 400, b"boat must be"),
        ({"action": "end", "end_mode": "LAND"}, 400, b"end_mode must be"),
        ({"action": "pause", "end_mode": "RTL"}, 400, b"only for action 'end'"),
        ({"action": "pause", "x": 1}, 400, b"unknown field"),
        ({"action": "pause", "leg": 1}, 400, b"only for actions 'approve' and 'reject'"),
        ({"action": "approve", "leg": -1}, 400, b"leg must be"),
        ([1, 2], 400, b"JSON object"),
        (b"{not json", 400, b"not valid JSON"),
        (b"\xff\xfe", 400, b"not valid JSON"),
        (b"x" * 5000, 413, b"at most 4096"),
    ]
    for body, code, text in cases:
        r = _post(loop, app, body)
        assert r.status == code and text in r.body, (body, r.status, r.body)
    r = _post(loop, app, {"action": "pause"}, ctype="text/plain")
    assert r.status == 415
    assert not (root / COMMANDS).exists()
    # a finished run: nothing to command
    rd_summary = root / "summary.json"
    rd_summary.write_text(json.dumps({"status": "complete", "finished_utc": "2026-01-01T00:00:00Z"}))
    r = _post(loop, app, {"action": "pause"})
    assert r.status == 409 and b"finished" in r.body
    assert json.loads(call(loop, app, "GET", "/api/state", headers=[("host", HOST)]).body)["control"]["finished"]


def test_commands_are_rate_limited(loop, tmp_path):
    clock = [100.0]
    app = _app(make_live_run(tmp_path / "run").root, rate=RateLimit(3, 10.0, clock=lambda: clock[0]))
    codes = [_post(loop, app, {"action": "resume"}).status for _ in range(4)]
    assert codes == [202, 202, 202, 429]
    r = _post(loop, app, {"action": "resume"})
    assert r.status == 429 and r.headers["retry-after"] == "10" and b"too many commands" in r.body
    clock[0] += 10.0
    assert _post(loop, app, {"action": "resume"}).status == 202


def test_a_body_nested_deeper_than_the_parser_goes_is_400_never_500(loop, tmp_path):
    root = make_live_run(tmp_path / "run").root
    app = _app(root)
    for body in (b"[" * 2048 + b"]" * 2048, b'{"a":' * 819 + b"1", b"[" * 4096):
        assert len(body) <= 4096
        r = _post(loop, app, body)
        assert r.status == 400 and r.body.startswith(b"passt-mav view: the body is not valid JSON"), (r.status, r.body)
    for body in (
        b'{"a":' * 600 + b"1" + b"}" * 600,
        b"1e999",
        b"NaN",
        b'{"action": "pause", "boat": 1e999}',
        b"9" * 4096,
        rb'"\ud800"',
        b"\x00",
    ):
        r = _post(loop, app, body)
        assert r.status == 400, (body[:40], r.status, r.body)
    assert not (root / COMMANDS).exists()


def test_failed_authentication_is_rate_limited_per_client(loop, tmp_path):
    """3,000 wrong tokens from one client: the first AUTH_FAILURES are 403, the rest 429 with Retry-After, the right
    token included while it lasts (a right guess cannot be told from a wrong one); another client is not held; after
    the window the right token commands again. Reading a non-loopback server without the token counts too."""
    clock = [100.0]
    root = make_live_run(tmp_path / "run").root
    app = _app(root, failures=FailureLimit(clock=lambda: clock[0]))
    attacker, operator = ("127.0.0.1", 40000), ("127.0.0.2", 40001)
    codes = [_post(loop, app, {"action": "pause"}, token_via="wrong", client=attacker).status for _ in range(3000)]
    assert codes[:AUTH_FAILURES] == [403] * AUTH_FAILURES and set(codes[AUTH_FAILURES:]) == {429}
    r = _post(loop, app, {"action": "pause"}, token_via="header", client=attacker)
    assert r.status == 429 and r.headers["retry-after"] == "60" and b"without the right token" in r.body
    assert _post(loop, app, {"action": "pause"}, token_via="header", client=operator).status == 202
    clock[0] += 60.0
    assert _post(loop, app, {"action": "resume"}, token_via="header", client=attacker).status == 202
    assert len(read_commands(root)[0]) == 2
    # a GET on a server bound to all addresses needs the token: failures count there too
    app = _app(root, host="0.0.0.0", failures=FailureLimit(3, 10.0, clock=lambda: clock[0]))
    h = [("host", HOST)]
    codes = [call(loop, app, "GET", "/api/state", headers=h, client=attacker).status for _ in range(5)]
    assert codes == [403, 403, 403, 429, 429]
    assert call(loop, app, "GET", "/api/state", query=f"token={TOKEN}", headers=h, client=operator).status == 200


def test_bad_raster_parameters_are_4xx_never_500(loop, run_root):
    app = _app(run_root)
    h = [("host", HOST)]
    for query, code in (("leg=-1", 400), ("leg=abc", 400), ("leg=99999999999999999999", 400), ("leg=7", 404)):
        r = call(loop, app, "GET", "/api/raster/speed.png", query=query, headers=h)
        assert r.status == code and r.body.startswith(b"passt-mav view: "), (query, r.status, r.body)
    assert call(loop, app, "GET", "/api/raster/secret.png", query="leg=0", headers=h).status == 404
    assert call(loop, app, "GET", "/api/raster/speed.png", query="leg=0", headers=h).status == 200
    assert not (run_root / "legs" / "007").exists()  # a GET writes nothing


def test_the_page_sets_no_cookie_and_a_cookie_proves_nothing(loop, run_root):
    """The address's ?token= is answered with the page and no cookie (the page keeps the token in sessionStorage,
    per port); a read carrying the token in a cookie is not told it may command, one with the header or the
    query is."""
    app = _app(run_root)
    r = call(loop, app, "GET", "/", query=f"token={TOKEN}", headers=[("host", HOST)])
    assert r.status == 200 and not r.set_cookies and r.headers["referrer-policy"] == "no-referrer"
    for path in ("/", "/api/state", "/api/openapi.json", "/static/view.js"):
        assert not call(loop, app, "GET", path, query=f"token={TOKEN}", headers=[("host", HOST)]).set_cookies, path

    def may_command(headers, query=""):
        s = call(loop, app, "GET", "/api/state", query=query, headers=[("host", HOST), *headers])
        assert s.status == 200
        return json.loads(s.body)["control"]["token"]

    assert may_command([("cookie", f"{OLD_COOKIE}={TOKEN}")]) is False
    assert may_command([("x-passt-token", TOKEN)]) is True
    assert may_command([], query=f"token={TOKEN}") is True
    # the page reads the token from the address, keeps it in sessionStorage and sends it in the header
    js = (REPO / "passt_mav" / "view" / "static" / "view.js").read_text()
    assert "sessionStorage.setItem" in js and "'X-Passt-Token': token" in js and "document.cookie" not in js


def test_a_non_loopback_bind_needs_the_token_to_read(loop, run_root):
    app = _app(run_root, host="0.0.0.0")
    host = f"192.168.1.20:{PORT}"
    assert call(loop, app, "GET", "/api/state", headers=[("host", host)]).status == 403
    assert (
        call(loop, app, "GET", "/api/state", headers=[("host", host), ("cookie", f"{OLD_COOKIE}={TOKEN}")]).status
        == 403
    )
    assert call(loop, app, "GET", "/api/state", query=f"token={TOKEN}", headers=[("host", host)]).status == 200
    assert call(loop, app, "GET", "/api/state", headers=[("host", host), ("x-passt-token", TOKEN)]).status == 200
    r = call(loop, app, "GET", "/api/stream", headers=[("host", host)])
    assert r.status == 403
    # the page's shell (no run data) loads without it: the page then reads with the token from sessionStorage
    for path in ("/", "/static/view.js", "/static/vendor/leaflet/leaflet.js"):
        assert call(loop, app, "GET", path, headers=[("host", host)]).status == 200, path
    # a DNS name is what a rebinding attack uses: refused even with the token
    r = call(loop, app, "GET", "/api/state", query=f"token={TOKEN}", headers=[("host", f"evil.example:{PORT}")])
    assert r.status == 403


def test_openapi_describes_every_route(loop, run_root):
    app = _app(run_root)
    r = call(loop, app, "GET", "/api/openapi.json", headers=[("host", HOST)])
    spec = json.loads(r.body)
    # every route the app serves, and nothing else (the static mount as its files' path)
    routes = {getattr(x, "path", None) for x in app.app.routes}
    assert spec["openapi"].startswith("3.1") and set(spec["paths"]) == routes - {"/static"} | {"/static/{path}"}
    assert len(routes) == 7


def test_event_streams_are_limited_per_client_and_another_client_is_served(loop, tmp_path):
    """Issue 55: 100 open /api/stream connections (no token needed on loopback) starved the view. One client
    holds at most MAX_STREAMS streams without the token: the 101st is 429 while another client, and the same
    client with the token (the operator's page: counted apart), are served; closed streams free their places."""
    root = make_live_run(tmp_path / "run").root
    app = _app(root, streams=OpenLimit())
    attacker, operator = ("127.0.0.1", 40000), ("127.0.0.2", 40001)
    h = [("host", HOST)]

    async def scenario():
        release = asyncio.Event()
        held = [await hold(app, "/api/stream", headers=h, client=attacker, release=release) for _ in range(100)]
        codes = [s for s, _, _ in held]
        assert codes == [200] * MAX_STREAMS + [429] * (100 - MAX_STREAMS)
        assert all(b.startswith(b"data: {") for s, b, _ in held if s == 200)
        s, body, _ = await hold(app, "/api/stream", headers=h, client=attacker, release=release)
        assert s == 429 and b"too many open event streams" in body and body.count(b"\n") == 0
        s, body, _ = await hold(app, "/api/stream", headers=h, client=operator, release=release)
        assert s == 200 and body.startswith(b"data: {")
        s, body, _ = await hold(app, "/api/stream", query=f"token={TOKEN}", headers=h, client=attacker, release=release)
        assert s == 200 and json.loads(body[6:])["control"]["token"] is True
        release.set()
        await asyncio.wait_for(asyncio.gather(*(t for _, _, t in held)), 30)
        again = asyncio.Event()
        s, _, t = await hold(app, "/api/stream", headers=h, client=attacker, release=again)
        again.set()
        await asyncio.wait_for(t, 30)
        return s

    assert loop.run_until_complete(scenario()) == 200
    assert app.streams.count(attacker[0]) == 0


def test_reads_without_the_token_are_limited_per_client(loop, run_root):
    clock = [100.0]
    app = _app(run_root, reads=FailureLimit(5, 10.0, clock=lambda: clock[0]))
    attacker, operator = ("127.0.0.1", 40000), ("127.0.0.2", 40001)
    h = [("host", HOST)]
    codes = [call(loop, app, "GET", "/api/state", headers=h, client=attacker).status for _ in range(7)]
    assert codes == [200] * 5 + [429] * 2
    r = call(loop, app, "GET", "/api/raster/speed.png", query="leg=0", headers=h, client=attacker)
    assert r.status == 429 and r.headers["retry-after"] == "10" and b"too many reads without the token" in r.body
    assert call(loop, app, "GET", "/api/state", headers=h, client=operator).status == 200
    assert call(loop, app, "GET", "/api/state", headers=[*h, ("x-passt-token", TOKEN)], client=attacker).status == 200
    clock[0] += 10.0
    assert call(loop, app, "GET", "/api/state", headers=h, client=attacker).status == 200


# -- the fuzz -----------------------------------------------------------------------------------------------
def _value(schema: dict):
    """A Hypothesis strategy for a parameter of ``schema``: valid values and junk of every kind."""
    junk = st.one_of(
        st.text(max_size=30),
        st.integers(-(10**30), 10**30).map(str),
        st.sampled_from(["", "-1", "0", "null", "1e9", "../../etc/passwd", "%00", "NaN", "\u00e9", "0x10"]),
    )
    if "enum" in schema:
        return st.one_of(st.sampled_from([str(x) for x in schema["enum"]]), junk)
    if schema.get("type") == "integer":
        return st.one_of(st.integers(-5, 10).map(str), junk)
    return junk


def _json_body():
    """Command bodies: well-formed ones, near misses and junk."""
    good = st.fixed_dictionaries(
        {"action": st.sampled_from(["pause", "resume", "skip", "replan", "end", "approve", "reject"])},
        optional={
            "boat": st.one_of(st.integers(-2, 3), st.just("all")),
            "end_mode": st.sampled_from(["HOLD", "RTL"]),
            "leg": st.integers(-1, 3),
        },
    ).map(lambda d: json.dumps(d).encode())
    anyjson = st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=10),
        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=3),
        max_leaves=8,
    ).map(lambda x: json.dumps(x).encode())
    return st.one_of(good, good, anyjson, st.binary(max_size=64))


HOSTS = {"own": HOST, "localhost": f"localhost:{PORT}", "foreign": f"evil.example:{PORT}", "port": "127.0.0.1:1"}
ORIGINS = {"none": None, "own": ORIGIN, "foreign": "http://evil.example", "null": "null", "https": f"https://{HOST}"}
TOKENS = ("none", "cookie", "header", "query", "wrong")


def _request(op_path: str, method: str, op: dict):
    """A strategy of (path, query, headers, body, host kind, origin kind, token kind) for one operation."""
    params = op.get("parameters") or []

    @st.composite
    def draw(d):
        path = op_path
        query = []
        for p in params:
            if p["in"] == "path":
                v = d(_value(p["schema"]))
                from urllib.parse import quote

                path = path.replace("{" + p["name"] + "}", quote(v, safe=""))
            elif p["in"] == "query" and d(st.booleans()):
                query.append((p["name"], d(_value(p["schema"]))))
        if d(st.integers(0, 2)) == 0:  # a third as the page would send them (else few commands get through)
            hk, ok, tk = "own", "own", d(st.sampled_from(("cookie", "header")))
        else:
            hk, ok, tk = (
                d(st.sampled_from(sorted(HOSTS))),
                d(st.sampled_from(sorted(ORIGINS))),
                d(st.sampled_from(TOKENS)),
            )
        headers = _headers(HOSTS[hk], ORIGINS[ok], tk)
        if tk == "query":
            query.append(("token", TOKEN))
        body = b""
        if method == "post":
            body = d(_json_body())
            headers.append(("content-type", d(st.sampled_from(["application/json", "application/json", "text/plain"]))))
        from urllib.parse import urlencode

        return path, urlencode(query), headers, body, hk, ok, tk

    return draw()


def _fuzz_operation(loop, app, op_path: str, method: str, op: dict, n: int) -> None:
    """``n`` Hypothesis examples of one operation, counted in :data:`FUZZ` (the checks: the fuzz test's docstring)."""

    @settings(
        max_examples=n,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(req=_request(op_path, method, op))
    def one(req):
        path, query, headers, body, hk, ok, tk = req
        r = call(loop, app, method.upper(), path, query=query, headers=headers, body=body)
        FUZZ["requests"] += 1
        FUZZ["operations"].add(f"{method.upper()} {op_path}")
        FUZZ["codes"][r.status] = FUZZ["codes"].get(r.status, 0) + 1
        if r.status >= 500:
            FUZZ["5xx"] += 1
        assert r.status < 500, (path, query, headers, body, r.status, r.body[:200])
        own_host = hk in ("own", "localhost")
        if method == "post" and r.status < 300:
            allowed = own_host and ok in ("own", "none") and tk == "header"  # a cookie never commands
            if not allowed:
                FUZZ["accepted_bad"] += 1
            assert allowed, (headers, r.status)
        if not own_host or ok in ("foreign", "null", "https"):
            assert r.status == 403, (headers, r.status)

    one()


FUZZ = {"requests": 0, "operations": set(), "5xx": 0, "accepted_bad": 0, "codes": {}}


def test_fuzz_every_operation_no_5xx_no_command_without_token_origin_host(loop, tmp_path):
    """Hypothesis over every operation of /api/openapi.json: never a 5xx; a command accepted (202) only with
    the token in the header (never by cookie), the own Host and no foreign Origin; a GET with a foreign Host or
    Origin never answered 200."""
    root = make_live_run(tmp_path / "run").root
    app = _app(root)
    spec = json.loads(call(loop, app, "GET", "/api/openapi.json", headers=[("host", HOST)]).body)
    n = int(os.environ.get("PASST_FUZZ_EXAMPLES", "40"))
    ops = [(p, m, op) for p, item in spec["paths"].items() for m, op in item.items()]
    assert len(ops) == 7

    for op_path, method, op in ops:
        _fuzz_operation(loop, app, op_path, method, op, 3 * n if method == "post" else n)
    print(
        f"fuzz: {FUZZ['requests']} requests over {len(FUZZ['operations'])} operations, "
        f"{FUZZ['5xx']} 5xx, {FUZZ['accepted_bad']} commands accepted that should not be; codes {sorted(FUZZ['codes'].items())}"
    )
    assert len(FUZZ["operations"]) == 7 and FUZZ["5xx"] == 0 and FUZZ["accepted_bad"] == 0
    # the commands that were accepted went to the channel, one line each
    accepted = FUZZ["codes"].get(202, 0)
    assert accepted > 0 and len(read_commands(root)[0]) == accepted


# -- the real server and the command line -------------------------------------------------------------------
def test_real_server_refuses_a_rebinding_host(tmp_path):
    import http.client

    from passt_mav.view import start_view

    rd = make_live_run(tmp_path / "run")
    vp = start_view(rd.root, log_file=tmp_path / "view.log")
    try:
        assert f"?token={vp.token}" in vp.url
        # the token in the cookie the view once set, replayed by whoever received it on another port: refused
        c = http.client.HTTPConnection("127.0.0.1", vp.port, timeout=30)
        h = {"Content-Type": "application/json", "Origin": f"http://127.0.0.1:{vp.port}"}
        c.request("POST", "/api/command", body="{}", headers={**h, "Cookie": f"passt_view_{vp.port}={vp.token}"})
        r = c.getresponse()
        assert r.status == 403, r.read()
        r.read()
        c.close()
        c = http.client.HTTPConnection("127.0.0.1", vp.port, timeout=30)
        c.request("GET", "/api/state", headers={"Host": "evil.example"})
        r = c.getresponse()
        assert r.status == 403 and b"DNS rebinding" in r.read()
        c.close()
        assert _get(vp.url.split("?")[0] + "api/raster/speed.png?leg=-1")[0] == 400
        c = http.client.HTTPConnection("127.0.0.1", vp.port, timeout=30)
        body = json.dumps({"action": "pause"})
        c.request(
            "POST",
            "/api/command",
            body=body,
            headers={"Content-Type": "application/json", "X-Passt-Token": vp.token},
        )
        r = c.getresponse()
        assert r.status == 202, r.read()
    finally:
        vp.stop()


def _run_cli(args, tmp_path, timeout=120):
    return subprocess.run(
        [sys.executable, "-m", "passt_mav.cli", *args], capture_output=True, text=True, timeout=timeout, cwd=tmp_path
    )


def test_a_busy_view_port_stops_run_before_it_connects(tmp_path):
    import socket

    from passt_mav.cli import build_parser

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        # nothing listens on the vehicle's port: had run gone on, it would try to connect (and wait)
        p = _run_cli(
            [
                "run",
                str(REPO / "missions" / "cylinder.yaml"),
                "--connect",
                "tcp:127.0.0.1:9",
                "--view",
                str(port),
                "--out",
                "r1",
            ],
            tmp_path,
        )
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and f"127.0.0.1:{port}" in p.stderr, p.stderr
    assert f"--view {port},optional" in p.stderr and "connecting" not in p.stdout
    assert not (tmp_path / "r1").exists()
    a = build_parser().parse_args(["run", "m.yaml", "--view", "optional"])
    assert (a.view, a.view_optional) == (0, True)
    a = build_parser().parse_args(["run", "m.yaml", "--view", f"{port},optional"])
    assert (a.view, a.view_optional) == (port, True)
    a = build_parser().parse_args(["run", "m.yaml", "--view", "8765"])
    assert (a.view, a.view_optional) == (8765, False)


def test_a_hundred_open_streams_do_not_starve_the_real_server(tmp_path):
    """Issue 55: 100 open /api/stream connections from one local process (no token needed on loopback) once made
    the health probe (GET /api/state) take 12.9 s (median). Now at most MAX_STREAMS of them are served, all from one
    poll of the run directory, and the probe answers at once."""
    import http.client
    import socket
    import statistics
    import time

    from passt_mav.view import start_view

    rd = make_live_run(tmp_path / "run")
    vp = start_view(rd.root, log_file=tmp_path / "view.log")
    socks = []
    try:
        for _ in range(100):
            s = socket.create_connection(("127.0.0.1", vp.port), timeout=30)
            s.sendall(f"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1:{vp.port}\r\n\r\n".encode())
            socks.append(s)
        heads = []
        for s in socks:
            heads.append(s.recv(64).split(b"\r\n", 1)[0])
        assert heads.count(b"HTTP/1.1 200 OK") == MAX_STREAMS, set(heads)
        assert heads.count(b"HTTP/1.1 429 Too Many Requests") == 100 - MAX_STREAMS
        times = []
        for _ in range(5):
            t0 = time.monotonic()
            c = http.client.HTTPConnection("127.0.0.1", vp.port, timeout=30)
            c.request("GET", "/api/state", headers={"Host": f"127.0.0.1:{vp.port}", "X-Passt-Token": vp.token})
            r = c.getresponse()
            assert r.status == 200 and json.loads(r.read())["control"]["token"] is True
            c.close()
            times.append(time.monotonic() - t0)
        print(f"health probe with 100 streams open: median {statistics.median(times) * 1000:.0f} ms")
        assert statistics.median(times) < 2.0, times
    finally:
        for s in socks:
            s.close()
        vp.stop()
