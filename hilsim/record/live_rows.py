"""What the live viewer is sent: the recording's rows, each entity's dense ones thinned.

The recording's file keeps every row (1 kHz joint plots, a transform per joint every 10 ms of sim time…),
more than a viewer needs to watch the robot move. So with ``logger.live`` the recorder has two recording streams
with one recording id: its file's, and the live one (:class:`LiveTee`), which gets everything the file gets
except that each entity's dense rows are thinned to at most :data:`LIVE_RATE_HZ` per second of sim time (the
first row of each period; a plot's to :data:`PLOT_RATE_HZ`), and the entities no view of the layout needs live
(:data:`NOT_LIVE`: most health values) are left out. Text logs and line strips (a planned path, a track: each
row a whole strip) are never thinned; static rows (the model, the world, the layout) go to both streams whole.
Until the live stream is *active* (a viewer joined: :mod:`hilsim.record.live`) it gets the static rows only.

No Zenoh keys: it sits between the recorder's row writer (:class:`hilsim.record.rows.RowWriter`) and Rerun.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import pyarrow as pa

LIVE_RATE_HZ = 30.0  # rows per entity per second of sim time the live viewer is sent at most (the 3D view's)
PLOT_RATE_HZ = 10.0  # the same for a plot's (Scalars) entity: a viewer drawing by software ingests ~half the
# full live stream's rate (docs/recording.md); the file keeps every row
# archetypes whose every row counts (a log line; a path or a track drawn as one strip per row)
WHOLE = ("TextLog", "LineStrips3D", "LineStrips2D", "GeoLineStrings")
# entities the live stream never gets (the file does): each service's health values but its level and real-time
# factor (~20 each, ~140 entities for the arm, half of all), and the rows of joint_states_throttle (a thinned copy
# of the joint states the joints' plots show; no view shows it)
NOT_LIVE = re.compile(r"(^|/)(health/[^/]+/(?!(level|real_time_factor)$)[^/]+|joint_states_throttle(/.*)?)$")


@functools.cache  # asked for every entity at every flush: the answer never changes
def live_entity(entity: str) -> bool:
    """Whether the live stream gets rows of ``entity`` (see :data:`NOT_LIVE`)."""
    return NOT_LIVE.search(entity.lstrip("/")) is None


class _Taken:
    """A component or time column with only some of its rows (duck-typed for ``send_columns``)."""

    def __init__(self, col: Any, rows: pa.Array) -> None:
        self.col, self.array = col, col.as_arrow_array().take(rows)

    def component_descriptor(self) -> Any:
        return self.col.component_descriptor()

    def timeline_name(self) -> str:
        return str(self.col.timeline_name())

    def as_arrow_array(self) -> pa.Array:
        return self.array


class LiveTee:
    """The file's recording stream and the live one, used by the row writer as one stream.

    ``log``, ``set_time`` and ``send_recording_name`` go to both (``log`` to the live stream only static rows
    until ``active()``); ``send_columns`` sends the file every row and, once ``active()``, the live stream each
    entity's first row of every ``1/rate_hz`` s of sim time (see the module's docstring); ``streams`` are both,
    for what needs a real stream (a URDF's static meshes: ``hilsim.record.rows.common.streams``). Anything else
    (``flush``…) is the file's stream's."""

    def __init__(self, rec: Any, live: Any, rate_hz: float = LIVE_RATE_HZ, plot_rate_hz: float = PLOT_RATE_HZ,
                 active: Callable[[], bool] = lambda: True) -> None:
        self.rec, self.live, self.active = rec, live, active
        self.streams = (rec, live)
        self.period_ns = int(1e9 / rate_hz)
        self.plot_period_ns = int(1e9 / plot_rate_hz)
        self._last: dict[str, int] = {}  # entity -> the last period it was sent a row in
        self.sent = self.thinned = 0  # rows the live stream got, and rows it was spared

    def __getattr__(self, name: str) -> Any:
        return getattr(self.rec, name)

    def log(self, *args: Any, **kwargs: Any) -> None:
        self.rec.log(*args, **kwargs)
        if (kwargs.get("static") or self.active()) and live_entity(str(args[0])):
            self.live.log(*args, **kwargs)

    def set_time(self, *args: Any, **kwargs: Any) -> None:
        self.rec.set_time(*args, **kwargs)
        self.live.set_time(*args, **kwargs)

    def send_recording_name(self, name: str) -> None:
        self.rec.send_recording_name(name)
        self.live.send_recording_name(name)

    def send_columns(self, entity: str, indexes: Iterable[Any], columns: Iterable[Any]) -> None:
        indexes, columns = list(indexes), list(columns)
        self.rec.send_columns(entity, indexes=indexes, columns=columns)
        if not self.active() or not live_entity(entity):  # nobody watches yet: the live stream costs nothing
            return
        rows = self._rows(entity, indexes, columns)
        if rows is None:
            self.live.send_columns(entity, indexes=indexes, columns=columns)
        elif len(rows):
            self.live.send_columns(entity, indexes=[_Taken(c, rows) for c in indexes],
                                   columns=[_Taken(c, rows) for c in columns])

    def _rows(self, entity: str, indexes: list[Any], columns: list[Any]) -> pa.Array | None:
        """The rows the live stream gets (None: all of them)."""
        times = indexes[0].as_arrow_array() if indexes else None
        n = len(times) if times is not None else 0
        archetypes = [str(getattr(c.component_descriptor(), "archetype", "") or "") for c in columns]
        if n == 0 or any(a.endswith(WHOLE) for a in archetypes):
            self.sent += n
            return None
        plot = bool(archetypes) and all(a.endswith("Scalars") for a in archetypes)
        period = times.cast(pa.int64()).to_numpy(zero_copy_only=False) // (self.plot_period_ns if plot
                                                                            else self.period_ns)
        last = self._last.get(entity, np.iinfo(np.int64).min)
        first = np.ones(n, dtype=bool)
        first[1:] = period[1:] != period[:-1]
        keep = np.flatnonzero(first & (period > last))
        if keep.size:
            self._last[entity] = int(period[keep].max())
        self.sent += int(keep.size)
        self.thinned += n - int(keep.size)
        return None if keep.size == n else pa.array(keep, pa.int64())

