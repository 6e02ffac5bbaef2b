"""The default layout of the Rerun viewer for a hilsim recording (stored in the ``.rrd``).

Left: the robot in 3D (with the planned tool paths) above the text logs; right: tabs with one
plot per joint and quantity (position, velocity, effort), the IMU, health and lockstep sync.
Entity paths are those of :mod:`hilsim.rerun_rows`.

Importing this module imports rerun, after turning its analytics off.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from hilsim.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun.blueprint as rrb  # noqa: E402

from hilsim.rerun_rows import part  # noqa: E402

QUANTITIES = ("position", "velocity", "effort")


def blueprint(joints: Iterable[str], robot_frame: str | None) -> rrb.Blueprint:
    """The layout for a robot with these moving joints; ``robot_frame`` (the URDF root link) is
    None when there is no robot model, and then there is no 3D view."""
    joints = list(joints)
    left: list[Any] = []
    if robot_frame is not None:
        left.append(
            rrb.Spatial3DView(
                name="robot",
                origin="/",
                contents=["/robot/**", "/joint_trajectory/tool_path", "/planner/path/tool_path"],
                spatial_information=rrb.archetypes.SpatialInformation(target_frame=robot_frame),
            )
        )
    left.append(rrb.TextLogView(name="log", origin="/", contents=["/log/**", "/planner/**", "/rejected/**"]))
    tabs: list[Any] = [
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
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*left), rrb.Tabs(*tabs), column_shares=[2, 3]))
