"""What the row families share: rerun (imported here, after turning its analytics off), ``part``,
the timeline and world frame, the per-step keys' sources, and the row buffers.

:class:`RowsBase` is the base of every family's mixin and of :class:`~hilsim.record.rows.writer.RowWriter`:
the buffers ``_scalar`` (one Scalars entity), ``_vector`` (several Scalars entities filled from one
message) and ``_text`` (a TextLog entity) that the families fill and ``RowWriter.flush`` sends.
No entity paths of its own.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from hilsim.core.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

MODEL_PERIOD_NS = 10_000_000  # 3D robot pose updates (joints, tf, the odometry's chassis): every 10 ms of sim time
TIMELINE = "sim_time"
WORLD_FRAME = "world"
COLOURS = {  # RGB of the 3D and map entities
    "truth": (40, 190, 60),  # green
    "odom": (0, 190, 240),  # cyan: not the rover's own orange
    "gps": (220, 30, 30),  # red
    "scan": (230, 0, 200),  # magenta
    "plan": (255, 210, 0),  # yellow: a rover's planned path, an arm's planned tool path
}

JOINT_SOURCES = {
    "truth/joint_states": "truth",
    "joint_states": "measured",
    "joint_commands": "command",
    "controller/reference": "reference",
}
IMU_SOURCES = {"truth/imu": "truth", "imu": "measured"}

Fault = Callable[..., None]  # fault(text, exc=exception): an error the recorder survives


def streams(rec: Any) -> tuple[Any, ...]:
    """The real recording streams behind ``rec``: a live tee's two (hilsim.record.live_rows), or ``rec`` itself
    (for what needs a real stream: a URDF's meshes logged by rerun's own loader)."""
    return tuple(getattr(rec, "streams", (rec,)))


def part(s: str) -> str:
    """One entity path segment, whatever characters ``s`` has (``/``, ``:``, spaces)."""
    return str(rr.escape_entity_path_part(s))


class RowsBase:
    """The state every family's rows use (set by ``RowWriter.__init__``) and the row buffers."""

    rec: rr.RecordingStream
    robot: str
    clock_ns: int
    buffered: int
    _fault: Fault
    _scalars: dict[str, tuple[list[int], list[float]]]
    _vectors: dict[tuple[str, ...], tuple[list[int], list[list[float]]]]
    _entity_cache: dict[tuple[Any, ...], tuple[str, ...]]
    _texts: dict[str, tuple[list[int], list[str], list[str]]]

    # ------------------------------------------------------------------ buffers
    def _scalar(self, entity: str, t: int, v: float) -> None:
        col = self._scalars.get(entity)
        if col is None:
            col = self._scalars[entity] = ([], [])
        col[0].append(t)
        col[1].append(v)
        self.buffered += 1

    def _vector(self, entities: tuple[str, ...], t: int, values: list[float]) -> None:
        col = self._vectors.get(entities)
        if col is None:
            col = self._vectors[entities] = ([], [])
        col[0].append(t)
        col[1].append(values)
        self.buffered += len(entities)

    def _text(self, entity: str, t: int, text: str, level: str = "INFO") -> None:
        col = self._texts.get(entity)
        if col is None:
            col = self._texts[entity] = ([], [], [])
        col[0].append(t)
        col[1].append(text)
        col[2].append(level)
        self.buffered += 1

    @staticmethod
    def _index(times: list[int]) -> list[rr.TimeColumn]:
        return [rr.TimeColumn(TIMELINE, duration=np.asarray(times, dtype="timedelta64[ns]"))]


def topic_parts(key: str) -> list[str]:
    """A key's chunks as entity paths use them: ``<domain>/<robot>/<topic…>`` (``<domain>/clock``),
    the type and hash chunks of an rmw_zenoh key (hilsim.core.keys) left off."""
    parts = key.split("/")
    return parts[:-2] if len(parts) > 3 and parts[-1].startswith("RIHS") else parts
