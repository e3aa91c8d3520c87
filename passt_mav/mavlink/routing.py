"""Message routing of one MAVLink link: subscriber queues, listener callbacks, the latest message per type.

The link's reader thread hands every message it receives to a :class:`MessageRouter`; any other thread
subscribes (:class:`Subscription`, a queue), adds listeners (callbacks run on the reader thread) or
reads the latest message of a type.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Iterable
from typing import Any, Self, TypeAlias

__all__ = ["MessageRouter", "Subscription", "Message"]

#: a pymavlink message: pymavlink has no type hints, its fields are read by name (``m.time_boot_ms``)
Message: TypeAlias = Any

log = logging.getLogger(__name__)


class Subscription:
    """A queue of the messages of some types, filled by the reader thread.

    Use as a context manager (unsubscribes on exit). ``get(timeout)`` returns the
    next message or None.
    """

    def __init__(self, router: MessageRouter, types: frozenset[str] | None, maxsize: int = 10000, raw: bool = False):
        self._router, self.types = router, types
        self._q: queue.Queue = queue.Queue(maxsize)
        #: a lockstep vehicle's clock does not run while this one waits (the lockstep's own acknowledgement)
        self._raw = raw

    def _offer(self, msg) -> None:
        try:
            self._q.put_nowait(msg)
        except queue.Full:  # a consumer that stopped reading must not stall the reader
            pass

    def get(self, timeout: float | None) -> Message | None:
        """The next message, or None after ``timeout`` s (or at once when the link's transport dies).

        A vehicle in lockstep (the router's ``stepper``, :class:`passt_mav.mavlink.link.Lockstep`): when
        nothing is queued, a step of 0 s (the vehicle's answers to what we sent), then steps of its clock
        until a message comes or ``timeout`` x the pace in vehicle seconds has run."""
        step = None if self._raw else self._router.stepper
        if step is None:
            try:
                return self._q.get(timeout=max(timeout, 0.0) if timeout is not None else None)
            except queue.Empty:
                return None
        budget, h = step.budget(timeout), 0.0  # vehicle seconds it may step; the next step
        while True:
            try:
                return self._q.get_nowait()
            except queue.Empty:
                pass
            if (h > 0 and budget.spent()) or not step.step(h):
                return None
            budget.stepped(h)
            h = step.step_s

    def drain(self) -> list:
        out: list[Message] = []
        while True:
            try:
                m = self._q.get_nowait()
            except queue.Empty:
                return out
            if m is not None:  # a wake-up of a dying link (MessageRouter.wake_subscribers), not a message
                out.append(m)

    def close(self) -> None:
        self._router.unsubscribe(self)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _type_set(types: str | Iterable[str] | None) -> frozenset[str] | None:
    """``types`` as a set of message type names (one name alone counts as one type; None = all types)."""
    if isinstance(types, str):
        types = (types,)
    return frozenset(types) if types is not None else None


class MessageRouter:
    """Hands each received message to the subscriptions and listeners that want its type, and keeps the
    latest message of each type. Subscribing and listening are thread-safe; :meth:`route` runs on the
    reader thread."""

    def __init__(self):
        self._lock = threading.Lock()
        self._subs: list[Subscription] = []
        self._listeners: list[tuple[Callable, frozenset[str] | None]] = []
        self._latest: dict[str, Message] = {}
        #: the vehicle's clock in lockstep (:class:`passt_mav.mavlink.link.Lockstep`), None when it keeps its own
        self.stepper = None

    def subscribe(self, types: str | Iterable[str] | None = None, *, raw: bool = False) -> Subscription:
        """A queue of every message of ``types`` (None = all) routed from now on (``raw``: its waits never
        step a lockstep vehicle's clock)."""
        sub = Subscription(self, _type_set(types), raw=raw)
        with self._lock:
            self._subs.append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Stop filling ``sub`` (a subscription already removed is ignored)."""
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def wake_subscribers(self) -> None:
        """The transport died: every waiting ``Subscription.get`` returns None now (as on a timeout), so a
        protocol exchange in progress fails at once on its next send instead of waiting out its timeout."""
        with self._lock:
            subs = list(self._subs)
        for s in subs:
            s._offer(None)

    def add_listener(self, callback: Callable[[object], None], types: str | Iterable[str] | None = None) -> None:
        """Call ``callback(msg)`` from the reader thread for each message of ``types`` (keep it quick)."""
        types = _type_set(types)
        with self._lock:
            self._listeners.append((callback, types))

    def remove_listener(self, callback: Callable[[object], None]) -> None:
        """Stop calling ``callback`` (every registration of it)."""
        with self._lock:
            self._listeners = [(c, t) for c, t in self._listeners if c is not callback]

    def latest(self, typ: str):
        """The last message of type ``typ`` kept by :meth:`route`, or None."""
        return self._latest.get(typ)

    def forget(self, *types: str) -> None:
        """Drop the last message of each of ``types``."""
        for t in types:
            self._latest.pop(t, None)

    def route(self, msg, typ: str, keep: bool) -> None:
        """Keep ``msg`` (of type ``typ``) as the latest of its type when ``keep``, then queue it for each
        subscription and call each listener of its type. A failing listener is logged, never raised."""
        if keep:
            self._latest[typ] = msg
        with self._lock:
            subs = list(self._subs)
            listeners = list(self._listeners)
        for s in subs:
            if s.types is None or typ in s.types:
                s._offer(msg)
        for cb, types in listeners:
            if types is None or typ in types:
                try:
                    cb(msg)
                except Exception:  # noqa: BLE001 - one faulty listener must not kill the reader
                    log.exception("listener %r failed on %s", cb, typ)
