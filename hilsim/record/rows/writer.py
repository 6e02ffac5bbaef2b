"""The writer's core: :class:`RowWriter`, its state, the dispatch of a message to its family's rows
by key and type, the rows of payloads that failed (``rejected/<key>``, ``errors/<key>``), the
counts (``buffered``, ``clock_ns``, ``rejections``) and :meth:`RowWriter.flush`, which sends every
family's buffered rows.

Entity paths written here (the others are written by the families' modules): ``clock``,
``sync/<service>``, ``log/<service>``, ``<planner|navigator>/feedback`` (TextLog) and its
``…/progress``, ``rejected/<key>``, ``errors/<key>``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.record.rows.common import IMU_SOURCES, JOINT_SOURCES, TIMELINE, Fault, part, rr, topic_parts
from hilsim.record.rows.fast import FastRows, _Layout
from hilsim.record.rows.generic import GenericRows
from hilsim.record.rows.imu import ImuRows
from hilsim.record.rows.joints import TRAJECTORY_TOPICS, JointRows
from hilsim.record.rows.mobile import ODOM_SOURCES, MobileRows, _Track
from hilsim.record.rows.status import StatusRows, log_level
from hilsim.record.rows.tasks import TaskRows
from hilsim.sim.kinematics import RobotModel
from hilsim.sim.scene import Scene


class RowWriter(FastRows, JointRows, ImuRows, MobileRows, StatusRows, TaskRows, GenericRows):
    """Rows of one recording, buffered per entity until :meth:`flush`.

    ``robot`` is the scenario's robot (its entities have no ``robots/<robot>/`` prefix);
    ``model`` the robot model, or None; ``fault(text, exc=…)`` reports an error that only
    loses part of a message's rows (a joint transform, one entity's batch). ``model_from_truth``: the
    recording has the truth's joint states, from which the model's moving links are posed
    (``robot/joint_transforms/…``); ``tf`` rows then do not name those links' frames (a frame posed by two
    entities is an error in Rerun's viewer, and the same truth twice).
    """

    def __init__(self, rec: rr.RecordingStream, robot: str, model: RobotModel | None, fault: Fault,
                 scene: Scene | None = None, model_from_truth: bool = False) -> None:
        self.rec = rec
        # the links posed from the truth's joint states: their tf rows name no frames
        self._posed = {j.child_link for j in model.joints.values()} if model is not None and model_from_truth \
            else set()
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
        # robots as arrays (hilsim.core.fleet): the joint topics a fleet sample (/<robot>/fleet/<topic>)
        # has carried; the fleet robots' rows of those topics come from it, not from their own keys
        # (the same values; with logger.batch nobody builds the robots' own keys, composed or not)
        self._fleet_covered: set[str] = set()
        self._fleet_groups: dict[tuple[str, ...], list[tuple[str, slice, tuple[str, ...]]]] = {}
        self._covered_keys: dict[str, bool] = {}
        # a fleet robot's own joint rows written before its topic was covered: (root, source) -> stamp,
        # so the fleet sample of that step does not write them again
        self._robot_rows: dict[tuple[str, str], int] = {}
        self._texts: dict[str, tuple[list[int], list[str], list[str]]] = {}
        self._model_rows: dict[str, tuple[list[int], list[float]]] = {}
        self._last_model_ns: int | None = None
        # tf: the latest transform written per child frame, and the rows waiting for flush()
        self._last_tf_ns: dict[str, int] = {}  # per message kind (its first frame): the chassis, the URDF's joints
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

    # ------------------------------------------------------------------ messages -> rows
    def covered(self, key: str) -> bool:
        """Whether a fleet robot's own joint key gets its rows from the fleet sample (:meth:`message`)."""
        got = self._covered_keys.get(key)
        if got is None:
            parts = topic_parts(key)
            got = len(parts) > 2 and parts[1] != self.robot and "/".join(parts[2:]) in self._fleet_covered
            self._covered_keys[key] = got
        return got

    def _fleet_joint_state(self, source: str, topic: str, msg: msgs.JointState) -> None:
        """A fleet sample's rows, robot by robot, as each robot's own key would give them (joints
        ``<robot>/<joint>``, each robot's joints together)."""
        if topic not in self._fleet_covered:
            self._fleet_covered.add(topic)
            self._covered_keys.clear()  # decided again with this topic covered
        names = tuple(msg.name)
        groups = self._fleet_groups.get(names)
        if groups is None:
            groups = []
            start = 0
            for i in range(1, len(names) + 1):
                robot = names[start].split("/", 1)[0]
                if i == len(names) or names[i].split("/", 1)[0] != robot:
                    root = "" if robot == self.robot else f"robots/{part(robot)}/"
                    groups.append((root, slice(start, i), tuple(n.split("/", 1)[-1] for n in names[start:i])))
                    start = i
            self._fleet_groups[names] = groups
        t = msgs.ns_of(msg.header.stamp)
        for quantity in ("position", "velocity", "effort"):
            values = getattr(msg, quantity)
            if not values:
                continue
            for root, sl, joints in groups:
                if self._robot_rows.get((root, source)) == t:
                    continue  # this step's rows came with the robot's own key, before the fleet's
                ck = (root, source, quantity, joints)
                entities = self._entity_cache.get(ck)
                if entities is None:
                    entities = tuple(f"{root}joints/{part(n)}/{quantity}/{source}" for n in joints)
                    self._entity_cache[ck] = entities
                self._vector(entities, t, values[sl])

    def message(self, key: str, msg: Any) -> None:
        """Rows of one decoded message on ``key`` (``/clock`` or ``/<robot>/<topic>``, :func:`topic_parts`)."""
        parts = topic_parts(key)
        if len(parts) == 2 and isinstance(msg, msgs.Clock):  # /clock
            t = msgs.ns_of(msg.clock)
            self.clock_ns = max(self.clock_ns, t)
            self._scalar("clock", t, t * 1e-9)
            return
        if len(parts) < 3:  # a global topic: /tf, /tf_static, or another ROS 2 node's
            if isinstance(msg, msgs.TFMessage):
                self._tf("", self.robot, msg)
            else:
                self._generic("", "/".join(parts[1:]), msg)
            return
        robot, topic = parts[1], "/".join(parts[2:])
        root = "" if robot == self.robot else f"robots/{part(robot)}/"
        if topic.startswith("fleet/") and topic[6:] in JOINT_SOURCES and isinstance(msg, msgs.JointState):
            self._fleet_joint_state(JOINT_SOURCES[topic[6:]], topic[6:], msg)
            return
        if root and topic in self._fleet_covered:
            return  # a fleet robot's joints: rows from its fleet sample (the same values)
        if root and topic in JOINT_SOURCES and isinstance(msg, msgs.JointState):
            self._robot_rows[root, JOINT_SOURCES[topic]] = msgs.ns_of(msg.header.stamp)
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
            self._text(f"{root}{topic}", t, f"{msg.goal_id}: {msg.state} {msg.progress:.0%}"
                       + (f" ({msg.planner}; {msg.choice})" if msg.choice else ""))
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

    def rejected(self, key: str, size: int, reason: Any) -> None:
        """A payload that did not decode: a text row under ``rejected/<key>``."""
        self._text(f"rejected/{part(key)}", self.clock_ns, f"{size} bytes: {reason}", "WARN")

    def error(self, key: str, e: BaseException, msg: Any) -> None:
        """A message :meth:`message` failed on: a text row under ``errors/<key>``."""
        self._text(f"errors/{part(key)}", self.clock_ns, f"{type(e).__name__}: {e}: {msg!r}"[:4000], "ERROR")

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
                frames = {} if rows[0][1] is None else {"parent_frame": [r[0] for r in rows],
                                                        "child_frame": [r[1] for r in rows]}
                cols = rr.Transform3D.columns(translation=a[:, :3], quaternion=a[:, 3:], **frames)
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
