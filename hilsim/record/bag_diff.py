"""Where two bags first differ: ``hilsim bag diff A B`` (a bag as a regression test).

Two lockstep runs with the same seed give the same messages (docs/recording.md, "Same seed, same bag"):
this compares them topic by topic, each topic's messages in their order of sim time (the stamp the bag
holds; ties in the order recorded), message by message, decoded (:func:`hilsim.core.msgs.decode` by the
channel's Zenoh key; raw bytes where that fails), field by field. What is wall-clock by nature is left
out: each message's receive time and its writer's id and source time (metadata), the topics
:data:`WALL_TOPICS` (health and logs, published once a wall second) and the fields :data:`WALL_FIELDS` (a
planner's measured planning time). ``--all`` compares those topics and fields too.

Reads only the bags' files.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hilsim.core import msgs
from hilsim.core.keys import UnknownKey, message_type
from hilsim.record.bag_read import BagMessage, open_bag

# topics whose samples come at wall-clock times (health once a second, log lines as they happen)
WALL_TOPICS = ("*/health/*", "*/log/*", "/rosout")
# fields measured on the wall clock
WALL_FIELDS = ("planning_time",)


@dataclass(frozen=True)
class Difference:
    """The first difference on one topic."""

    topic: str
    index: int  # the message's position among the topic's messages (0-based)
    sim_ns: int  # its sim time (of the message in A, else in B)
    field: str  # the field path ("position[2]"), "" for the message as a whole
    a: str  # what A holds there ("(none)": A has fewer messages; "(no such topic)")
    b: str

    def line(self) -> str:
        where = f"{self.topic} message {self.index + 1} at t={self.sim_ns / 1e9:.3f} s"
        what = f"{self.field}: " if self.field else ""
        return f"{where}: {what}{self.a} != {self.b}"


def _ignored(topic: str, patterns: Iterable[str]) -> bool:
    return any(fnmatch.fnmatchcase(topic, p) for p in patterns)  # a glob's * spans slashes too


def _by_topic(path: str | Path, skip: tuple[str, ...]) -> dict[str, list[BagMessage]]:
    out: dict[str, list[BagMessage]] = defaultdict(list)
    for m in open_bag(path).messages():
        if not _ignored(m.topic, skip):
            out[m.topic].append(m)
    for ms in out.values():
        if all(_sim(m) is not None for m in ms):
            ms.sort(key=lambda m: m.pub_ns)  # stable: ties stay in the order recorded
    return out


def _sim(m: BagMessage) -> int | None:
    """A message's sim time; None for a type without a stamp (the bag's publish time is then its receive time)."""
    return None if m.pub_ns == m.log_ns else m.pub_ns


def _show(v: Any) -> str:
    text = repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


def _decoded(m: BagMessage) -> Any:
    try:
        return msgs.decode(message_type(m.key), m.data) if m.key else None
    except (UnknownKey, msgs.BadMessage, ValueError):
        return None


def _first_field(a: Any, b: Any, path: str, skip_fields: tuple[str, ...]) -> tuple[str, Any, Any] | None:
    """The first field where two decoded messages differ, depth first in declaration order."""
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        for f in dataclasses.fields(a):
            if f.name in skip_fields:
                continue
            got = _first_field(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}" if path else f.name,
                               skip_fields)
            if got is not None:
                return got
        return None
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            got = _first_field(x, y, f"{path}[{i}]", skip_fields)
            if got is not None:
                return got
        if len(a) != len(b):
            return f"len({path})", len(a), len(b)
        return None
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return None
    return None if a == b else (path, a, b)


def _compare(topic: str, xs: list[BagMessage], ys: list[BagMessage], skip_fields: tuple[str, ...]) -> Difference | None:
    last = 0  # a message without a stamp is said at the sim time of the topic's latest one before it
    for i, (x, y) in enumerate(zip(xs, ys, strict=False)):
        tx, ty = _sim(x), _sim(y)
        if tx is not None and ty is not None and tx != ty:
            return Difference(topic, i, min(tx, ty), "sim time", f"{tx / 1e9:.6f} s", f"{ty / 1e9:.6f} s")
        last = tx if tx is not None else last
        if x.data == y.data:
            continue
        dx, dy = _decoded(x), _decoded(y)
        if dx is None or dy is None:
            return Difference(topic, i, last, "", f"{len(x.data)} bytes", f"{len(y.data)} bytes (other bytes)")
        got = _first_field(dx, dy, "", skip_fields)
        if got is not None:
            return Difference(topic, i, last, got[0], _show(got[1]), _show(got[2]))
    if len(xs) != len(ys):
        i = min(len(xs), len(ys))
        extra = (xs if len(xs) > len(ys) else ys)[i]  # the first message only one of them has
        at = _sim(extra)
        return Difference(topic, i, last if at is None else at, "count", f"{len(xs)} messages", f"{len(ys)} messages")
    return None


def diff(a: str | Path, b: str | Path, *, everything: bool = False, ignore: Iterable[str] = ()) -> list[Difference]:
    """Each topic's first difference between bags ``a`` and ``b`` (empty: equal), earliest sim time first.
    ``everything``: compare the wall-clock topics and fields too; ``ignore``: more topic globs to leave out.
    Raises :class:`hilsim.record.bag.BagError` if a bag cannot be read."""
    skip = tuple(ignore) + (() if everything else WALL_TOPICS)
    skip_fields = () if everything else WALL_FIELDS
    xa, xb = _by_topic(a, skip), _by_topic(b, skip)
    out = []
    for topic in sorted(set(xa) | set(xb)):
        if topic not in xb or topic not in xa:
            ms = xa.get(topic) or xb[topic]
            has = f"{len(ms)} messages"
            out.append(Difference(topic, 0, _sim(ms[0]) or 0, "topic", has if topic in xa else "(no such topic)",
                                  has if topic in xb else "(no such topic)"))
            continue
        d = _compare(topic, xa[topic], xb[topic], skip_fields)
        if d is not None:
            out.append(d)
    out.sort(key=lambda d: (d.sim_ns, d.topic))
    return out
