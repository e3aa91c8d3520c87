"""The operator's command channel: the live page's requests to the controller, through the run directory.

The view server (:mod:`passt_mav.view.server`) checks a request (token, Host, Origin, rate; see
docs/console.md) and appends it here; the controller picks it up between its own steps
(:class:`CommandReader`) and answers through ``events.jsonl`` (kind ``command``, the command's ``id``
in the event's ``command_id``). The view never imports the vehicle side, the controller never serves
HTTP: this file is the one channel between them::

    ROOT/live/commands.jsonl   append-only, one JSON object a line: id, utc (ISO-8601, the server's clock),
                               boat (int, or "all" for a fleet), action (ACTIONS), end_mode (END_MODES,
                               for "end"), leg (for "approve"/"reject": the leg meant; unset: the one
                               awaiting approval), source (who asked: "view <client address>", "console")

Appended under an exclusive ``flock`` and flushed per line, so a reader never sees half a line it keeps
(a half-written last line waits for its newline, as :func:`~passt_mav.runs.live.read_events` does).
"""

from __future__ import annotations

import collections
import datetime as _dt
import json
import logging
import secrets
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "ACTIONS",
    "END_MODES",
    "COMMANDS",
    "CommandError",
    "append_command",
    "CommandReader",
    "read_commands",
    "console_keys",
    "start_console_keys",
]

log = logging.getLogger(__name__)

COMMANDS = "live/commands.jsonl"
#: what the page can ask of a boat (docs/console.md): HOLD keeping the loop's state, AUTO at the same
#: item, end the leg and plan the next, re-plan this leg from here, end the mission (HOLD or RTL); approve
#: or reject the leg awaiting approval (approve mode)
ACTIONS = ("pause", "resume", "skip", "replan", "end", "approve", "reject")
END_MODES = ("HOLD", "RTL")


class CommandError(ValueError):
    """A command that is not well formed (the message names the field)."""


def validate(body, n_boats: int) -> dict:
    """The command in the JSON ``body`` (a dict: ``boat``, ``action``, ``end_mode``) checked against a run of
    ``n_boats`` boats; returns the normalised command (``end_mode`` only for ``end``, default HOLD).
    Raises :class:`CommandError` naming what is wrong."""
    if not isinstance(body, dict):
        raise CommandError("the body must be a JSON object with 'boat' and 'action'")
    extra = set(body) - {"boat", "action", "end_mode", "leg"}
    if extra:
        raise CommandError(f"unknown field(s) {sorted(extra)}; expected boat, action, end_mode, leg")
    action = body.get("action")
    if action not in ACTIONS:
        raise CommandError(f"action must be one of {', '.join(ACTIONS)}; got {action!r}")
    boat = body.get("boat", 0)
    if boat != "all" and (isinstance(boat, bool) or not isinstance(boat, int) or not 0 <= boat < n_boats):
        raise CommandError(f"boat must be 0..{n_boats - 1} or 'all' (the run has {n_boats} boat(s)); got {boat!r}")
    out = {"boat": boat, "action": action}
    mode = body.get("end_mode")
    if action == "end":
        mode = "HOLD" if mode is None else mode
        if mode not in END_MODES:
            raise CommandError(f"end_mode must be one of {', '.join(END_MODES)}; got {mode!r}")
        out["end_mode"] = mode
    elif mode is not None:
        raise CommandError("end_mode is only for action 'end'")
    leg = body.get("leg")
    if leg is not None:
        if action not in ("approve", "reject"):
            raise CommandError("leg is only for actions 'approve' and 'reject'")
        if isinstance(leg, bool) or not isinstance(leg, int) or leg < 0:
            raise CommandError(f"leg must be a leg index >= 0; got {leg!r}")
        out["leg"] = leg
    return out


def append_command(root: str | Path, command: dict, *, source: str) -> dict:
    """Append ``command`` (checked by :func:`validate`) to ``ROOT/live/commands.jsonl`` with a new id, the UTC
    time and ``source``; returns the record written."""
    import fcntl

    rec = {
        "id": secrets.token_hex(6),
        "utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
        **command,
        "source": source,
    }
    path = Path(root) / COMMANDS
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            f.write(json.dumps(rec) + "\n")
            f.flush()
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
    return rec


def read_commands(root: str | Path, offset: int = 0) -> tuple[list[dict], int]:
    """(commands after byte ``offset`` of ``commands.jsonl``, the new offset); a half-written last line waits,
    a line that is not a command is skipped (logged)."""
    from passt_mav.runs.live import read_jsonl

    recs, end = read_jsonl(Path(root) / COMMANDS, offset)
    out = [r for r in recs if isinstance(r, dict) and r.get("action") in ACTIONS]
    if len(out) < len(recs):
        log.warning("commands: skipped %d bad line(s) of %s", len(recs) - len(out), Path(root) / COMMANDS)
    return out, end


class CommandReader:
    """Boat ``boat``'s new commands (its own and those for ``"all"``), read from where the last call stopped.

    ``skip_existing``: start at the file's end (a resumed run does not replay a finished session's commands).
    """

    def __init__(self, root: str | Path, boat: int = 0, *, skip_existing: bool = True):
        self.root, self.boat = Path(root), int(boat)
        self.offset = 0
        self._queue: collections.deque[dict] = collections.deque()  # read, not yet taken (:meth:`take`)
        if skip_existing:
            try:
                self.offset = (self.root / COMMANDS).stat().st_size
            except OSError:
                self.offset = 0

    def poll(self) -> list[dict]:
        """The commands for this boat that arrived since the last call, oldest first (those :meth:`take` left
        queued first)."""
        new, self.offset = read_commands(self.root, self.offset)
        out = [*self._queue, *(c for c in new if c.get("boat") in (self.boat, "all"))]
        self._queue.clear()
        return out

    def take(self) -> Iterator[dict]:
        """This boat's commands, oldest first, one at a time: those that arrived since the last read join the
        queue, and one leaves it only when the caller asks for the next. A caller that stops early (to carry
        out a Pause and wait in it, or to end the leg) leaves the rest queued for the next wait, so every
        command is taken in the order given: a Resume sent right after its Pause resumes that Pause."""
        new, self.offset = read_commands(self.root, self.offset)
        self._queue.extend(c for c in new if c.get("boat") in (self.boat, "all"))
        while self._queue:
            yield self._queue.popleft()


#: console keys (approve mode) -> the command they send
KEYS = {"a": "approve", "approve": "approve", "r": "reject", "reject": "reject"}


def console_keys(root: str | Path, stream) -> int:
    """Read lines from ``stream`` (the console) until it ends: ``a`` / ``r`` (or ``approve`` / ``reject``) + Enter
    append that command for every boat's leg awaiting approval (``boat: "all"``, no leg: the one awaiting), source
    ``console``; other lines are ignored. Returns the number of commands sent."""
    n = 0
    for line in stream:
        action = KEYS.get(line.strip().lower())
        if action is not None:
            append_command(root, {"boat": "all", "action": action}, source="console")
            n += 1
    return n


def start_console_keys(root: str | Path, stream):
    """:func:`console_keys` in a daemon thread (it blocks on the console); returns the thread."""
    import threading

    th = threading.Thread(target=console_keys, args=(root, stream), name="console-keys", daemon=True)
    th.start()
    return th
