"""Rows of any other message type: its numeric fields as Scalars (short numeric arrays by index),
or its text when it has none.

Entity paths: ``<topic>/<field path>``: Scalars; ``<topic>``: TextLog (a message without numbers).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from hilsim.core import msgs
from hilsim.record.rows.common import RowsBase


class GenericRows(RowsBase):
    """The generic rows' methods of :class:`~hilsim.record.rows.writer.RowWriter`."""

    def _stamp(self, msg: Any) -> int:
        h = getattr(msg, "header", None)
        if isinstance(h, msgs.Header):
            return msgs.ns_of(h.stamp)
        s = getattr(msg, "stamp", None)
        return msgs.ns_of(s) if isinstance(s, msgs.Time) else self.clock_ns

    def _generic(self, root: str, topic: str, msg: Any) -> None:
        t = self._stamp(msg)
        flat: list[tuple[str, float]] = []
        _flatten(msg, "", flat)
        for path, v in flat:
            self._scalar(f"{root}{topic}{path}", t, v)
        if not flat:
            self._text(f"{root}{topic}", t, repr(msg)[:4000])


def _flatten(obj: Any, path: str, out: list[tuple[str, float]]) -> None:
    """Numeric leaves of a message as (entity suffix, value); short numeric arrays by index."""
    if isinstance(obj, bool | int | float):
        out.append((path, float(obj)))
    elif isinstance(obj, list):
        if 0 < len(obj) <= 9 and all(isinstance(v, int | float) for v in obj):
            out.extend((f"{path}/{i}", float(v)) for i, v in enumerate(obj))
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, msgs.Header | msgs.Time):
        for f in dataclasses.fields(obj):
            _flatten(getattr(obj, f.name), f"{path}/{f.name}", out)
