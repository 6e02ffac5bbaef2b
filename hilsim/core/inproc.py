"""An in-process stand-in for a Zenoh session: the services' own code, no transport.

Every ``put`` is queued and delivered by :meth:`Bus.drain` in order, in one thread, so a
lockstep pipeline (physics → sensors → controller → physics) runs as a plain loop. Payloads
are still CDR-encoded and decoded by the services, exactly as over Zenoh. Used by
``hilsim bench loop`` as the no-transport limit, and by tests that want a whole pipeline
without processes.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key_expr: str, payload: _Payload, attachment: bytes | None = None) -> None:
        self.key_expr = key_expr
        self.payload = payload
        self.attachment = None if attachment is None else _Payload(attachment)
        self.kind = zenoh.SampleKind.PUT


class _Decl:
    def __init__(self, undeclare: Callable[[], None] = lambda: None) -> None:
        self._undeclare = undeclare

    def undeclare(self) -> None:
        self._undeclare()


def key_matches(expr: str, key: str) -> bool:
    """Zenoh key-expression match for the forms hilsim uses: exact, `*` (one chunk), `**` (any)."""
    e, k = expr.split("/"), key.split("/")
    if "**" in e:
        i = e.index("**")
        return key_matches("/".join(e[:i]), "/".join(k[:i])) if i else True
    return len(e) == len(k) and all(a in ("*", b) for a, b in zip(e, k, strict=True))


class _Publisher(_Decl):
    def __init__(self, bus: Bus, key: str) -> None:
        super().__init__()
        self.bus, self.key = bus, key

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self.bus.queue.append((self.key, bytes(payload), attachment))


class _Liveliness:
    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def declare_token(self, key: str) -> _Decl:
        self.bus.tokens.add(key)
        for expr, cb in list(self.bus.live_subs):
            if key_matches(expr, key):
                cb(_Sample(key, _Payload(b"")))
        return _Decl(lambda: self.bus.tokens.discard(key))

    def declare_subscriber(self, expr: str, cb: Callable[[Any], None], history: bool = False) -> _Decl:
        entry = (expr, cb)
        self.bus.live_subs.append(entry)
        if history:
            for k in sorted(self.bus.tokens):
                if key_matches(expr, k):
                    cb(_Sample(k, _Payload(b"")))
        return _Decl(lambda: self.bus.live_subs.remove(entry))


class Session:
    """What :class:`hilsim.core.service.Service` needs of a Zenoh session."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def declare_publisher(self, key: str, **_: Any) -> _Publisher:
        return _Publisher(self.bus, key)

    def declare_subscriber(self, expr: str, cb: Callable[[Any], None]) -> _Decl:
        entry = (expr, cb)
        self.bus.subs.append(entry)
        return _Decl(lambda: self.bus.subs.remove(entry))

    def declare_queryable(self, expr: str, cb: Callable[[Any], None]) -> _Decl:
        return _Decl()  # request/reply is not needed for the loop

    def liveliness(self) -> _Liveliness:
        return _Liveliness(self.bus)

    def close(self) -> None:
        pass


class Bus:
    """Delivers queued messages to matching subscribers, in publication order."""

    def __init__(self) -> None:
        self.queue: deque[tuple[str, bytes, bytes | None]] = deque()
        self.subs: list[tuple[str, Callable[[Any], None]]] = []
        self.live_subs: list[tuple[str, Callable[[Any], None]]] = []
        self.tokens: set[str] = set()
        self.delivered = 0
        self._routes: dict[str, list[Callable[[Any], None]]] = {}

    def session(self) -> Session:
        return Session(self)

    def drain(self, until: Callable[[], bool] = lambda: False) -> None:
        q, routes = self.queue, self._routes
        while q and not until():
            key, data, att = q.popleft()
            cbs = routes.get(key)
            if cbs is None:
                cbs = routes[key] = [cb for expr, cb in self.subs if key_matches(expr, key)]
            for cb in cbs:
                cb(_Sample(key, _Payload(data), att))
                self.delivered += 1
