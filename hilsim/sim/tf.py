"""A robot's frames from its URDF, as ROS 2's robot_state_publisher gives them to tf2 and rviz2.

:class:`UrdfFrames` reads the URDF's joints once: every ``fixed`` joint is a static transform
(``/tf_static``, sent once, kept for late joiners), every moving joint (revolute, continuous,
prismatic) a transform of the joint's value (``/tf``): the joint's origin, then the rotation about
(or the shift along) its axis. Frame ids are the URDF's link names, so rviz2's RobotModel display,
given the same URDF on ``robot_description``, places every link. A fleet's robots prefix their
frames with ``<robot>/`` (one global tf tree, as multi-robot ROS 2 systems keep it).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from hilsim.core import msgs

MOVING = ("revolute", "continuous", "prismatic")

Quat = tuple[float, float, float, float]  # x, y, z, w


def quat_rpy(roll: float, pitch: float, yaw: float) -> Quat:
    """URDF's fixed-axis roll, pitch, yaw as a quaternion."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def quat_mul(a: Quat, b: Quat) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def rotate(q: Quat, v: tuple[float, float, float]) -> tuple[float, float, float]:
    x, y, z, w = q
    vx, vy, vz = v
    # v + 2w(q×v) + 2 q×(q×v)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    cx, cy, cz = 2 * cx, 2 * cy, 2 * cz
    return (vx + w * cx + y * cz - z * cy, vy + w * cy + z * cx - x * cz, vz + w * cz + x * cy - y * cx)


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rot: Quat
    axis: tuple[float, float, float]
    mimic: tuple[str, float, float] | None = None  # (leader joint, multiplier, offset): URDF <mimic>


def _floats(text: str | None, n: int, default: float) -> tuple[float, ...]:
    vals = [float(v) for v in (text or "").split()]
    return tuple(vals) if len(vals) == n else (default,) * n


def read_joints(urdf: Path) -> list[Joint]:
    out = []
    # the robot's own joints only: <transmission> (ros_control) and <gazebo> blocks hold <joint> elements too
    for j in ET.parse(urdf).getroot().findall("joint"):
        origin, axis = j.find("origin"), j.find("axis")
        xyz = _floats(origin.get("xyz") if origin is not None else None, 3, 0.0)
        rpy = _floats(origin.get("rpy") if origin is not None else None, 3, 0.0)
        ax = _floats(axis.get("xyz") if axis is not None else None, 3, 0.0)
        if not any(ax):
            ax = (1.0, 0.0, 0.0)  # URDF's default axis
        norm = math.sqrt(sum(a * a for a in ax))
        m = j.find("mimic")
        mimic = None if m is None else (m.get("joint", ""), float(m.get("multiplier", "1")),
                                         float(m.get("offset", "0")))
        out.append(Joint(j.get("name", ""), j.get("type", "fixed"), j.find("parent").get("link", ""),  # type: ignore[union-attr]
                         j.find("child").get("link", ""), xyz, quat_rpy(*rpy),  # type: ignore[union-attr, arg-type]
                         (ax[0] / norm, ax[1] / norm, ax[2] / norm), mimic))
    return out


class UrdfFrames:
    """The static and moving transforms of one robot's URDF."""

    def __init__(self, urdf: Path, prefix: str = "") -> None:
        self.urdf_text = Path(urdf).read_text()
        self.joints = read_joints(Path(urdf))
        self.prefix = prefix
        self.fixed = [j for j in self.joints if j.kind not in MOVING]
        self.moving = [j for j in self.joints if j.kind in MOVING]

    def _stamped(self, stamp_ns: int, j: Joint, xyz: tuple[float, float, float], rot: Quat) -> msgs.TransformStamped:
        return msgs.TransformStamped(
            header=msgs.header(stamp_ns, self.prefix + j.parent), child_frame_id=self.prefix + j.child,
            transform=msgs.Transform(translation=msgs.Vector3(x=xyz[0], y=xyz[1], z=xyz[2]),
                                     rotation=msgs.Quaternion(x=rot[0], y=rot[1], z=rot[2], w=rot[3])))

    def static(self, stamp_ns: int = 0) -> msgs.TFMessage:
        """Every fixed joint's transform (``/tf_static``)."""
        return msgs.TFMessage(transforms=[self._stamped(stamp_ns, j, j.xyz, j.rot) for j in self.fixed])

    def moving_transforms(self, stamp_ns: int, position: dict[str, float]) -> list[msgs.TransformStamped]:
        """The moving joints' transforms at the given joint values (joints without a value are left out;
        a mimic joint follows its leader, as robot_state_publisher has it)."""
        out = []
        for j in self.moving:
            q = position.get(j.name)
            if q is None and j.mimic is not None and j.mimic[0] in position:
                q = j.mimic[2] + j.mimic[1] * position[j.mimic[0]]
            if q is None:
                continue
            if j.kind == "prismatic":
                d = rotate(j.rot, (j.axis[0] * q, j.axis[1] * q, j.axis[2] * q))
                out.append(self._stamped(stamp_ns, j, (j.xyz[0] + d[0], j.xyz[1] + d[1], j.xyz[2] + d[2]), j.rot))
            else:
                s = math.sin(q / 2)
                turn = (j.axis[0] * s, j.axis[1] * s, j.axis[2] * s, math.cos(q / 2))
                out.append(self._stamped(stamp_ns, j, j.xyz, quat_mul(j.rot, turn)))
        return out
