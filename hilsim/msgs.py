"""ROS 2 message types, CDR-encoded with pycdr2, plus validation of what arrives.

The field layout of each class follows the ROS 2 ``.msg`` definition, so a ROS 2 node
(e.g. through rmw_zenoh or zenoh-bridge-ros2dds) decodes the bytes as the ROS type named
in ``typename``. A few hilsim-specific action messages (``hilsim_msgs/…``) follow the same
conventions.

:func:`decode` is the only way services turn bytes into messages: it rejects garbage,
truncated payloads, inconsistent array sizes and non-finite numbers with :class:`BadMessage`.
"""


import dataclasses
import math
import sys
import threading
from dataclasses import dataclass, field
from typing import Any, TypeVar

from pycdr2 import IdlStruct
from pycdr2._support import Buffer
from pycdr2.types import array, float32, float64, int8, int32, sequence, uint8, uint32

from hilsim import fastcdr

T = TypeVar("T", bound=IdlStruct)


class BadMessage(ValueError):
    """A payload that is not a valid message of the expected type."""


# ---------------------------------------------------------------- builtin / std / geometry
@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Duration(IdlStruct, typename="builtin_interfaces/msg/Duration"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Clock(IdlStruct, typename="rosgraph_msgs/msg/Clock"):
    clock: Time = field(default_factory=Time)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs/msg/Vector3"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Point(IdlStruct, typename="geometry_msgs/msg/Point"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs/msg/Quaternion"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs/msg/Pose"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs/msg/Twist"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class Transform(IdlStruct, typename="geometry_msgs/msg/Transform"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs/msg/TransformStamped"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs/msg/TFMessage"):
    transforms: sequence[TransformStamped] = field(default_factory=list)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs/msg/PoseWithCovariance"):
    pose: Pose = field(default_factory=Pose)
    covariance: array[float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs/msg/TwistWithCovariance"):
    twist: Twist = field(default_factory=Twist)
    covariance: array[float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Odometry(IdlStruct, typename="nav_msgs/msg/Odometry"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


# ---------------------------------------------------------------- sensor_msgs
@dataclass
class JointState(IdlStruct, typename="sensor_msgs/msg/JointState"):
    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)


@dataclass
class Imu(IdlStruct, typename="sensor_msgs/msg/Imu"):
    header: Header = field(default_factory=Header)
    orientation: Quaternion = field(default_factory=Quaternion)
    orientation_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    angular_velocity: Vector3 = field(default_factory=Vector3)
    angular_velocity_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    linear_acceleration: Vector3 = field(default_factory=Vector3)
    linear_acceleration_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)


@dataclass
class NavSatStatus(IdlStruct, typename="sensor_msgs/msg/NavSatStatus"):
    status: int8 = 0
    service: uint8 = 1


@dataclass
class NavSatFix(IdlStruct, typename="sensor_msgs/msg/NavSatFix"):
    header: Header = field(default_factory=Header)
    status: NavSatStatus = field(default_factory=NavSatStatus)
    latitude: float64 = 0.0
    longitude: float64 = 0.0
    altitude: float64 = 0.0
    position_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    position_covariance_type: uint8 = 0


@dataclass
class LaserScan(IdlStruct, typename="sensor_msgs/msg/LaserScan"):
    header: Header = field(default_factory=Header)
    angle_min: float32 = 0.0
    angle_max: float32 = 0.0
    angle_increment: float32 = 0.0
    time_increment: float32 = 0.0
    scan_time: float32 = 0.0
    range_min: float32 = 0.0
    range_max: float32 = 0.0
    ranges: sequence[float32] = field(default_factory=list)
    intensities: sequence[float32] = field(default_factory=list)


# ---------------------------------------------------------------- trajectory_msgs
@dataclass
class JointTrajectoryPoint(IdlStruct, typename="trajectory_msgs/msg/JointTrajectoryPoint"):
    positions: sequence[float64] = field(default_factory=list)
    velocities: sequence[float64] = field(default_factory=list)
    accelerations: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)
    time_from_start: Duration = field(default_factory=Duration)


@dataclass
class JointTrajectory(IdlStruct, typename="trajectory_msgs/msg/JointTrajectory"):
    """header.stamp is the sim time at which the first point applies; an empty
    trajectory (no points) means: stop and hold the current position (ROS convention)."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    points: sequence[JointTrajectoryPoint] = field(default_factory=list)


# ---------------------------------------------------------------- diagnostics / logging
@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs/msg/KeyValue"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs/msg/DiagnosticStatus"):
    level: uint8 = 0  # OK=0 WARN=1 ERROR=2 STALE=3
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs/msg/DiagnosticArray"):
    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


@dataclass
class Log(IdlStruct, typename="rcl_interfaces/msg/Log"):
    stamp: Time = field(default_factory=Time)
    level: uint8 = 20  # DEBUG=10 INFO=20 WARN=30 ERROR=40 FATAL=50
    name: str = ""
    msg: str = ""
    file: str = ""
    function: str = ""
    line: uint32 = 0


# ---------------------------------------------------------------- parameters (live gains)
@dataclass
class Parameter(IdlStruct, typename="hilsim_msgs/msg/Parameter"):
    """A named float parameter, e.g. ``joint_2.kp``."""

    name: str = ""
    value: float64 = 0.0


@dataclass
class SetParameters(IdlStruct, typename="hilsim_msgs/srv/SetParameters_Request"):
    parameters: sequence[Parameter] = field(default_factory=list)


@dataclass
class SetParametersResult(IdlStruct, typename="rcl_interfaces/msg/SetParametersResult"):
    successful: bool = False
    reason: str = ""


# ---------------------------------------------------------------- move action (planner)
@dataclass
class MoveGoal(IdlStruct, typename="hilsim_msgs/action/Move_Goal"):
    """Goal of the planner's move action. ``target_kind`` is ``joints`` (``joint_positions``)
    or ``pose`` (``pose`` of the tool in the world frame; ``use_orientation`` says whether
    its orientation counts). Zero ``planning_time`` means the service default."""

    goal_id: str = ""
    target_kind: str = "joints"
    joint_names: sequence[str] = field(default_factory=list)
    joint_positions: sequence[float64] = field(default_factory=list)
    pose: Pose = field(default_factory=Pose)
    use_orientation: bool = False
    planner: str = ""
    planning_time: float64 = 0.0
    execute: bool = True


@dataclass
class GoalResponse(IdlStruct, typename="hilsim_msgs/action/Move_GoalResponse"):
    goal_id: str = ""
    accepted: bool = False
    reason: str = ""


@dataclass
class CancelRequest(IdlStruct, typename="hilsim_msgs/action/Move_Cancel"):
    goal_id: str = ""


@dataclass
class MoveFeedback(IdlStruct, typename="hilsim_msgs/action/Move_Feedback"):
    header: Header = field(default_factory=Header)
    goal_id: str = ""
    state: str = ""  # planning | executing | settling
    progress: float64 = 0.0


@dataclass
class MoveResult(IdlStruct, typename="hilsim_msgs/action/Move_Result"):
    header: Header = field(default_factory=Header)
    goal_id: str = ""
    success: bool = False
    error_code: int32 = 0
    message: str = ""
    trajectory: JointTrajectory = field(default_factory=JointTrajectory)
    planning_time: float64 = 0.0
    execution_error: sequence[float64] = field(default_factory=list)
    planner: str = ""


# error codes of MoveResult (MoveIt-like)
SUCCESS = 1
FAILURE = 99999
PLANNING_FAILED = -1
INVALID_GOAL = -2
TIMED_OUT = -6
CANCELED = -7
CONTROL_FAILED = -4
GOAL_IN_COLLISION = -10
GOAL_OUT_OF_LIMITS = -11
NO_IK_SOLUTION = -31


# ---------------------------------------------------------------- time helpers
def stamp(ns: int) -> Time:
    """Sim time in integer nanoseconds -> ROS Time."""
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def ns_of(t: Time | Duration) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def seconds(t: Time | Duration) -> float:
    return int(t.sec) + int(t.nanosec) * 1e-9


def duration(s: float) -> Duration:
    ns = round(s * 1e9)
    return Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(ns: int, frame_id: str = "") -> Header:
    return Header(stamp=stamp(ns), frame_id=frame_id)


# ---------------------------------------------------------------- encode / decode / validate
_local = threading.local()


def _buffer() -> Buffer:
    # pycdr2 encodes every message of a type through one shared buffer by default: threads of
    # one process (zenoh callbacks, health, workers) would corrupt each other's bytes.
    buf = getattr(_local, "buf", None)
    if buf is None:
        buf = _local.buf = Buffer()
    return buf


def encode(msg: IdlStruct) -> bytes:
    fast = _FAST_ENCODE.get(type(msg))
    if fast is not None:
        return fast(msg)
    return msg.serialize(buffer=_buffer())


def encode_reference(msg: IdlStruct) -> bytes:
    """pycdr2's encoding, bypassing the fast path (the reference the fast path is tested against)."""
    return msg.serialize(buffer=_buffer())


def decode(cls: type[T], payload: bytes, *, n_joints: int | None = None) -> T:
    """Decode and validate; raise :class:`BadMessage` with a one-line reason.

    ``n_joints``: for JointState / JointTrajectory, the number of joints expected.
    """
    data = bytes(payload)
    if len(data) < 4:
        # pycdr2 would read an empty buffer as all zeros
        raise BadMessage(f"payload of {len(data)} bytes has no CDR encapsulation header")
    fast = _FAST_DECODE.get(cls)
    try:
        if fast is not None and data[:4] == _LE:
            msg, used = fast(data)
        else:
            buf = Buffer(data, align_offset=4)  # the 4-byte encapsulation header precedes the body
            msg = cls.__idl__.deserialize(buf)  # type: ignore[attr-defined]
            used = buf.tell()
    except Exception as e:  # struct.error, UnicodeDecodeError, IndexError, ValueError, …
        raise BadMessage(f"not a valid {cls.__name__} CDR payload ({len(data)} bytes): {e}") from e
    # More than alignment padding left over means the payload was another (longer) message.
    if len(data) - used >= 4:
        raise BadMessage(f"payload has {len(data)} bytes, a {cls.__name__} of this content has {used}")
    validate(msg, n_joints=n_joints)
    return msg


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


def validate(msg: IdlStruct, *, n_joints: int | None = None) -> None:
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


def to_dict(msg: Any) -> Any:
    """Plain data (for JSON output of ``hilsim topic echo --json``)."""
    if dataclasses.is_dataclass(msg):
        return {f.name: to_dict(getattr(msg, f.name)) for f in dataclasses.fields(msg)}
    if isinstance(msg, list):
        return [to_dict(v) for v in msg]
    if isinstance(msg, float) and not math.isfinite(msg):
        return str(msg)
    return msg


def type_name(cls: type) -> str:
    return cls.__dict__.get("__idl_typename__", cls.__name__).replace("::", "/")


_LE = fastcdr.HEADER_LE
_FAST_ENCODE, _FAST_DECODE = fastcdr.build(sys.modules[__name__])


def _prepare_all() -> None:
    """Build pycdr2's per-type machinery now: its lazy first-use set-up is not thread-safe."""
    for obj in list(globals().values()):
        if isinstance(obj, type) and issubclass(obj, IdlStruct) and obj is not IdlStruct:
            obj.deserialize(encode_reference(obj()))


_prepare_all()
