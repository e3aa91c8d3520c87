"""The view server's OpenAPI 3.1 description (served at ``/api/openapi.json``).

Written as data beside the routes (:mod:`passt_mav.view.server`) rather than generated from docstrings:
the property-based test (tests/test_view_security.py) drives every operation from it, so it is the
contract the server is held to (no 5xx for any parameter; no command without the token, from a foreign
Origin or with a foreign Host).
"""

from __future__ import annotations

from passt_mav.runs.commands import ACTIONS, END_MODES
from passt_mav.view.gate import MAX_STREAMS

__all__ = ["openapi", "RASTERS"]

#: the rasters ``/api/raster/{what}.png`` serves (:meth:`passt_mav.view.state.RunState.raster`)
RASTERS = ("speed", "std", "reward", "land")

_REFUSED = {
    "403": {"description": "foreign Host or Origin, or the token is missing (one line of text)"},
    "429": {"description": "too many requests from this client (Retry-After; one line of text)"},
}


def _text(desc: str) -> dict:
    return {"description": desc, "content": {"text/plain": {"schema": {"type": "string"}}}}


def openapi(version: str) -> dict:
    """The description of this server (``version``: the package's)."""
    command = {
        "type": "object",
        "additionalProperties": False,
        "required": ["action"],
        "properties": {
            "boat": {
                "oneOf": [{"type": "integer", "minimum": 0}, {"const": "all"}],
                "default": 0,
                "description": "the boat (0-based) or 'all' (a fleet)",
            },
            "action": {"enum": list(ACTIONS)},
            "end_mode": {"enum": list(END_MODES), "description": "for action 'end' only (default HOLD)"},
            "leg": {
                "type": "integer",
                "minimum": 0,
                "description": "for 'approve'/'reject' only: the leg meant (unset: the one awaiting approval)",
            },
        },
    }
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "passt-mav live view",
            "version": version,
            "description": "The operator's console of one run (docs/console.md). Reading is open on loopback "
            "(elsewhere it needs the token, in the header or the query); commands need the run's token in the "
            "X-Passt-Token header. A cookie is never a credential.",
        },
        "components": {
            "securitySchemes": {
                "header": {"type": "apiKey", "in": "header", "name": "X-Passt-Token"},
                "query": {"type": "apiKey", "in": "query", "name": "token"},
            },
            "schemas": {"Command": command},
        },
        "paths": {
            "/": {
                "get": {
                    "summary": "the page (it keeps the address's ?token= in sessionStorage; no cookie)",
                    "parameters": [{"name": "token", "in": "query", "schema": {"type": "string"}}],
                    "responses": {"200": {"description": "index.html"}, **_REFUSED},
                }
            },
            "/api/state": {
                "get": {
                    "summary": "one snapshot of the run (JSON)",
                    "responses": {"200": {"description": "the snapshot"}, **_REFUSED},
                }
            },
            "/api/stream": {
                "get": {
                    "summary": "server-sent events: a snapshot whenever a file of the run changes (at most "
                    f"{MAX_STREAMS} open at a time per client without the token, {MAX_STREAMS} with it)",
                    "responses": {"200": {"description": "text/event-stream"}, **_REFUSED},
                }
            },
            "/api/raster/{what}.png": {
                "get": {
                    "summary": "a raster of the run (PNG, north up)",
                    "parameters": [
                        {"name": "what", "in": "path", "required": True, "schema": {"enum": list(RASTERS)}},
                        {"name": "leg", "in": "query", "schema": {"type": "integer", "minimum": 0}},
                    ],
                    "responses": {
                        "200": {"description": "image/png"},
                        "400": _text("a bad parameter (named)"),
                        "404": _text("nothing to draw (yet)"),
                        **_REFUSED,
                    },
                }
            },
            "/api/command": {
                "post": {
                    "summary": "ask the controller to act on a boat (picked up between its steps; the result "
                    "comes as an event of kind 'command' with this command's id)",
                    "security": [{"header": []}],
                    "requestBody": {
                        "required": True,
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Command"}}},
                    },
                    "responses": {
                        "202": {"description": "queued: {id, utc, boat, action, end_mode?, source}"},
                        "400": _text("a bad command (named)"),
                        "409": _text("the run has finished"),
                        "413": _text("body too large"),
                        "415": _text("not application/json"),
                        "429": _text("too many commands (Retry-After)"),
                        **_REFUSED,
                    },
                }
            },
            "/api/openapi.json": {
                "get": {"summary": "this description", "responses": {"200": {"description": "JSON"}, **_REFUSED}}
            },
            "/static/{path}": {
                "get": {
                    "summary": "the page's files (Leaflet vendored)",
                    "parameters": [{"name": "path", "in": "path", "required": True, "schema": {"type": "string"}}],
                    "responses": {"200": {"description": "a file"}, "404": {"description": "no such file"}},
                }
            },
        },
    }
