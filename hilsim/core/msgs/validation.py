"""Validation of decoded messages: what :func:`hilsim.core.msgs.decode` checks beyond the CDR layout.

Every float anywhere in a message must be finite (except where ROS gives inf a meaning), and
the arrays of a JointState, JointTrajectory or MoveGoal must agree in size (with the robot's
joint count when the receiver knows it). A failure is a :class:`BadMessage` with a one-line reason.
"""

import dataclasses
import math
from typing import Any

from pycdr2 import IdlStruct

from hilsim.core.msgs.action import MoveGoal
from hilsim.core.msgs.builtin import Clock, ns_of
from hilsim.core.msgs.geometry import OccupancyGrid
from hilsim.core.msgs.sensor import Imu, JointState
from hilsim.core.msgs.trajectory import JointTrajectory


class BadMessage(ValueError):
    """A payload that is not a valid message of the expected type."""


_FIELDS: dict[type, tuple[str, ...]] = {}
_NO_FLOAT_CHECK = {"LaserScan": ("ranges", "intensities")}  # inf = no return, by ROS convention


def _fields(cls: type) -> tuple[str, ...]:
    f = _FIELDS.get(cls)
    if f is None:
        skip = _NO_FLOAT_CHECK.get(cls.__name__, ())
        f = _FIELDS[cls] = tuple(x.name for x in dataclasses.fields(cls) if x.name not in skip)
    return f


def _check_floats(obj: Any, path: str) -> None:
    """Reject NaN/inf anywhere in a message (the path is built only when something is wrong)."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise BadMessage(f"{path} is not finite ({obj})")
    elif isinstance(obj, list):
        if not obj or isinstance(obj[0], str | int | bool):
            return
        if isinstance(obj[0], float):
            # one sum is far cheaper than a test per element; NaN and inf survive a sum
            if not math.isfinite(sum(obj)):
                for v in obj:
                    if not math.isfinite(v):
                        raise BadMessage(f"{path} contains a non-finite value ({v})")
        else:
            for i, o in enumerate(obj):
                _check_floats(o, f"{path}[{i}]")
    elif hasattr(obj, "__dataclass_fields__"):
        for name in _fields(type(obj)):
            _check_floats(getattr(obj, name), f"{path}.{name}" if path else name)


def _floats_of_joint_state(m: Any) -> bool:
    return math.isfinite(sum(m.position) + sum(m.velocity) + sum(m.effort))


def _floats_of_imu(m: Any) -> bool:
    o, a, g = m.orientation, m.angular_velocity, m.linear_acceleration
    return math.isfinite(o.x + o.y + o.z + o.w + a.x + a.y + a.z + g.x + g.y + g.z + sum(m.orientation_covariance)
                         + sum(m.angular_velocity_covariance) + sum(m.linear_acceleration_covariance))


# the per-step types: every float they have, summed at once (NaN and inf survive a sum); only a
# message that fails goes through the general walk, which names the field
_QUICK: dict[type, Any] = {JointState: _floats_of_joint_state, Imu: _floats_of_imu, Clock: lambda m: True}


def validate(msg: IdlStruct, *, n_joints: int | None = None) -> None:
    quick = _QUICK.get(type(msg))
    if quick is None or not quick(msg):
        _check_floats(msg, "")
    if isinstance(msg, JointState):
        n = len(msg.name)
        if n_joints is not None and n != n_joints:
            raise BadMessage(f"JointState has {n} names, expected {n_joints}")
        for fname in ("position", "velocity", "effort"):
            k = len(getattr(msg, fname))
            if k not in (0, n):
                raise BadMessage(f"JointState.{fname} has {k} values for {n} names")
    elif isinstance(msg, JointTrajectory):
        n = len(msg.joint_names)
        if n_joints is not None and msg.points and n != n_joints:
            raise BadMessage(f"JointTrajectory has {n} joint names, expected {n_joints}")
        last = -1
        for i, p in enumerate(msg.points):
            if len(p.positions) != n:
                raise BadMessage(f"JointTrajectory.points[{i}] has {len(p.positions)} positions for {n} joints")
            for fname in ("velocities", "accelerations", "effort"):
                if len(getattr(p, fname)) not in (0, n):
                    raise BadMessage(f"JointTrajectory.points[{i}].{fname} has the wrong size")
            t = ns_of(p.time_from_start)
            if t <= last:
                raise BadMessage(f"JointTrajectory.points[{i}].time_from_start is not increasing")
            last = t
    elif isinstance(msg, MoveGoal):
        if msg.target_kind not in ("joints", "pose"):
            raise BadMessage(f"MoveGoal.target_kind is {msg.target_kind!r}, expected 'joints' or 'pose'")
        if msg.target_kind == "joints":
            if n_joints is not None and len(msg.joint_positions) != n_joints:
                raise BadMessage(f"MoveGoal has {len(msg.joint_positions)} joint positions, expected {n_joints}")
            if msg.joint_names and len(msg.joint_names) != len(msg.joint_positions):
                raise BadMessage("MoveGoal.joint_names and joint_positions differ in length")
        if msg.planning_time < 0:
            raise BadMessage("MoveGoal.planning_time is negative")
    elif isinstance(msg, OccupancyGrid):
        if len(msg.data) != msg.info.width * msg.info.height:
            raise BadMessage(
                f"OccupancyGrid has {len(msg.data)} cells for {msg.info.width}x{msg.info.height}"
            )
        if msg.info.resolution <= 0 and msg.data:
            raise BadMessage("OccupancyGrid.info.resolution is not positive")
