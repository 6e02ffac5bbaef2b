"""The default layout of the Rerun viewer for a hilsim recording (stored in the ``.rrd``).

Left: the 3D view (the world's static geometry, the robot, and for a mobile robot its laser scan,
the trails of the truth and of the odometry, the GPS fixes, the chassis where the odometry puts
it, the occupancy grid and the planned path; for the arm the planned tool paths) above the text
logs. Right: tabs; for a mobile robot first the odometry against the truth (x, y, yaw and the
body twist) and, in a world with a geodetic datum, the map (GPS fixes and the truth and odometry
trails on Rerun's map view); then one plot per joint and quantity (position, velocity, effort),
the IMU, health and lockstep sync. Entity paths are those of :mod:`hilsim.record.rows`.

The map view draws OpenStreetMap tiles under the tracks, which the viewer fetches from the
network when that tab is shown; it is not the tab shown first.

Importing this module imports rerun, after turning its analytics off.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from hilsim.core.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun.blueprint as rrb  # noqa: E402

from hilsim.record.rows import ODOM_QUANTITIES, WORLD_FRAME, part  # noqa: E402
from hilsim.sim.kinematics import RobotModel  # noqa: E402
from hilsim.sim.scene import Scene  # noqa: E402

QUANTITIES = ("position", "velocity", "effort")
OVERVIEW_RADIUS = 15.0  # [m] a mobile robot's 3D view frames the static geometry this close to its start
# what the 3D view shows (entities of hilsim.record.rows)
SPATIAL_CONTENTS = [
    "/world/**", "/robot/**", "/joint_trajectory/tool_path", "/planner/joint_trajectory/tool_path",
    "/planner/path/tool_path", "/scan", "/paths/**", "/odom/estimate", "/map", "/plan",
]


def blueprint(joints: Iterable[str], robot_frame: str | None, scene: Scene | None = None) -> rrb.Blueprint:
    """The layout for a robot with these moving joints. ``robot_frame`` (the URDF root link) is
    None when there is no robot model; ``scene`` the world's geometry (the 3D view is then in the
    world frame), None if it could not be read. Without either there is no 3D view."""
    joints = list(joints)
    mobile = scene is not None and scene.base is not None
    left: list[Any] = []
    frame = WORLD_FRAME if scene is not None else robot_frame
    if frame is not None:
        eye = None
        if mobile:
            eye = _overview(scene)  # type: ignore[arg-type]
        elif scene is not None and scene.root_pose is not None:  # an arm: close to it, not the whole floor
            x, y, z = (float(v) for v in scene.root_pose[0])
            eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=(x + 1.2, y - 1.0, z + 0.7),
                                    look_target=(x + 0.1, y, z + 0.1), eye_up=(0.0, 0.0, 1.0))
        left.append(
            rrb.Spatial3DView(
                name="world" if scene is not None else "robot",
                origin="/",
                contents=SPATIAL_CONTENTS,
                spatial_information=rrb.archetypes.SpatialInformation(target_frame=frame),
                eye_controls=eye,
            )
        )
    left.append(rrb.TextLogView(name="log", origin="/", contents=[
        "/log/**", "/planner/**", "/navigator/**", "/task/**", "/rejected/**", "/errors/**"]))
    tabs: list[Any] = []
    if mobile:
        tabs.append(rrb.Grid(
            *(rrb.TimeSeriesView(name=f"{q}: truth, odom", origin=f"/odometry/{q}")
              for q in ODOM_QUANTITIES if q != "z"),
            name="odometry",
        ))
        if scene is not None and scene.datum is not None:
            tabs.append(rrb.MapView(name="map", origin="/geo", zoom=18.0))
    tabs += [
        rrb.Grid(
            *(rrb.TimeSeriesView(name=f"{j} {q}", origin=f"/joints/{part(j)}/{q}") for j in joints),
            name=q,
        )
        for q in QUANTITIES
    ]
    tabs += [
        rrb.TimeSeriesView(name="imu", origin="/imu"),
        rrb.TimeSeriesView(name="health", origin="/health"),
        rrb.TimeSeriesView(name="sync", origin="/sync"),
    ]
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*left, row_shares=[3, 1] if len(left) == 2 else None),
                                        rrb.Tabs(*tabs), column_shares=[3, 2] if mobile else [2, 3]))


def default_blueprint(model: RobotModel | None, scene: Scene | None) -> rrb.Blueprint:
    """The layout the recorder stores for a robot model and a world scene (either may be None)."""
    if model is None:
        return blueprint([], None, scene)
    return blueprint(model.joints, model.root, scene)


def _overview(scene: Scene) -> rrb.EyeControls3D:
    """A camera over where a mobile robot drives: the static geometry within OVERVIEW_RADIUS of its
    start (the whole of the indoor flat; the rocks, crates and slope around the outdoor start, not
    buildings 40 m away), seen from behind the start and above, at 40°."""
    x0, y0 = scene.base_start[:2] if scene.base_start is not None else (0.0, 0.0)
    near = [g for g in scene.geoms if g.kind != "plane" and math.hypot(g.pos[0] - x0, g.pos[1] - y0) <= OVERVIEW_RADIUS]
    if near:
        lo = np.min([g.pos[:2] - g.half_extent[:2] for g in near] + [[x0, y0]], axis=0)
        hi = np.max([g.pos[:2] + g.half_extent[:2] for g in near] + [[x0, y0]], axis=0)
    else:
        lo, hi = np.array([x0 - 5.0, y0 - 5.0]), np.array([x0 + 5.0, y0 + 5.0])
    cx, cy = (lo + hi) / 2
    d = float(np.linalg.norm(hi - lo))  # the diagonal: at this distance the area fills the view
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=(cx - 0.55 * d, cy - 0.45 * d, 0.65 * d),
                             look_target=(cx, cy, 0.0), eye_up=(0.0, 0.0, 1.0))
