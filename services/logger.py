"""The logger service: records every message of the simulation into a Rerun ``.rrd`` file.

Reads: everything under ``<prefix>/`` (``logger.record`` key expressions, ``**`` by default).
Writes: only its own health and log keys, and files in the run directory
(``logger.run_dir``, or ``<logger.out_dir>/<YYYYmmdd-HHMMSS>``):

- ``recording.rrd``       the Rerun recording, timeline ``sim_time`` (message stamps);
- ``scenario.yaml``       the scenario of the run (written unless already there);
- ``record_summary.json`` ``{key: {received, recorded, rejected}}`` written at exit.

Nothing is lost and nothing blocks the simulation: the Zenoh callback only appends
``(key, payload)`` to an unbounded queue; a worker thread decodes (``hilsim.msgs.decode``),
turns messages into rows buffered per entity and sends them with ``send_columns`` every
0.5 s or every few thousand rows. A payload that does not decode is counted as rejected
and still recorded, as a text row under ``rejected/…``. At exit (SIGINT/SIGTERM) the
subscriber is undeclared, the queue drained, the file flushed, and one line per key
``recorded <key>: received N recorded M`` is printed; received equals recorded.
Rerun analytics are off (``hilsim.recording.disable_analytics``) and nothing is sent over
the network: the recording stream only saves to the file.

Entity layout (entities of robots other than the scenario's go under ``robots/<robot>/``):

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
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from hilsim import msgs
from hilsim.config import Scenario, write_scenario
from hilsim.geometry import rpy_to_matrix
from hilsim.keys import UnknownKey, message_type
from hilsim.recording import RECORDING_NAME, SUMMARY_NAME, disable_analytics
from hilsim.service import Service

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402
from rerun.urdf import UrdfTree  # noqa: E402

FLUSH_PERIOD_S = 0.5  # wall seconds between send_columns batches
FLUSH_ROWS = 20_000  # …or earlier when this many rows are buffered
MODEL_PERIOD_NS = 10_000_000  # 3D robot pose updates: every 10 ms of sim time
TIMELINE = "sim_time"

JOINT_SOURCES = {
    "truth/joint_states": "truth",
    "joint_states": "measured",
    "joint_commands": "command",
    "controller/reference": "reference",
}
IMU_SOURCES = {"truth/imu": "truth", "imu": "measured"}
LOG_LEVELS = ((50, "CRITICAL"), (40, "ERROR"), (30, "WARN"), (20, "INFO"), (10, "DEBUG"))
DIAG_LEVELS = {0: "INFO", 1: "WARN", 2: "ERROR", 3: "WARN"}


def _part(s: str) -> str:
    """One entity path segment, whatever characters ``s`` has (``/``, ``:``, spaces)."""
    return str(rr.escape_entity_path_part(s))


def _log_level(level: int) -> str:
    for threshold, name in LOG_LEVELS:
        if level >= threshold:
            return name
    return "TRACE"


# ---------------------------------------------------------------- kinematics (tool paths)
def _axis_angle(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) about a unit axis by angles q (N,)."""
    x, y, z = axis
    c, s = np.cos(q), np.sin(q)
    t = 1 - c
    return np.stack(
        [
            np.stack([t * x * x + c, t * x * y - s * z, t * x * z + s * y], -1),
            np.stack([t * x * y + s * z, t * y * y + c, t * y * z - s * x], -1),
            np.stack([t * x * z - s * y, t * y * z + s * x, t * z * z + c], -1),
        ],
        -2,
    )


class ToolKinematics:
    """Forward kinematics from the URDF root to the tool link (``tool_link``, else the deepest link)."""

    def __init__(self, tree: UrdfTree) -> None:
        joints = {j.child_link: j for j in tree.joints()}
        self.root = tree.root_link().name

        def depth(link: str) -> int:
            n = 0
            while link in joints:
                link, n = joints[link].parent_link, n + 1
            return n

        tool = "tool_link" if "tool_link" in joints else max(joints, key=depth, default=self.root)
        chain = []
        link = tool
        while link in joints:
            chain.append(joints[link])
            link = joints[link].parent_link
        self.tool = tool
        self.chain = list(reversed(chain))

    def positions(self, joint_names: list[str], q: np.ndarray) -> np.ndarray:
        """Tool positions (N, 3) in the root frame for joint values q (N, len(joint_names))."""
        n = q.shape[0]
        col = {name: i for i, name in enumerate(joint_names)}
        rot = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        pos = np.zeros((n, 3))
        for j in self.chain:
            o_rot = rpy_to_matrix(*j.origin_rpy)
            pos = pos + rot @ np.asarray(j.origin_xyz)
            rot = rot @ o_rot
            if j.joint_type == "fixed" or j.name not in col:
                continue
            axis = np.asarray(j.axis, dtype=float)
            axis = axis / (np.linalg.norm(axis) or 1.0)
            v = q[:, col[j.name]]
            if j.joint_type == "prismatic":
                pos = pos + (rot @ axis) * v[:, None]
            else:
                rot = rot @ _axis_angle(axis, v)
        return pos


# ---------------------------------------------------------------- the service
class LoggerService(Service):
    name = "logger"

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        self.run_dir = self._choose_run_dir()
        self.rrd_path = self.run_dir / RECORDING_NAME
        self.summary_path = self.run_dir / SUMMARY_NAME
        self.rec: rr.RecordingStream | None = None
        self._queue: deque[tuple[str, bytes]] = deque()
        self._key_names: dict[str, str] = {}
        self.recorded: Counter[str] = Counter()
        self._pending: Counter[str] = Counter()  # rows buffered, not yet sent, per key
        self._scalars: dict[str, tuple[list[int], list[float]]] = {}
        # Several scalar entities filled from one message (a JointState's joints, an Imu's axes):
        # one row of values per message here, split into entities at flush time.
        self._vectors: dict[tuple[str, ...], tuple[list[int], list[list[float]]]] = {}
        self._entity_cache: dict[tuple[Any, ...], tuple[str, ...]] = {}
        self._texts: dict[str, tuple[list[int], list[str], list[str]]] = {}
        self._model_rows: dict[str, tuple[list[int], list[float]]] = {}
        self._buffered = 0
        self._clock_ns = 0
        self._last_model_ns: int | None = None
        self._urdf: UrdfTree | None = None
        self._urdf_joints: dict[str, Any] = {}
        self._kin: ToolKinematics | None = None
        self._subs: list[Any] = []
        self._worker: threading.Thread | None = None
        self._worker_stop = threading.Event()
        self._warned: set[str] = set()
        # pycdr2 serializes through one buffer per message class, and msgs.decode re-serializes to
        # check the size: the worker's decoding and this process's own health/log publishing
        # (DiagnosticArray, Log) must not interleave, or valid payloads are rejected.
        self._codec_lock = threading.RLock()
        self._finished = False

    # ------------------------------------------------------------------ setup
    def _choose_run_dir(self) -> Path:
        lc = self.sc.logger
        if lc.run_dir is not None:
            return Path(lc.run_dir)
        base = Path(lc.out_dir) / time.strftime("%Y%m%d-%H%M%S")
        d, i = base, 1
        while d.exists():  # two runs started within the same second
            d, i = base.with_name(f"{base.name}-{i}"), i + 1
        return d

    def setup(self) -> None:
        assert self.session is not None
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if not (self.run_dir / "scenario.yaml").exists():
            write_scenario(self.sc, self.run_dir / "scenario.yaml")
        self._load_model()
        self.rec = rr.RecordingStream("hilsim", send_properties=True)
        # file sink only: no viewer, no network
        self.rec.save(self.rrd_path, default_blueprint=self._blueprint())
        self.rec.send_recording_name(f"{self.sc.name} {self.run_dir.name}")
        self._log_model()
        self._worker = threading.Thread(target=self._work, name="logger-worker", daemon=True)
        self._worker.start()
        for expr in self.sc.logger.record:
            sub = self.session.declare_subscriber(self.keys.scoped(expr), self._on_sample)
            self._subs.append(sub)
            self._declared.append(sub)
        self.log.info(
            "recording %s to %s", ", ".join(self.keys.scoped(e) for e in self.sc.logger.record), self.rrd_path
        )

    def _load_model(self) -> None:
        urdf = self.sc.world.urdf
        if urdf is None:
            return
        try:
            tree = UrdfTree.from_file_path(urdf, entity_path_prefix="robot")
            self._kin = ToolKinematics(tree)
        except Exception as e:  # a model rerun cannot load must not stop the recording
            self.warn(f"robot model {urdf} not recorded: {type(e).__name__}: {e}")
            return
        self._urdf = tree
        self._urdf_joints = {j.name: j for j in tree.joints() if j.joint_type != "fixed"}

    def _log_model(self) -> None:
        assert self.rec is not None
        if self._urdf is None or self._kin is None:
            return
        try:
            self._urdf.log_urdf_to_recording(self.rec)
        except Exception as e:
            self.warn(f"robot model {self.sc.world.urdf} not recorded: {type(e).__name__}: {e}")
            self._urdf, self._urdf_joints = None, {}
            return
        for topic in ("joint_trajectory", "planner/path"):
            self.rec.log(f"{topic}/tool_path", rr.CoordinateFrame(self._kin.root), static=True)

    def _blueprint(self) -> rrb.Blueprint:
        """Default layout of the viewer: the robot in 3D, logs, and one plot per joint and quantity."""
        joints = list(self._urdf_joints)
        left: list[Any] = []
        if self._kin is not None:
            left.append(
                rrb.Spatial3DView(
                    name="robot",
                    origin="/",
                    contents=["/robot/**", "/joint_trajectory/tool_path", "/planner/path/tool_path"],
                    spatial_information=rrb.archetypes.SpatialInformation(target_frame=self._kin.root),
                )
            )
        left.append(rrb.TextLogView(name="log", origin="/", contents=["/log/**", "/planner/**", "/rejected/**"]))
        tabs: list[Any] = [
            rrb.Grid(
                *(rrb.TimeSeriesView(name=f"{j} {q}", origin=f"/joints/{_part(j)}/{q}") for j in joints),
                name=q,
            )
            for q in ("position", "velocity", "effort")
        ]
        tabs += [
            rrb.TimeSeriesView(name="imu", origin="/imu"),
            rrb.TimeSeriesView(name="health", origin="/health"),
            rrb.TimeSeriesView(name="sync", origin="/sync"),
        ]
        return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*left), rrb.Tabs(*tabs), column_shares=[2, 3]))

    # ------------------------------------------------------------------ receiving (Zenoh thread)
    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Only queue: decoding here would slow Zenoh's delivery to every other subscriber.
        k = str(sample.key_expr)
        k = self._key_names.setdefault(k, k)  # one string per key, not one per queued sample
        self._queue.append((k, sample.payload.to_bytes()))
        # The base's health thread iterates these counters under self.lock.
        with self.lock:
            self.counts_in[k] += 1

    # ------------------------------------------------------------------ the worker
    def _work(self) -> None:
        q = self._queue
        last_flush = time.monotonic()
        while True:
            try:
                key, payload = q.popleft()
            except IndexError:
                if self._worker_stop.is_set():
                    break
                if self._buffered and time.monotonic() - last_flush >= FLUSH_PERIOD_S:
                    self._flush()
                    last_flush = time.monotonic()
                time.sleep(0.002)
                continue
            self._handle(key, payload)
            if self._buffered >= FLUSH_ROWS or time.monotonic() - last_flush >= FLUSH_PERIOD_S:
                self._flush()
                last_flush = time.monotonic()

    def _handle(self, key: str, payload: bytes) -> None:
        try:
            cls = message_type(key)
            with self._codec_lock:
                msg = msgs.decode(cls, payload)
        except (UnknownKey, msgs.BadMessage) as e:
            with self.lock:
                self.rejected[key] += 1
            if key not in self._warned:  # one warning per key; the rest are counted
                self._warned.add(key)
                self.warn(f"rejected payload on {key}: {e} (further ones on this key are only counted)")
            self._text(f"rejected/{_part(key)}", self._clock_ns, f"{len(payload)} bytes: {e}", "WARN")
            self._pending[key] += 1
            return
        try:
            self._dispatch(key, msg)
        except Exception as e:  # a bug here must not lose the sample: record it as text
            self.fault(f"cannot turn {key} into rows: {type(e).__name__}: {e}", exc=e)
            self._text(f"errors/{_part(key)}", self._clock_ns, f"{type(e).__name__}: {e}: {msg!r}"[:4000], "ERROR")
        self._pending[key] += 1

    # ------------------------------------------------------------------ rows
    def _scalar(self, entity: str, t: int, v: float) -> None:
        col = self._scalars.get(entity)
        if col is None:
            col = self._scalars[entity] = ([], [])
        col[0].append(t)
        col[1].append(v)
        self._buffered += 1

    def _vector(self, entities: tuple[str, ...], t: int, values: list[float]) -> None:
        col = self._vectors.get(entities)
        if col is None:
            col = self._vectors[entities] = ([], [])
        col[0].append(t)
        col[1].append(values)
        self._buffered += len(entities)

    def _text(self, entity: str, t: int, text: str, level: str = "INFO") -> None:
        col = self._texts.get(entity)
        if col is None:
            col = self._texts[entity] = ([], [], [])
        col[0].append(t)
        col[1].append(text)
        col[2].append(level)
        self._buffered += 1

    def _set_time(self, t: int) -> None:
        assert self.rec is not None
        self.rec.set_time(TIMELINE, duration=np.timedelta64(t, "ns"))

    @staticmethod
    def _index(times: list[int]) -> list[rr.TimeColumn]:
        return [rr.TimeColumn(TIMELINE, duration=np.asarray(times, dtype="timedelta64[ns]"))]

    def _flush(self) -> None:
        """Send every buffered row, then count the samples they came from as recorded."""
        rec = self.rec
        assert rec is not None
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
                    cols = self._urdf_joints[name].compute_transform_columns(vs, clamp=False)
                    sends.append((f"robot/joint_transforms/{_part(name)}", self._index(ts), cols))
                except Exception as e:  # the plots of this joint are recorded; only its 3D pose is lost
                    self.fault(f"cannot compute the transform of {name}: {type(e).__name__}: {e}", exc=e)
                ts.clear()
                vs.clear()
        for entity, index, columns in sends:
            try:
                rec.send_columns(entity, indexes=index, columns=columns)
            except Exception as e:  # count the loss (recorded < received) but keep recording
                ok = False
                self.fault(f"cannot record {entity}: {type(e).__name__}: {e}", exc=e)
        self._buffered = 0
        if ok:
            with self.lock:
                self.recorded.update(self._pending)
        self._pending.clear()

    # ------------------------------------------------------------------ messages -> rows
    def _dispatch(self, key: str, msg: Any) -> None:
        parts = key.split("/")
        if len(parts) == 2:  # <prefix>/clock
            t = msgs.ns_of(msg.clock)
            self._clock_ns = max(self._clock_ns, t)
            self.sim_ns = self._clock_ns
            self._scalar("clock", t, t * 1e-9)
            return
        robot, topic = parts[1], "/".join(parts[2:])
        root = "" if robot == self.sc.robot else f"robots/{_part(robot)}/"
        if topic in JOINT_SOURCES:
            self._joint_state(root, JOINT_SOURCES[topic], msg, model=(topic == "truth/joint_states" and not root))
        elif topic in IMU_SOURCES:
            self._imu(root, IMU_SOURCES[topic], msg)
        elif topic in ("joint_trajectory", "planner/path"):
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
            self._text(f"{root}log/{_part(parts[3])}", msgs.ns_of(msg.stamp), text, _log_level(msg.level))
        elif parts[2] == "sync" and len(parts) == 4:
            t = msgs.ns_of(msg.clock)
            self._scalar(f"{root}sync/{_part(parts[3])}", t, t * 1e-9)
        else:
            self._generic(root, topic, msg)

    def _stamp(self, msg: Any) -> int:
        h = getattr(msg, "header", None)
        if isinstance(h, msgs.Header):
            return msgs.ns_of(h.stamp)
        s = getattr(msg, "stamp", None)
        return msgs.ns_of(s) if isinstance(s, msgs.Time) else self._clock_ns

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
                entities = tuple(f"{root}joints/{_part(n)}/{quantity}/{source}" for n in names)
                self._entity_cache[ck] = entities
            self._vector(entities, t, values)
        if model and self._urdf_joints and msg.position:
            last = self._last_model_ns
            if last is None or t - last >= MODEL_PERIOD_NS or t < last:
                self._last_model_ns = t
                for name, v in zip(msg.name, msg.position, strict=False):
                    if name in self._urdf_joints:
                        col = self._model_rows.setdefault(name, ([], []))
                        col[0].append(t)
                        col[1].append(v)
                        self._buffered += 1

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
                    self._scalar(f"{root}joints/{_part(name)}/position/planned", t0 + tf, v)
        assert self.rec is not None
        self._set_time(t0)
        strips = [np.column_stack([x, q[:, i]]) for i in range(q.shape[1])]
        self.rec.log(f"{ent}/joint_space", rr.LineStrips2D(strips, labels=list(msg.joint_names)))
        if self._kin is not None and not root:
            self.rec.log(f"{ent}/tool_path", rr.LineStrips3D([self._kin.positions(list(msg.joint_names), q)]))

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
            base = f"{root}health/{_part(st.name or 'unnamed')}"
            self._scalar(f"{base}/level", t, float(st.level))
            for kv in st.values:
                try:
                    v = float(kv.value)
                except ValueError:
                    continue
                if math.isfinite(v):
                    self._scalar(f"{base}/{_part(kv.key)}", t, v)
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

    # ------------------------------------------------------------------ health
    def publish_health(self) -> None:
        with self._codec_lock:
            super().publish_health()

    def _publish_log(self, level: int, text: str) -> None:
        with self._codec_lock:
            super()._publish_log(level, text)

    def health_values(self) -> dict[str, Any]:  # called under self.lock
        return {
            "queue": len(self._queue),
            "recorded": sum(self.recorded.values()),
            "rrd": str(self.rrd_path),
        }

    # ------------------------------------------------------------------ stopping
    def loop(self) -> None:
        while not self.stop_event.wait(0.2):
            if self._worker is not None and not self._worker.is_alive():
                raise RuntimeError("the recording worker stopped unexpectedly")
        self._finish()

    def teardown(self) -> None:
        self._finish()

    def _finish(self) -> None:
        """Stop receiving, record everything queued, close the file, report the counts."""
        if self._finished:
            return
        self._finished = True
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass  # already gone with the session
        self._worker_stop.set()
        if self._worker is not None:
            self._worker.join()
        if self.rec is None:
            return
        while self._queue:  # anything that arrived while the worker was stopping
            self._handle(*self._queue.popleft())
        self._flush()
        self.rec.flush()
        self.rec.disconnect()
        self._report()

    def _report(self) -> None:
        with self.lock:
            received = Counter(self.counts_in)
        keys = sorted(set(received) | set(self.recorded))
        summary = {
            k: {"received": received[k], "recorded": self.recorded[k], "rejected": self.rejected[k]} for k in keys
        }
        tmp = self.summary_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
        tmp.replace(self.summary_path)
        total_in, total_rec = sum(received.values()), sum(self.recorded.values())
        lines = [f"recorded {k}: received {received[k]} recorded {self.recorded[k]}" for k in keys]
        lines.append(
            f"recorded total: received {total_in} recorded {total_rec} rejected {sum(self.rejected.values())} "
            f"in {len(keys)} keys -> {self.rrd_path}"
        )
        try:
            print("\n".join(lines), flush=True)
        except BrokenPipeError:
            # whoever read our stdout is gone (a killed launcher); the summary file is written
            self.log.warning("stdout closed; per-key counts are in %s", self.summary_path)
        if total_in != total_rec:
            self.fault(f"received {total_in} messages but recorded {total_rec}")


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
