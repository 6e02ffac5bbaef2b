"""The rover's rows: odometry, ``tf``, laser scans, GPS fixes, the occupancy grid and the plan, the
world's static scene, and the trails that grow with sim time (:class:`_Track`).

Entity paths (``robots/<robot>/`` in front for robots other than the scenario's; trails, tracks
and the chassis box only for the scenario's robot):

- ``tf/<child frame>``: Transform3D parent → child from ``tf`` (every 10 ms of sim time; a
  transform that did not change is not repeated); a fixed-base robot: ``tf/<root link>`` from the
  world model, static
- ``odometry/<q>/<truth|odom>``: Scalars of ``truth/odom`` and ``odom``; q = x, y, z, yaw (in the
  world) and vx, vy, wz (in the chassis frame)
- ``paths/<truth|odom>/<k>``: LineStrips3D, the trail in the world (a point every 100 ms);
  ``paths/gps/<k>``: Points3D of the GPS fixes in the world (with a datum), at the chassis' true height
- ``odom/estimate``: Boxes3D, the chassis where the odometry puts it
- ``geo/gps/<k>``, ``geo/<truth|odom>/<k>``: GeoPoints of ``gps/fix``; GeoLineStrings of the truth
  and odometry trails (with a datum); ``gps/fix/<field>`` Scalars as any message
  (:mod:`hilsim.record.rows.generic`)
- ``scan`` (any LaserScan topic): Points3D of the finite ranges, in the scan's frame
- ``map`` (any OccupancyGrid topic): a textured quad (``map/status``: TextLog of a grid not drawn);
  ``plan`` (any nav_msgs/Path topic): LineStrips3D, ``plan/summary`` TextLog
- ``world/<geom>``: the world's static geometry (``Scene.log_static``), static, frame ``world``

The odometry (``odom``, frame ``odom``) is drawn in the world with its frame where the rover
started, as a robot's ``odom`` frame starts where the robot is: the free base's pose in the world
model (:attr:`Scene.base_start`); without a scene, the first ``truth/odom`` if it came before the
first ``odom``, else the world's origin.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.geometry import yaw_of
from hilsim.record.rows.common import COLOURS, MODEL_PERIOD_NS, TIMELINE, WORLD_FRAME, part, rr, streams
from hilsim.record.rows.generic import GenericRows
from hilsim.sim.kinematics import RobotModel
from hilsim.sim.scene import Scene

TRACK_PERIOD_NS = 100_000_000  # a point of a trail (truth, odometry) every 100 ms of sim time
TRACK_BLOCK = 100  # points per trail entity (see _Track)
GRID_TEXTURE_MAX = 4096  # cells per side of an occupancy grid's texture (larger grids: max-pooled)
GRID_LIFT = 0.01  # [m] the grid's quad above its origin, so it is not hidden in the floor
PATH_LIFT = 0.05  # [m] a plan drawn above the grid
ODOM_SOURCES = {"truth/odom": "truth", "odom": "odom"}
ODOM_QUANTITIES = ("x", "y", "z", "yaw", "vx", "vy", "wz")  # pose in the world, twist in the chassis frame


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


class MobileRows(GenericRows):
    """The rover rows' methods of :class:`~hilsim.record.rows.writer.RowWriter`."""

    model: RobotModel | None
    scene: Scene | None
    _last_tf_ns: dict[str, int]
    _posed: set[str]
    _tf_last: dict[str, tuple[Any, ...]]
    _tf_rows: dict[str, list[tuple[Any, ...]]]
    _tf_times: dict[str, list[int]]
    _odom_origin: tuple[float, float, float, float] | None
    _truth_z: float | None
    _tracks: dict[str, _Track]
    _ghost: tuple[list[int], list[list[float]], list[list[float]]]
    _last_ghost_ns: int | None
    _scans: dict[str, tuple[list[int], list[np.ndarray], list[str]]]
    _scan_dirs: dict[tuple[int, float, float], np.ndarray]

    def log_scene(self) -> None:
        """The world's static geometry, where a fixed-base robot stands in it, and the style of the
        entities the rover's messages fill (static). Raises whatever rerun raises."""
        sc = self.scene
        if sc is None:
            return
        rec = self.rec
        for r in streams(rec):
            sc.log_static(r, WORLD_FRAME)
        if sc.root_pose is not None and self.model is not None:
            pos, quat = sc.root_pose
            rec.log(f"tf/{part(self.model.root)}", rr.Transform3D(
                translation=pos, quaternion=quat, parent_frame=WORLD_FRAME, child_frame=self.model.root), static=True)
        rec.log("scan", rr.Points3D.from_fields(colors=[COLOURS["scan"]], radii=[0.04]), static=True)
        if sc.base_box is not None:
            rec.log("odom/estimate", rr.Boxes3D.from_fields(
                half_sizes=[sc.base_box[1]], colors=[COLOURS["odom"]], fill_mode="majorwireframe"),
                rr.CoordinateFrame(WORLD_FRAME), static=True)

    # ------------------------------------------------------------------ the rover
    def _frame(self, root: str, robot: str, frame: str) -> str:
        """A frame id of ``robot`` as a Rerun frame: another robot's frames get its name in front."""
        return frame if not root or frame == WORLD_FRAME else f"{robot}:{frame}"

    def _tf(self, root: str, robot: str, msg: msgs.TFMessage) -> None:
        if not msg.transforms:
            return
        first = msg.transforms[0]
        t = msgs.ns_of(first.header.stamp)
        last = self._last_tf_ns.get(first.child_frame_id)
        if last is not None and 0 <= t - last < MODEL_PERIOD_NS:
            return  # the cheap path: four of five physics steps
        self._last_tf_ns[first.child_frame_id] = t
        for tr in msg.transforms:
            tt, r = tr.transform.translation, tr.transform.rotation
            if not root and tr.child_frame_id in self._posed:  # posed from the truth's joint states already
                parent = child = None
            else:
                parent, child = (self._frame(root, robot, tr.header.frame_id),
                                 self._frame(root, robot, tr.child_frame_id))
            row = (parent, child, tt.x, tt.y, tt.z, r.x, r.y, r.z, r.w)
            entity = f"{root}tf/{part(tr.child_frame_id)}"
            if self._tf_last.get(entity) == row:
                continue  # a sensor's frame on the chassis: written once
            self._tf_last[entity] = row
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
