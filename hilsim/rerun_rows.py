"""Decoded hilsim messages as Rerun rows: what the recorder writes for each kind of message.

:class:`RowWriter` turns one message into rows buffered per entity (timeline ``sim_time``, the
message's sim-time stamp) and sends them with ``send_columns`` when :meth:`RowWriter.flush` is
called. Entity layout (entities of robots other than the scenario's go under ``robots/<robot>/``):

==============================================  =============================================
``joints/<joint>/<q>/<source>``                 Scalars; q = position | velocity | effort;
                                                source = truth (``truth/joint_states``),
                                                measured (``joint_states``), command
                                                (``joint_commands``), reference
                                                (``controller/reference``), planned
                                                (``joint_trajectory`` points at their sim time)
``imu/<truth|measured>/<field>/<axis>``         Scalars; field = orientation, angular_velocity,
                                                linear_acceleration
``clock``                                       Scalars: sim time [s]
``sync/<service>``                              Scalars: the acknowledged step [s]
``health/<service>/level`` and ``/<value>``     Scalars (numeric values of the status)
``health/<service>/status``                     TextLog: state and all values
``log/<service>``                               TextLog (rcl_interfaces/Log)
``planner/feedback``, ``planner/result``        TextLog, plus ``…/progress`` and
                                                ``planner/result/planning_time`` Scalars
``<trajectory topic>``                          TextLog summary (``joint_trajectory``,
                                                ``planner/path``)
``<trajectory topic>/joint_space``              LineStrips2D: one strip per joint, x = time
                                                from start [s] (or waypoint index for paths)
``<trajectory topic>/tool_path``                LineStrips3D of the tool (forward kinematics of
                                                the URDF), in the URDF root frame
``robot/<robot name>/…``, ``tf_static``         the URDF model (``world.urdf``), static
``robot/joint_transforms/<joint>``              Transform3D of each moving joint from
                                                ``truth/joint_states``, every 10 ms of sim time
``<topic>/<field path>``                        Scalars of any other message type (numeric fields)
``rejected/<key>``, ``errors/<key>``            TextLog of payloads that failed to decode / to
                                                be turned into rows
==============================================  =============================================

Importing this module imports rerun, after turning its analytics off.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from hilsim import msgs
from hilsim.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

from hilsim.kinematics import RobotModel  # noqa: E402

MODEL_PERIOD_NS = 10_000_000  # 3D robot pose updates: every 10 ms of sim time
TIMELINE = "sim_time"
TRAJECTORY_TOPICS = ("joint_trajectory", "planner/path")

JOINT_SOURCES = {
    "truth/joint_states": "truth",
    "joint_states": "measured",
    "joint_commands": "command",
    "controller/reference": "reference",
}
IMU_SOURCES = {"truth/imu": "truth", "imu": "measured"}
LOG_LEVELS = ((50, "CRITICAL"), (40, "ERROR"), (30, "WARN"), (20, "INFO"), (10, "DEBUG"))
DIAG_LEVELS = {0: "INFO", 1: "WARN", 2: "ERROR", 3: "WARN"}

Fault = Callable[..., None]  # fault(text, exc=exception): an error the recorder survives


def part(s: str) -> str:
    """One entity path segment, whatever characters ``s`` has (``/``, ``:``, spaces)."""
    return str(rr.escape_entity_path_part(s))


def log_level(level: int) -> str:
    for threshold, name in LOG_LEVELS:
        if level >= threshold:
            return name
    return "TRACE"


class RowWriter:
    """Rows of one recording, buffered per entity until :meth:`flush`.

    ``robot`` is the scenario's robot (its entities have no ``robots/<robot>/`` prefix);
    ``model`` the robot model, or None; ``fault(text, exc=…)`` reports an error that only
    loses part of a message's rows (a joint transform, one entity's batch).
    """

    def __init__(self, rec: rr.RecordingStream, robot: str, model: RobotModel | None, fault: Fault) -> None:
        self.rec = rec
        self.robot = robot
        self.model = model
        self._fault = fault
        self.clock_ns = 0  # the latest sim time seen on <prefix>/clock
        self.buffered = 0  # rows waiting for flush()
        self._scalars: dict[str, tuple[list[int], list[float]]] = {}
        # Several scalar entities filled from one message (a JointState's joints, an Imu's axes):
        # one row of values per message here, split into entities at flush time.
        self._vectors: dict[tuple[str, ...], tuple[list[int], list[list[float]]]] = {}
        self._entity_cache: dict[tuple[Any, ...], tuple[str, ...]] = {}
        self._texts: dict[str, tuple[list[int], list[str], list[str]]] = {}
        self._model_rows: dict[str, tuple[list[int], list[float]]] = {}
        self._last_model_ns: int | None = None

    # ------------------------------------------------------------------ static content
    def log_model(self) -> None:
        """The robot model (static) and the frame tool paths are drawn in. If rerun cannot log
        the model, the model's joint transforms are not recorded and its error is raised."""
        m = self.model
        if m is None:
            return
        try:
            m.log_static(self.rec)
        except Exception:
            m.joints = {}
            raise
        for topic in TRAJECTORY_TOPICS:
            self.rec.log(f"{topic}/tool_path", rr.CoordinateFrame(m.root), static=True)

    # ------------------------------------------------------------------ messages -> rows
    def message(self, key: str, msg: Any) -> None:
        """Rows of one decoded message on ``key`` (``<prefix>/clock`` or ``<prefix>/<robot>/<topic>``)."""
        parts = key.split("/")
        if len(parts) == 2:  # <prefix>/clock
            t = msgs.ns_of(msg.clock)
            self.clock_ns = max(self.clock_ns, t)
            self._scalar("clock", t, t * 1e-9)
            return
        robot, topic = parts[1], "/".join(parts[2:])
        root = "" if robot == self.robot else f"robots/{part(robot)}/"
        if topic in JOINT_SOURCES:
            self._joint_state(root, JOINT_SOURCES[topic], msg, model=(topic == "truth/joint_states" and not root))
        elif topic in IMU_SOURCES:
            self._imu(root, IMU_SOURCES[topic], msg)
        elif topic in TRAJECTORY_TOPICS:
            self._trajectory(root, topic, msg)
        elif topic == "planner/feedback":
            t = msgs.ns_of(msg.header.stamp)
            self._text(f"{root}planner/feedback", t, f"{msg.goal_id}: {msg.state} {msg.progress:.0%}")
            self._scalar(f"{root}planner/feedback/progress", t, msg.progress)
        elif topic == "planner/result":
            self._result(root, msg)
        elif parts[2] == "health" and len(parts) == 4:
            self._health(root, msg)
        elif parts[2] == "log" and len(parts) == 4:
            text = f"[{msg.name}] {msg.msg}" if msg.name else msg.msg
            self._text(f"{root}log/{part(parts[3])}", msgs.ns_of(msg.stamp), text, log_level(msg.level))
        elif parts[2] == "sync" and len(parts) == 4:
            t = msgs.ns_of(msg.clock)
            self._scalar(f"{root}sync/{part(parts[3])}", t, t * 1e-9)
        else:
            self._generic(root, topic, msg)

    def rejected(self, key: str, size: int, reason: Any) -> None:
        """A payload that did not decode: a text row under ``rejected/<key>``."""
        self._text(f"rejected/{part(key)}", self.clock_ns, f"{size} bytes: {reason}", "WARN")

    def error(self, key: str, e: BaseException, msg: Any) -> None:
        """A message :meth:`message` failed on: a text row under ``errors/<key>``."""
        self._text(f"errors/{part(key)}", self.clock_ns, f"{type(e).__name__}: {e}: {msg!r}"[:4000], "ERROR")

    def _stamp(self, msg: Any) -> int:
        h = getattr(msg, "header", None)
        if isinstance(h, msgs.Header):
            return msgs.ns_of(h.stamp)
        s = getattr(msg, "stamp", None)
        return msgs.ns_of(s) if isinstance(s, msgs.Time) else self.clock_ns

    def _joint_state(self, root: str, source: str, msg: msgs.JointState, *, model: bool) -> None:
        t = msgs.ns_of(msg.header.stamp)
        names = tuple(msg.name)
        for quantity in ("position", "velocity", "effort"):
            values = getattr(msg, quantity)
            if not values:
                continue
            ck = (root, source, quantity, names)
            entities = self._entity_cache.get(ck)
            if entities is None:
                entities = tuple(f"{root}joints/{part(n)}/{quantity}/{source}" for n in names)
                self._entity_cache[ck] = entities
            self._vector(entities, t, values)
        joints = self.model.joints if self.model is not None else {}
        if model and joints and msg.position:
            last = self._last_model_ns
            if last is None or t - last >= MODEL_PERIOD_NS or t < last:
                self._last_model_ns = t
                for name, v in zip(msg.name, msg.position, strict=False):
                    if name in joints:
                        col = self._model_rows.setdefault(name, ([], []))
                        col[0].append(t)
                        col[1].append(v)
                        self.buffered += 1

    def _imu(self, root: str, source: str, msg: msgs.Imu) -> None:
        ck = (root, source, "imu")
        entities = self._entity_cache.get(ck)
        if entities is None:
            base = f"{root}imu/{source}"
            entities = tuple(f"{base}/orientation/{a}" for a in "xyzw") + tuple(
                f"{base}/{f}/{a}" for f in ("angular_velocity", "linear_acceleration") for a in "xyz"
            )
            self._entity_cache[ck] = entities
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        values = [o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z]
        self._vector(entities, msgs.ns_of(msg.header.stamp), values)

    def _trajectory(self, root: str, topic: str, msg: msgs.JointTrajectory) -> None:
        t0 = msgs.ns_of(msg.header.stamp)
        ent = f"{root}{topic}"
        pts = msg.points
        if not pts:
            self._text(ent, t0, "empty trajectory: stop and hold")
            return
        tfs = np.array([msgs.ns_of(p.time_from_start) for p in pts], dtype=np.int64)
        q = np.array([p.positions for p in pts], dtype=float).reshape(len(pts), len(msg.joint_names))
        self._text(
            ent,
            t0,
            f"{len(pts)} points over {tfs[-1] * 1e-9:.3f} s for {', '.join(msg.joint_names)}; "
            f"start {q[0].round(4).tolist()} end {q[-1].round(4).tolist()}",
        )
        # Path waypoints have no meaningful timing: plot them against their index.
        x = tfs * 1e-9 if topic == "joint_trajectory" else np.arange(len(pts), dtype=float)
        if topic == "joint_trajectory":
            for i, name in enumerate(msg.joint_names):
                for tf, v in zip(tfs.tolist(), q[:, i].tolist(), strict=True):
                    self._scalar(f"{root}joints/{part(name)}/position/planned", t0 + tf, v)
        self.rec.set_time(TIMELINE, duration=np.timedelta64(t0, "ns"))
        strips = [np.column_stack([x, q[:, i]]) for i in range(q.shape[1])]
        self.rec.log(f"{ent}/joint_space", rr.LineStrips2D(strips, labels=list(msg.joint_names)))
        if self.model is not None and not root:
            tool = self.model.kin.positions(list(msg.joint_names), q)
            self.rec.log(f"{ent}/tool_path", rr.LineStrips3D([tool]))

    def _result(self, root: str, msg: msgs.MoveResult) -> None:
        t = msgs.ns_of(msg.header.stamp)
        err = max((abs(e) for e in msg.execution_error), default=0.0)
        text = (
            f"{msg.goal_id}: {'success' if msg.success else 'failure'} (code {msg.error_code}) {msg.message}; "
            f"planner {msg.planner}, planning {msg.planning_time:.3f} s, "
            f"{len(msg.trajectory.points)} points, max execution error {err:.4f}"
        )
        self._text(f"{root}planner/result", t, text, "INFO" if msg.success else "WARN")
        self._scalar(f"{root}planner/result/planning_time", t, msg.planning_time)

    def _health(self, root: str, msg: msgs.DiagnosticArray) -> None:
        t = msgs.ns_of(msg.header.stamp)
        for st in msg.status:
            base = f"{root}health/{part(st.name or 'unnamed')}"
            self._scalar(f"{base}/level", t, float(st.level))
            for kv in st.values:
                try:
                    v = float(kv.value)
                except ValueError:
                    continue
                if math.isfinite(v):
                    self._scalar(f"{base}/{part(kv.key)}", t, v)
            values = ", ".join(f"{kv.key}={kv.value}" for kv in st.values)
            self._text(f"{base}/status", t, f"{st.message}: {values}", DIAG_LEVELS.get(st.level, "WARN"))

    def _generic(self, root: str, topic: str, msg: Any) -> None:
        t = self._stamp(msg)
        flat: list[tuple[str, float]] = []
        _flatten(msg, "", flat)
        for path, v in flat:
            self._scalar(f"{root}{topic}{path}", t, v)
        if not flat:
            self._text(f"{root}{topic}", t, repr(msg)[:4000])

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

    def flush(self) -> bool:
        """Send every buffered row; False if a batch could not be sent (reported as a fault)."""
        rec = self.rec
        sends: list[tuple[str, list[rr.TimeColumn], Any]] = []
        for entity, (ts, vs) in self._scalars.items():
            if ts:
                sends.append((entity, self._index(ts), rr.Scalars.columns(scalars=np.asarray(vs, dtype=float))))
                ts.clear()
                vs.clear()
        for entities, (ts, rows) in self._vectors.items():
            if ts:
                index = self._index(ts)
                values = np.asarray(rows, dtype=float)
                sends += [(e, index, rr.Scalars.columns(scalars=values[:, i])) for i, e in enumerate(entities)]
                ts.clear()
                rows.clear()
        for entity, (ts, texts, levels) in self._texts.items():
            if ts:
                sends.append((entity, self._index(ts), rr.TextLog.columns(text=texts, level=levels)))
                ts.clear()
                texts.clear()
                levels.clear()
        ok = True
        for name, (ts, vs) in self._model_rows.items():
            if ts:
                try:
                    assert self.model is not None
                    cols = self.model.transform_columns(name, vs)
                    sends.append((f"robot/joint_transforms/{part(name)}", self._index(ts), cols))
                except Exception as e:  # the plots of this joint are recorded; only its 3D pose is lost
                    self._fault(f"cannot compute the transform of {name}: {type(e).__name__}: {e}", exc=e)
                ts.clear()
                vs.clear()
        for entity, index, columns in sends:
            try:
                rec.send_columns(entity, indexes=index, columns=columns)
            except Exception as e:  # count the loss (recorded < received) but keep recording
                ok = False
                self._fault(f"cannot record {entity}: {type(e).__name__}: {e}", exc=e)
        self.buffered = 0
        return ok


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
