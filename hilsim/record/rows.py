"""Decoded hilsim messages as Rerun rows: what the recorder writes for each kind of message.

:class:`RowWriter` turns one message into rows buffered per entity (timeline ``sim_time``, the
message's sim-time stamp) and sends them with ``send_columns`` when :meth:`RowWriter.flush` is
called. The per-step keys (clock, joint states, IMU) have a fast path that skips message objects
(:meth:`RowWriter.raw`, :class:`_Layout`): the same rows, read from the payloads' bytes in one
numpy pass per batch (``tests/test_rows_fast.py`` holds the two paths to the same rows).
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
``<planner|navigator>/feedback``, ``…/result``  TextLog, plus ``…/progress`` and
                                                ``…/result/planning_time`` Scalars
``<trajectory topic>``                          TextLog summary (``joint_trajectory``,
                                                ``planner/path``)
``<trajectory topic>/joint_space``              LineStrips2D: one strip per joint, x = time
                                                from start [s] (or waypoint index for paths)
``<trajectory topic>/tool_path``                LineStrips3D of the tool (forward kinematics of
                                                the URDF), in the URDF root frame
``robot/<robot name>/…``, ``tf_static``         the URDF model (``world.urdf``), static
``robot/joint_transforms/<joint>``              Transform3D of each moving joint from
                                                ``truth/joint_states``, every 10 ms of sim time
``world/<geom>``                                the world's static geometry (``hilsim.sim.scene``),
                                                static, frame ``world``
``tf/<child frame>``                            Transform3D parent → child from ``tf`` (every
                                                10 ms of sim time; a transform that did not
                                                change is not repeated); a fixed-base robot:
                                                ``tf/<root link>`` from the world model, static
``scan``                                        Points3D of the finite ranges of ``scan``, in
                                                the scan's frame (its ``header.frame_id``)
``odometry/<q>/<truth|odom>``                   Scalars of ``truth/odom`` and ``odom``; q = x,
                                                y, z, yaw (in the world) and vx, vy, wz (in the
                                                chassis frame)
``paths/<truth|odom>/<k>``                      LineStrips3D: the trail in the world (a point
                                                every 100 ms), ``paths/gps/<k>`` Points3D of
                                                the GPS fixes in the world (with a datum), at
                                                the chassis' true height
``odom/estimate``                               Boxes3D: the chassis where the odometry puts it
``geo/gps/<k>``, ``geo/<truth|odom>/<k>``       GeoPoints of ``gps/fix``; GeoLineStrings of the
                                                truth and odometry trails (with a datum)
``map``, ``plan``                               ``map`` (nav_msgs/OccupancyGrid) as a textured
                                                quad, ``plan`` (nav_msgs/Path) LineStrips3D
``<topic>/<field path>``                        Scalars of any other message type (numeric fields)
``rejected/<key>``, ``errors/<key>``            TextLog of payloads that failed to decode / to
                                                be turned into rows
==============================================  =============================================

The odometry (``odom``, frame ``odom``) is drawn in the world with its frame where the rover
started, as a robot's ``odom`` frame starts where the robot is: the free base's pose in the world
model (:attr:`Scene.base_start`); without a scene, the first ``truth/odom`` if it came before the
first ``odom``, else the world's origin.
Trails and tracks grow with time but stay cheap to write: see :class:`_Track`.

Importing this module imports rerun, after turning its analytics off.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.geometry import yaw_of
from hilsim.core.msgs import fastcdr
from hilsim.core.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

from hilsim.sim.kinematics import RobotModel  # noqa: E402
from hilsim.sim.scene import Scene  # noqa: E402

MODEL_PERIOD_NS = 10_000_000  # 3D robot pose updates (joints, tf, the odometry's chassis): every 10 ms of sim time
TRACK_PERIOD_NS = 100_000_000  # a point of a trail (truth, odometry) every 100 ms of sim time
TRACK_BLOCK = 100  # points per trail entity (see _Track)
GRID_TEXTURE_MAX = 4096  # cells per side of an occupancy grid's texture (larger grids: max-pooled)
GRID_LIFT = 0.01  # [m] the grid's quad above its origin, so it is not hidden in the floor
PATH_LIFT = 0.05  # [m] a plan drawn above the grid
TIMELINE = "sim_time"
WORLD_FRAME = "world"
TRAJECTORY_TOPICS = ("joint_trajectory", "planner/path")
ODOM_SOURCES = {"truth/odom": "truth", "odom": "odom"}
ODOM_QUANTITIES = ("x", "y", "z", "yaw", "vx", "vy", "wz")  # pose in the world, twist in the chassis frame
COLOURS = {  # RGB of the 3D and map entities
    "truth": (40, 190, 60),  # green
    "odom": (0, 190, 240),  # cyan: not the rover's own orange
    "gps": (220, 30, 30),  # red
    "scan": (230, 0, 200),  # magenta
    "plan": (255, 210, 0),  # yellow
}

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


def scan_points(msg: msgs.LaserScan, cache: dict[tuple[int, float, float], np.ndarray] | None = None) -> np.ndarray:
    """Points (N, 3) of a scan's finite ranges in its own frame: ray i at ``angle_min + i·angle_increment``
    counter-clockwise from x, in the x-y plane (``±inf``, no return or too close, and NaN are left out)."""
    r = np.asarray(msg.ranges, dtype=float)
    key = (len(r), msg.angle_min, msg.angle_increment)
    cs = cache.get(key) if cache is not None else None
    if cs is None:
        a = msg.angle_min + msg.angle_increment * np.arange(len(r))
        cs = np.stack([np.cos(a), np.sin(a)], axis=1)
        if cache is not None:
            cache[key] = cs
    ok = np.isfinite(r)
    xy = cs[ok] * r[ok, None]
    return np.column_stack([xy, np.zeros(len(xy))])


class _Track:
    """A trail that grows with sim time, drawn with the viewer's latest-at semantics.

    A point is kept every ``period_ns``. Points are cut into blocks of ``TRACK_BLOCK``, one entity
    each (``<entity>/<k>``); each new point re-sends its block so far as one row. At any time the
    viewer then shows the whole trail up to that time, and each point is written at most
    TRACK_BLOCK times, instead of once per later point as when the whole trail is re-sent.
    """

    def __init__(self, entity: str, period_ns: int, static: list[Any]) -> None:
        self.entity = entity
        self.period_ns = period_ns
        self.static = static  # logged once on each block entity: colour, radius, frame
        self.last_ns: int | None = None
        self.points: list[Any] = []
        self.k = -1
        self.rows: dict[str, tuple[list[int], list[np.ndarray]]] = {}

    def due(self, t: int) -> bool:
        last = self.last_ns
        return last is None or t - last >= self.period_ns or t < last

    def add(self, rec: rr.RecordingStream, t: int, point: Any) -> None:
        self.last_ns = t
        if self.k < 0 or len(self.points) >= TRACK_BLOCK:
            self.k += 1
            self.points = self.points[-1:]  # a line's next block starts where the last one ended
            rec.log(f"{self.entity}/{self.k}", *self.static, static=True)
        self.points.append(point)
        col = self.rows.setdefault(f"{self.entity}/{self.k}", ([], []))
        col[0].append(t)
        col[1].append(np.asarray(self.points, dtype=float))


_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header: XCDR1, little-endian
_TIME = struct.Struct("<iI")
IMU_DOUBLES = 37  # orientation 4, then 9 covariance, 3 + 9 (angular velocity), 3 + 9 (acceleration)
IMU_VALUES = (0, 1, 2, 3, 13, 14, 15, 25, 26, 27)  # the recorded ones among them


@dataclasses.dataclass
class _Layout:
    """The bytes of one key's JointState or Imu messages, learnt from one that decoded and validated.

    Every later payload of exactly this layout (same size; the same bytes everywhere but the
    stamp and the doubles: frame id, joint names, sequence lengths, padding) is the same message
    but for its stamp and values, and is read straight into columns by :meth:`RowWriter.drain`
    (numpy over the concatenated payloads) without building a message object. The finiteness
    check ``msgs.validate`` makes is done there, for the whole batch at once."""

    cls: type
    size: int
    checks: tuple[tuple[int, bytes], ...]  # (offset, bytes that must be there)
    dtype: np.dtype
    blocks: tuple[tuple[str, tuple[str, ...]], ...]  # dtype field of doubles, entities of its columns (or ())
    rows: int  # rows buffered per sample
    model_names: tuple[str, ...] = ()  # truth/joint_states of the scenario's robot: the joints of the model
    payloads: list[bytes] = dataclasses.field(default_factory=list)
    clocks: list[int] = dataclasses.field(default_factory=list)  # clock_ns at arrival (a rejected row's time)

    def fits(self, data: bytes) -> bool:
        if len(data) != self.size:
            return False
        for off, b in self.checks:
            if not data.startswith(b, off):
                return False
        return True


def _layout(cls: type, data: bytes, doubles: list[tuple[int, int]], blocks: tuple[tuple[str, ...], ...],
            rows: int) -> _Layout:
    """A layout from a payload whose doubles lie at ``doubles`` ((offset, count) each)."""
    checks, pos = [(0, data[:4])], 12  # bytes 4..12: the stamp
    for off, n in doubles:
        if off > pos:
            checks.append((pos, data[pos:off]))
        pos = off + 8 * n
    dtype = np.dtype({"names": ["sec", "nsec", *(f"d{i}" for i in range(len(doubles)))],
                      "formats": ["<i4", "<u4", *(("<f8", (n,)) for _, n in doubles)],
                      "offsets": [4, 8, *(off for off, _ in doubles)], "itemsize": len(data)})
    return _Layout(cls, len(data), tuple(checks), dtype,
                   tuple((f"d{i}", b) for i, b in enumerate(blocks)), rows)


class RowWriter:
    """Rows of one recording, buffered per entity until :meth:`flush`.

    ``robot`` is the scenario's robot (its entities have no ``robots/<robot>/`` prefix);
    ``model`` the robot model, or None; ``fault(text, exc=…)`` reports an error that only
    loses part of a message's rows (a joint transform, one entity's batch).
    """

    def __init__(self, rec: rr.RecordingStream, robot: str, model: RobotModel | None, fault: Fault,
                 scene: Scene | None = None) -> None:
        self.rec = rec
        self.robot = robot
        self.model = model
        self.scene = scene
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
        # tf: the latest transform written per child frame, and the rows waiting for flush()
        self._last_tf_ns: int | None = None
        self._tf_last: dict[str, tuple[Any, ...]] = {}
        self._tf_rows: dict[str, list[tuple[Any, ...]]] = {}
        self._tf_times: dict[str, list[int]] = {}
        # the odom frame in the world (x, y, z, yaw), fixed by the first truth/odom or odom
        self._odom_origin: tuple[float, float, float, float] | None = None
        self._truth_z: float | None = None  # the chassis' latest true height (GPS fixes are drawn there)
        self._tracks: dict[str, _Track] = {}
        self._ghost: tuple[list[int], list[list[float]], list[list[float]]] = ([], [], [])
        self._last_ghost_ns: int | None = None
        self._scans: dict[str, tuple[list[int], list[np.ndarray], list[str]]] = {}
        self._scan_dirs: dict[tuple[int, float, float], np.ndarray] = {}
        # the fast path (:meth:`raw`): per key, the clock marker or the layout of its messages
        self._layouts: dict[str, _Layout | None] = {}
        self._fast_rows: list[tuple[tuple[str, ...], np.ndarray, np.ndarray]] = []  # entities, times, values
        # payloads the fast path found invalid (non-finite values) at drain time: (key, reason);
        # recorded under rejected/<key> like any other, and taken by the recorder to count them
        self.rejections: list[tuple[str, msgs.BadMessage]] = []

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

    def log_scene(self) -> None:
        """The world's static geometry, where a fixed-base robot stands in it, and the style of the
        entities the rover's messages fill (static). Raises whatever rerun raises."""
        sc = self.scene
        if sc is None:
            return
        rec = self.rec
        sc.log_static(rec, WORLD_FRAME)
        if sc.root_pose is not None and self.model is not None:
            pos, quat = sc.root_pose
            rec.log(f"tf/{part(self.model.root)}", rr.Transform3D(
                translation=pos, quaternion=quat, parent_frame=WORLD_FRAME, child_frame=self.model.root), static=True)
        rec.log("scan", rr.Points3D.from_fields(colors=[COLOURS["scan"]], radii=[0.04]), static=True)
        if sc.base_box is not None:
            rec.log("odom/estimate", rr.Boxes3D.from_fields(
                half_sizes=[sc.base_box[1]], colors=[COLOURS["odom"]], fill_mode="majorwireframe"),
                rr.CoordinateFrame(WORLD_FRAME), static=True)

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
        elif topic in ODOM_SOURCES:
            self._odometry(root, ODOM_SOURCES[topic], msg)
        elif topic == "tf":
            self._tf(root, robot, msg)
        elif topic in TRAJECTORY_TOPICS:
            self._trajectory(root, topic, msg)
        elif isinstance(msg, msgs.LaserScan):
            self._scan(root, topic, robot, msg)
        elif isinstance(msg, msgs.NavSatFix):
            self._gps(root, topic, msg)
        elif isinstance(msg, msgs.OccupancyGrid):
            self._grid(root, topic, robot, msg)
        elif isinstance(msg, msgs.Path):
            self._path(root, topic, robot, msg)
        elif isinstance(msg, msgs.MoveFeedback):
            t = msgs.ns_of(msg.header.stamp)
            self._text(f"{root}{topic}", t, f"{msg.goal_id}: {msg.state} {msg.progress:.0%}")
            self._scalar(f"{root}{topic}/progress", t, msg.progress)
        elif isinstance(msg, msgs.MoveResult):
            self._result(root, topic, msg)
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

    # ------------------------------------------------------------------ the fast path
    def raw(self, key: str, data: bytes) -> bool:
        """Rows of a payload on a key whose layout is known (:meth:`learn`), without decoding it
        into a message: True if taken (its rows buffered, or its validation left to
        :meth:`drain`), False if it must go the ordinary way (decode, validate, :meth:`message`)."""
        lay = self._layouts.get(key, False)
        if lay is False:
            return False
        if lay is None:  # <prefix>/clock: 12 bytes, no floats to check
            if len(data) != 12 or not data.startswith(_LE):
                return False
            sec, ns = _TIME.unpack_from(data, 4)
            t = sec * 1_000_000_000 + ns
            if t > self.clock_ns:
                self.clock_ns = t
            self._scalar("clock", t, t * 1e-9)
            return True
        if not lay.fits(data):
            self.drain(key)  # rows in arrival order: what came before goes first
            return False
        lay.payloads.append(data)
        lay.clocks.append(self.clock_ns)
        self.buffered += lay.rows
        return True

    def learn(self, key: str, data: bytes, msg: Any) -> None:
        """After ``msg`` (decoded and validated from ``data``) went through :meth:`message`: let
        later payloads of the same layout on ``key`` take the fast path (clock, joint states, IMU)."""
        if key in self._layouts:
            return
        parts = key.split("/")
        if len(parts) == 2 and isinstance(msg, msgs.Clock):
            self._layouts[key] = None
            return
        if len(parts) < 3 or not data.startswith(_LE):
            return
        robot, topic = parts[1], "/".join(parts[2:])
        root = "" if robot == self.robot else f"robots/{part(robot)}/"
        try:
            if topic in JOINT_SOURCES and isinstance(msg, msgs.JointState):
                lay = self._joint_layout(root, JOINT_SOURCES[topic], data)
                # the model's joint transforms come from the positions: d0 when there are any
                if lay is not None and msg.position and topic == "truth/joint_states" and not root:
                    lay.model_names = tuple(msg.name)
            elif topic in IMU_SOURCES and isinstance(msg, msgs.Imu):
                lay = self._imu_layout(root, IMU_SOURCES[topic], data)
            else:
                return
        except (ValueError, struct.error):  # not laid out as expected: the ordinary way it stays
            return
        if lay is not None:
            self._layouts[key] = lay

    def _joint_layout(self, root: str, source: str, data: bytes) -> _Layout | None:
        r = fastcdr._Reader(data)
        r.time()
        r.string()
        names = tuple(r.strseq())
        doubles, blocks, rows = [], [], 0
        for quantity in ("position", "velocity", "effort"):
            n = r.u32()
            if not n:
                continue
            r.align(8)
            doubles.append((r.pos, n))
            r.pos += 8 * n
            blocks.append(tuple(f"{root}joints/{part(nm)}/{quantity}/{source}" for nm in names))
            rows += n
        if r.pos != len(data) or any(n != len(names) for _, n in doubles):
            return None
        return _layout(msgs.JointState, data, doubles, tuple(blocks), rows)

    def _imu_layout(self, root: str, source: str, data: bytes) -> _Layout | None:
        r = fastcdr._Reader(data)
        r.time()
        r.string()
        r.align(8)
        if r.pos + 8 * IMU_DOUBLES != len(data):
            return None
        base = f"{root}imu/{source}"
        entities = tuple(f"{base}/orientation/{a}" for a in "xyzw") + tuple(
            f"{base}/{f}/{a}" for f in ("angular_velocity", "linear_acceleration") for a in "xyz")
        return _layout(msgs.Imu, data, [(r.pos, IMU_DOUBLES)], (entities,), len(entities))

    def drain(self, key: str) -> None:
        """Turn the payloads the fast path holds for ``key`` into rows: one numpy view over all of
        them; a sample with a non-finite value is rejected (``rejected/<key>``, :attr:`rejections`)."""
        lay = self._layouts.get(key)
        if lay is None or not lay.payloads:
            return
        payloads, clocks = lay.payloads, lay.clocks
        lay.payloads, lay.clocks = [], []
        arr = np.frombuffer(b"".join(payloads), dtype=lay.dtype)
        ok = np.ones(len(arr), dtype=bool)
        for f, _ in lay.blocks:
            ok &= np.isfinite(arr[f]).all(axis=1)
        if not ok.all():
            for i in np.flatnonzero(~ok).tolist():
                self.buffered -= lay.rows
                try:
                    msgs.decode(lay.cls, payloads[i])
                    reason = msgs.BadMessage(f"{lay.cls.__name__} has a non-finite value")  # not expected
                except msgs.BadMessage as e:
                    reason = e
                self.rejections.append((key, reason))
                self._text(f"rejected/{part(key)}", clocks[i], f"{len(payloads[i])} bytes: {reason}", "WARN")
            arr = arr[ok]
            if not len(arr):
                return
        t = arr["sec"].astype(np.int64) * 1_000_000_000 + arr["nsec"]
        if lay.cls is msgs.Imu:
            values = arr["d0"][:, IMU_VALUES]
            self._fast_rows.append((lay.blocks[0][1], t, np.ascontiguousarray(values.T)))
            return
        for f, entities in lay.blocks:
            self._fast_rows.append((entities, t, np.ascontiguousarray(arr[f].T)))
        if lay.model_names:
            self._model_fast(lay.model_names, t, arr["d0"])

    def _model_fast(self, names: tuple[str, ...], t: np.ndarray, position: np.ndarray) -> None:
        """The joint transforms of ``truth/joint_states``, every MODEL_PERIOD_NS (as :meth:`_joint_state`)."""
        joints = self.model.joints if self.model is not None else {}
        if not joints:
            return
        last, picked = self._last_model_ns, []
        for i, ti in enumerate(t.tolist()):
            if last is None or ti - last >= MODEL_PERIOD_NS or ti < last:
                last = ti
                picked.append(i)
        self._last_model_ns = last
        if not picked:
            return
        ts = t[picked].tolist()
        for j, name in enumerate(names):
            if name in joints:
                col = self._model_rows.setdefault(name, ([], []))
                col[0].extend(ts)
                col[1].extend(position[picked, j].tolist())
                self.buffered += len(ts)

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

    def _result(self, root: str, topic: str, msg: msgs.MoveResult) -> None:
        t = msgs.ns_of(msg.header.stamp)
        err = max((abs(e) for e in msg.execution_error), default=0.0)
        text = (
            f"{msg.goal_id}: {'success' if msg.success else 'failure'} (code {msg.error_code}) {msg.message}; "
            f"planner {msg.planner}, planning {msg.planning_time:.3f} s, "
            f"{len(msg.trajectory.points)} points, max execution error {err:.4f}"
        )
        self._text(f"{root}{topic}", t, text, "INFO" if msg.success else "WARN")
        self._scalar(f"{root}{topic}/planning_time", t, msg.planning_time)

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

    # ------------------------------------------------------------------ the rover
    def _frame(self, root: str, robot: str, frame: str) -> str:
        """A frame id of ``robot`` as a Rerun frame: another robot's frames get its name in front."""
        return frame if not root or frame == WORLD_FRAME else f"{robot}:{frame}"

    def _tf(self, root: str, robot: str, msg: msgs.TFMessage) -> None:
        if not msg.transforms:
            return
        t = msgs.ns_of(msg.transforms[0].header.stamp)
        last = self._last_tf_ns
        if last is not None and 0 <= t - last < MODEL_PERIOD_NS:
            return  # the cheap path: four of five physics steps
        self._last_tf_ns = t
        for tr in msg.transforms:
            tt, r = tr.transform.translation, tr.transform.rotation
            child = self._frame(root, robot, tr.child_frame_id)
            row = (self._frame(root, robot, tr.header.frame_id), child, tt.x, tt.y, tt.z, r.x, r.y, r.z, r.w)
            if self._tf_last.get(child) == row:
                continue  # a sensor's frame on the chassis: written once
            self._tf_last[child] = row
            entity = f"{root}tf/{part(tr.child_frame_id)}"
            self._tf_rows.setdefault(entity, []).append(row)
            self._tf_times.setdefault(entity, []).append(t)
            self.buffered += 1

    def _odometry(self, root: str, source: str, msg: msgs.Odometry) -> None:
        t = msgs.ns_of(msg.header.stamp)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        x, y, z, yaw = p.x, p.y, p.z, yaw_of(q)
        if not root:
            origin = self._odom_origin
            if origin is None:  # the odom frame starts where the rover truly is when it starts
                sc = self.scene
                if sc is not None and sc.base_start is not None:  # its start in the model (a restarted
                    origin = sc.base_start  # recorder may not see the run's first truth)
                else:
                    origin = (x, y, z, yaw) if source == "truth" else (0.0, 0.0, 0.0, 0.0)
                self._odom_origin = origin
            if source == "odom":  # into the world
                c, s = math.cos(origin[3]), math.sin(origin[3])
                x, y, z, yaw = (origin[0] + c * x - s * y, origin[1] + s * x + c * y, origin[2] + z,
                                math.atan2(math.sin(origin[3] + yaw), math.cos(origin[3] + yaw)))
        ck = (root, source, "odometry")
        entities = self._entity_cache.get(ck)
        if entities is None:
            entities = self._entity_cache[ck] = tuple(f"{root}odometry/{q_}/{source}" for q_ in ODOM_QUANTITIES)
        tw = msg.twist.twist
        self._vector(entities, t, [x, y, z, yaw, tw.linear.x, tw.linear.y, tw.angular.z])
        if source == "truth" and not root:
            self._truth_z = z
        if root:
            return
        track = self._tracks.get(source)
        if track is None:
            # the truth wider: where the odometry is right, its line lies on the truth's, edged in green
            radius = 0.04 if source == "truth" else 0.02
            track = self._tracks[source] = _Track(f"paths/{source}", TRACK_PERIOD_NS, [
                rr.LineStrips3D.from_fields(colors=[COLOURS[source]], radii=[radius]), rr.CoordinateFrame(WORLD_FRAME)])
        if track.due(t):
            track.add(self.rec, t, (x, y, z))
            self.buffered += 1
            self._geo_track(source, t, x, y)
        sc = self.scene
        if source == "odom" and sc is not None and sc.base_box is not None:
            last = self._last_ghost_ns
            if last is None or t - last >= MODEL_PERIOD_NS or t < last:
                self._last_ghost_ns = t
                c, s = math.cos(yaw), math.sin(yaw)
                bx, by, bz = sc.base_box[0]
                g = self._ghost
                g[0].append(t)
                g[1].append([x + c * bx - s * by, y + s * bx + c * by, z + bz])
                g[2].append([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
                self.buffered += 1

    def _geo_track(self, source: str, t: int, x: float, y: float) -> None:
        datum = self.scene.datum if self.scene is not None else None
        if datum is None:
            return
        key = f"geo/{source}"
        track = self._tracks.get(key)
        if track is None:
            track = self._tracks[key] = _Track(key, TRACK_PERIOD_NS, [
                rr.GeoLineStrings.from_fields(colors=[COLOURS[source]], radii=[-2.0])])  # 2 ui points wide
        lat, lon = datum.to_geo(x, y)
        track.add(self.rec, t, (lat, lon))
        self.buffered += 1

    def _scan(self, root: str, topic: str, robot: str, msg: msgs.LaserScan) -> None:
        t = msgs.ns_of(msg.header.stamp)
        col = self._scans.setdefault(f"{root}{topic}", ([], [], []))
        col[0].append(t)
        col[1].append(scan_points(msg, self._scan_dirs))
        col[2].append(self._frame(root, robot, msg.header.frame_id))
        self.buffered += 1

    def _gps(self, root: str, topic: str, msg: msgs.NavSatFix) -> None:
        self._generic(root, topic, msg)  # latitude, longitude, altitude, status as plots
        if root or not (math.isfinite(msg.latitude) and math.isfinite(msg.longitude)):
            return
        t = msgs.ns_of(msg.header.stamp)
        track = self._tracks.get("geo/gps")
        if track is None:  # every fix is kept: a point each, on the map
            track = self._tracks["geo/gps"] = _Track("geo/gps", 0, [
                rr.GeoPoints.from_fields(colors=[COLOURS["gps"]], radii=[-3.0])])
        track.add(self.rec, t, (msg.latitude, msg.longitude))
        self.buffered += 1
        datum = self.scene.datum if self.scene is not None else None
        if datum is not None:  # and in the world, next to the truth's trail
            world = self._tracks.get("gps")
            if world is None:
                world = self._tracks["gps"] = _Track("paths/gps", 0, [
                    rr.Points3D.from_fields(colors=[COLOURS["gps"]], radii=[0.06]), rr.CoordinateFrame(WORLD_FRAME)])
            x, y = datum.to_world(msg.latitude, msg.longitude)
            # at the rover's true height when there is a truth: the view is for the horizontal error
            # (the vertical one, σ of metres, would float fixes in the air; gps/fix/altitude plots it)
            z = self._truth_z if self._truth_z is not None else msg.altitude - datum.alt
            world.add(self.rec, t, (float(x), float(y), z))
            self.buffered += 1

    def _grid(self, root: str, topic: str, robot: str, msg: msgs.OccupancyGrid) -> None:
        """An occupancy grid as a quad on the ground textured with its cells: free light, occupied
        black, unknown mid grey, in between by the occupancy probability."""
        t = msgs.ns_of(msg.header.stamp)
        info = msg.info
        w, h, res = int(info.width), int(info.height), float(info.resolution)
        if w * h == 0 or len(msg.data) != w * h:
            self._text(f"{root}{topic}/status", t, f"occupancy grid {w}x{h} with {len(msg.data)} cells: not drawn",
                       "WARN")
            return
        cells = np.asarray(msg.data, dtype=np.int16).reshape(h, w)
        step = max(1, -(-max(w, h) // GRID_TEXTURE_MAX))  # a texture the viewer can hold: keep the max
        if step > 1:
            hh, ww = -(-h // step), -(-w // step)
            padded = np.full((hh * step, ww * step), -1, np.int16)
            padded[:h, :w] = cells
            cells = padded.reshape(hh, step, ww, step).max(axis=(1, 3))
        grey = np.where(cells < 0, 128, 235 - np.clip(cells, 0, 100) * 2.35).astype(np.uint8)
        o = info.origin
        rot = _quat_matrix(o.orientation)
        corners = np.array([[0, 0, GRID_LIFT], [w * res, 0, GRID_LIFT], [w * res, h * res, GRID_LIFT],
                            [0, h * res, GRID_LIFT]]) @ rot.T + [o.position.x, o.position.y, o.position.z]
        self.rec.set_time(TIMELINE, duration=np.timedelta64(t, "ns"))
        # row 0 of the grid is at the origin (y = 0): the texture's v runs with the rows
        self.rec.log(f"{root}{topic}", rr.Mesh3D(
            vertex_positions=corners, triangle_indices=[[0, 1, 2], [0, 2, 3]],
            vertex_texcoords=[[0, 0], [1, 0], [1, 1], [0, 1]], vertex_normals=[rot[:, 2]] * 4,
            albedo_texture=np.repeat(grey[:, :, None], 3, axis=2)),
            rr.CoordinateFrame(self._frame(root, robot, msg.header.frame_id or WORLD_FRAME)))

    def _path(self, root: str, topic: str, robot: str, msg: msgs.Path) -> None:
        t = msgs.ns_of(msg.header.stamp)
        pts = [(p.pose.position.x, p.pose.position.y, p.pose.position.z + PATH_LIFT) for p in msg.poses]
        self._text(f"{root}{topic}/summary", t, f"{len(pts)} poses" + (
            f" from ({pts[0][0]:.2f}, {pts[0][1]:.2f}) to ({pts[-1][0]:.2f}, {pts[-1][1]:.2f})" if pts else ""))
        self.rec.set_time(TIMELINE, duration=np.timedelta64(t, "ns"))
        self.rec.log(f"{root}{topic}", rr.LineStrips3D([pts] if pts else [], colors=[COLOURS["plan"]], radii=[0.04]),
                     rr.CoordinateFrame(self._frame(root, robot, msg.header.frame_id or WORLD_FRAME)))

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
        for key in self._layouts:
            self.drain(key)
        sends: list[tuple[str, list[rr.TimeColumn], Any]] = []
        for entities, t, columns in self._fast_rows:
            index = [rr.TimeColumn(TIMELINE, duration=t.view("timedelta64[ns]"))]
            sends += [(e, index, rr.Scalars.columns(scalars=columns[i])) for i, e in enumerate(entities)]
        self._fast_rows.clear()
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
        for entity, rows in self._tf_rows.items():
            if rows:
                ts = self._tf_times[entity]
                a = np.asarray([r[2:] for r in rows], dtype=float)
                cols = rr.Transform3D.columns(translation=a[:, :3], quaternion=a[:, 3:],
                                              parent_frame=[r[0] for r in rows], child_frame=[r[1] for r in rows])
                sends.append((entity, self._index(ts), cols))
                rows.clear()
                ts.clear()
        for entity, (ts, pts, frames) in self._scans.items():
            if ts:
                cols = rr.Points3D.columns(positions=np.concatenate(pts)).partition([len(p) for p in pts])
                sends.append((entity, self._index(ts), [*cols, *rr.CoordinateFrame.columns(frame=frames)]))
                ts.clear()
                pts.clear()
                frames.clear()
        for track in self._tracks.values():
            for entity, (ts, blocks) in track.rows.items():
                if not ts:
                    continue
                lengths = [len(b) for b in blocks]
                if track.entity.startswith("geo/gps"):
                    cols = rr.GeoPoints.columns(positions=np.concatenate(blocks)).partition(lengths)
                elif track.entity.startswith("geo/"):
                    cols = rr.GeoLineStrings.columns(line_strings=blocks).partition([1] * len(blocks))
                elif track.entity == "paths/gps":
                    cols = rr.Points3D.columns(positions=np.concatenate(blocks)).partition(lengths)
                else:
                    cols = rr.LineStrips3D.columns(strips=blocks).partition([1] * len(blocks))
                sends.append((entity, self._index(ts), cols))
                ts.clear()
                blocks.clear()
            track.rows = {}  # a full block is never sent again
        g = self._ghost
        if g[0]:
            sends.append(("odom/estimate", self._index(g[0]), rr.Boxes3D.columns(
                centers=np.asarray(g[1]), quaternions=np.asarray(g[2]))))
            for c in g:
                c.clear()
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


def _quat_matrix(q: msgs.Quaternion) -> np.ndarray:
    w, x, y, z = q.w, q.x, q.y, q.z
    n = w * w + x * x + y * y + z * z
    if n == 0.0:  # an unset orientation: the identity
        return np.eye(3)
    s = 2.0 / n
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
    ])


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
