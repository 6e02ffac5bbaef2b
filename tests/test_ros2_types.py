"""hilsim.core.ros2.types: the ROS 2 definitions, their RIHS01 hashes, MCAP schemas and DDS names.

Checked against published hashes, against rosbags (an independent implementation of the .msg parser
and of RIHS01 for messages), against mcap_ros2's reader, and against hilsim's own pycdr2 classes.
"""

from __future__ import annotations

import dataclasses
import io
import typing
import warnings
from typing import Any

import pytest
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

from hilsim.core.ros2 import types

try:
    from hilsim.core import msgs
except ImportError:  # before the restructuring
    from hilsim import msgs  # type: ignore[no-redef]

from pycdr2 import IdlStruct
from pycdr2.types import array as cdr_array
from pycdr2.types import sequence as cdr_sequence

with warnings.catch_warnings():  # mcap_ros2.reader warns on import that it will move
    warnings.simplefilter("ignore", DeprecationWarning)
    from mcap_ros2.reader import read_ros2_messages

JAZZY = get_typestore(Stores.ROS2_JAZZY)

# ------------------------------------------------------------------------------------ published
PUBLISHED = {
    # rmw_zenoh's design doc and the type hashes of the ROS 2 Jazzy binaries
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "rosgraph_msgs/msg/Clock": "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564",
    "builtin_interfaces/msg/Time": "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    "action_msgs/msg/GoalStatusArray": "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e",
    "action_msgs/srv/CancelGoal_Request": "RIHS01_3d3c84653c1f96918086887e1dcb236faec88b81a5b14fd4cf4840065bcdf8af",
}


@pytest.mark.parametrize(("name", "expected"), sorted(PUBLISHED.items()))
def test_published_hashes(name: str, expected: str) -> None:
    assert types.type_hash(name) == expected


def _with_examples() -> types.TypeRegistry:
    reg = types._default_registry()
    reg.add_srv("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n")
    reg.add_action("example_interfaces/action/Fibonacci", "int32 order\n---\nint32[] sequence\n---\nint32[] sequence\n")
    return reg


def test_service_and_action_hashes_match_published_values() -> None:
    """A service's hash covers Request, Response and the synthesised Event (with
    service_msgs/ServiceEventInfo): rmw_zenoh's design doc gives the key of add_two_ints; the
    Fibonacci action parts are those seen in rmw_zenoh keys on Jazzy."""
    reg = _with_examples()
    assert (
        reg.type_hash("example_interfaces/srv/AddTwoInts")
        == "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    )
    fib = "example_interfaces/action/Fibonacci"
    assert (
        reg.type_hash(f"{fib}_SendGoal_Request")
        == "RIHS01_3d088942b413247db536576f0286768c6be8fcd5d0c9a5d544f359fba090a238"
    )
    assert (
        reg.type_hash(f"{fib}_GetResult_Request")
        == "RIHS01_c8a4f5e7d13b81286ee1043e2ecd084281cecf1ff06aaa799464f5f15479f003"
    )
    assert (
        reg.type_hash(f"{fib}_FeedbackMessage")
        == "RIHS01_c1de71afd52e49a89c53d8262366884185bc0a02f78ce051c4e46b0a7fe59bb2"
    )
    # the structure rosidl gives services and actions
    assert [f.name for f in reg.fields("example_interfaces/srv/AddTwoInts")] == [
        "request_message",
        "response_message",
        "event_message",
    ]
    event = reg.fields("example_interfaces/srv/AddTwoInts_Event")
    assert [(f.name, f.type, f.container, f.size) for f in event] == [
        ("info", "service_msgs/msg/ServiceEventInfo", "", 0),
        ("request", "example_interfaces/srv/AddTwoInts_Request", "bounded_sequence", 1),
        ("response", "example_interfaces/srv/AddTwoInts_Response", "bounded_sequence", 1),
    ]
    assert [f.name for f in reg.fields(fib)] == [
        "goal",
        "result",
        "feedback",
        "send_goal_service",
        "get_result_service",
        "feedback_message",
    ]
    assert reg.kind(fib) == "action" and reg.kind(f"{fib}_SendGoal") == "srv" and reg.kind(f"{fib}_Goal") == "msg"


# --------------------------------------------------------------------------------- vs. rosbags
def _rosbags_fields(fielddefs: Any) -> list[tuple[str, str, str, int, int]]:
    """rosbags' field list as (name, type, container, size, string bound)."""
    out = []
    for name, (node, arg) in fielddefs:
        container, size = "", 0
        if node == Nodetype.ARRAY:
            container, ((node, arg), size) = "array", arg
        elif node == Nodetype.SEQUENCE:
            (node, arg), size = arg
            container = "bounded_sequence" if size else "sequence"
        if node == Nodetype.NAME:
            out.append((name, arg, container, size, 0))
        else:
            base, bound = arg
            out.append((name, base, container, size, bound or 0))
    return out


def _ours(name: str, registry: types.TypeRegistry | None = None) -> list[tuple[str, str, str, int, int]]:
    flds = (registry or types.REGISTRY).fields(name)
    return [(f.name, f.type, f.container, f.size, f.string_bound) for f in flds]


OWN_MSGS = [n for n in types.known_types(("msg",)) if n.split("/")[0] in types.HILSIM_PACKAGES]
STANDARD_MSGS = [
    n for n in types.known_types(("msg",)) if n.split("/")[0] not in types.HILSIM_PACKAGES and n in JAZZY.fielddefs
]


def test_every_needed_standard_type_is_covered() -> None:
    needed = {
        "builtin_interfaces/msg/Time",
        "builtin_interfaces/msg/Duration",
        "std_msgs/msg/Header",
        "std_msgs/msg/String",
        "rosgraph_msgs/msg/Clock",
        "tf2_msgs/msg/TFMessage",
        "nav_msgs/msg/Odometry",
        "nav_msgs/msg/Path",
        "nav_msgs/msg/OccupancyGrid",
        "nav_msgs/msg/MapMetaData",
        "sensor_msgs/msg/JointState",
        "sensor_msgs/msg/Imu",
        "sensor_msgs/msg/LaserScan",
        "sensor_msgs/msg/NavSatFix",
        "sensor_msgs/msg/NavSatStatus",
        "trajectory_msgs/msg/JointTrajectory",
        "trajectory_msgs/msg/JointTrajectoryPoint",
        "diagnostic_msgs/msg/DiagnosticArray",
        "diagnostic_msgs/msg/DiagnosticStatus",
        "diagnostic_msgs/msg/KeyValue",
        "rcl_interfaces/msg/Log",
        "rcl_interfaces/msg/Parameter",
        "rcl_interfaces/msg/ParameterValue",
        "rcl_interfaces/msg/SetParametersResult",
        "rcl_interfaces/srv/SetParameters",
        "action_msgs/msg/GoalInfo",
        "action_msgs/msg/GoalStatus",
        "action_msgs/msg/GoalStatusArray",
        "action_msgs/srv/CancelGoal",
        "unique_identifier_msgs/msg/UUID",
        "control_msgs/action/FollowJointTrajectory",
        "control_msgs/action/FollowJointTrajectory_Goal",
        "control_msgs/action/FollowJointTrajectory_SendGoal",
        "control_msgs/action/FollowJointTrajectory_GetResult",
        "control_msgs/action/FollowJointTrajectory_FeedbackMessage",
        "control_msgs/msg/JointTolerance",
    } | {
        f"geometry_msgs/msg/{n}"
        for n in (
            "Point Quaternion Pose PoseStamped PoseWithCovariance Twist TwistWithCovariance Vector3 Transform "
            "TransformStamped"
        ).split()
    }
    assert needed <= set(types.known_types())
    # Jazzy's FollowJointTrajectory goal carries a MultiDOFJointTrajectory
    goal = {f.name: f.type for f in types.fields("control_msgs/action/FollowJointTrajectory_Goal")}
    assert goal["multi_dof_trajectory"] == "trajectory_msgs/msg/MultiDOFJointTrajectory"


@pytest.mark.parametrize("name", STANDARD_MSGS)
def test_standard_types_agree_with_rosbags(name: str) -> None:
    assert _ours(name) == _rosbags_fields(JAZZY.fielddefs[name][1])
    if name in CHAR_MSGS:
        # rosbags hashes .msg ``char`` as FIELD_TYPE_CHAR; rosidl turns ``char`` into an IDL uint8
        # (rosidl_adapter's MSG_TYPE_TO_IDL), which the published AddTwoInts service hash and what a
        # real ROS 2 participant announces for ros_discovery_info (below) confirm.
        store = get_typestore(Stores.EMPTY)
        for n in CHAR_MSGS[name]:
            store.register(_rosbags_types(n, types.definition(n).replace("char[16]", "uint8[16]")))
        assert types.type_hash(name) == store.hash_rihs01(name)
        return
    assert types.type_hash(name) == JAZZY.hash_rihs01(name)


# the types that hold a .msg ``char``, and what each needs registered (dependencies first)
_GID = ["rmw_dds_common/msg/Gid"]
CHAR_MSGS = {"service_msgs/msg/ServiceEventInfo": ["builtin_interfaces/msg/Time", "service_msgs/msg/ServiceEventInfo"],
             "rmw_dds_common/msg/Gid": _GID,
             "rmw_dds_common/msg/NodeEntitiesInfo": [*_GID, "rmw_dds_common/msg/NodeEntitiesInfo"],
             "rmw_dds_common/msg/ParticipantEntitiesInfo": [*_GID, "rmw_dds_common/msg/NodeEntitiesInfo",
                                                            "rmw_dds_common/msg/ParticipantEntitiesInfo"]}


def test_ros_discovery_info_has_the_hash_real_participants_announce() -> None:
    # the USER_DATA of a Kilted rclpy node's ros_discovery_info writer (rmw_fastrtps_cpp), as Cyclone's
    # discovery trace printed it: typehash=RIHS01_91a0…;
    assert types.type_hash("rmw_dds_common/msg/ParticipantEntitiesInfo") == (
        "RIHS01_91a0593bacdcc50ea9bdcf849a938b128412cc1ea821245c663bcd26f83c295e")


def test_rosbags_has_what_it_can() -> None:
    """Every standard message type rosbags' Jazzy store lacks is one it never ships (control_msgs)
    or a service / action part, checked through its definition text below."""
    absent = {
        n
        for n in types.known_types(("msg",))
        if n.split("/")[0] not in types.HILSIM_PACKAGES and n not in JAZZY.fielddefs
    }
    assert all(n.startswith("control_msgs/") or "/srv/" in n or "/action/" in n for n in absent), absent


def _rosbags_text(name: str) -> str:
    """The definition with nested types written in full: a synthesised part refers to action and
    service types, which a ``pkg/Name`` reference cannot name (rosbags resolves ``pkg/kind/Name``)."""
    suffix = {"": "", "array": "[{}]", "bounded_sequence": "[<={}]", "sequence": "[]"}
    return "".join(
        f"{f.type + suffix[f.container].format(f.size) if f.is_nested else f.msg_type()} {f.name}\n"
        for f in types.fields(name)
    )


def _rosbags_types(name: str, text: str) -> Any:
    """rosbags' parse of ``text`` as ``name`` (rosbags files a ``pkg/srv/X`` under ``pkg/srv/msg/X``)."""
    (defs,) = get_types_from_msg(text, name).values()
    return {name: defs}


def _rosbags_store_with(names: list[str]) -> Any:
    store = get_typestore(Stores.ROS2_JAZZY)
    for n in names:
        # our .msg text where it has only message references (rosbags resolves a bare name in
        # pkg/action/X.action to pkg/action/Name, rosidl to pkg/msg/Name), else the one with full names
        text = types.definition(n) if "/msg/" in n or n in OWN_MSGS else _rosbags_text(n)
        store.register(_rosbags_types(n, text))
    return store


# messages rosbags' store lacks whose hash does not depend on service_msgs/ServiceEventInfo (see above)
EXTRA_MSGS = [
    n
    for n in types.known_types(("msg",))
    if n not in JAZZY.fielddefs and n not in OWN_MSGS and not n.endswith("_Event")
]


# a service's _Event message holds service_msgs/ServiceEventInfo, whose char[16] rosbags hashes apart
# from rosidl (see above): those are checked through the service hashes against published values
@pytest.mark.parametrize("name", [n for n in OWN_MSGS if not n.endswith("_Event")] + EXTRA_MSGS)
def test_definitions_round_trip_through_rosbags(name: str) -> None:
    """rosbags parses our text into the same fields and hashes it to the same RIHS01."""
    deps = [n for n in [*types.REGISTRY.dependencies(name), name] if n not in JAZZY.fielddefs]
    store = _rosbags_store_with(deps)
    assert _ours(name) == _rosbags_fields(store.fielddefs[name][1])
    assert types.type_hash(name) == store.hash_rihs01(name)


def test_hilsim_types_have_own_package_hashes() -> None:
    for name in OWN_MSGS:
        assert types.type_hash(name).startswith("RIHS01_") and len(types.type_hash(name)) == 71


# ----------------------------------------------------------------------------------- parsing
def test_parser_details() -> None:
    flds, consts = types.parse_msg(
        "# comment\nint8 A =  -1  # c\nstring S=a # b\nint8 status -2\nstring<=5[<=3] names\n"
        "Pose\tp\ngeometry_msgs/Point   q\nfoo/action/X_Goal g\nuint8[16] uuid\n",
        "geometry_msgs",
    )
    assert consts == (types.Constant("int8", "A", "-1"), types.Constant("string", "S", "a # b"))
    assert flds == (
        types.Field("status", "int8", default="-2"),
        types.Field("names", "string", "bounded_sequence", 3, 5),
        types.Field("p", "geometry_msgs/msg/Pose"),
        types.Field("q", "geometry_msgs/msg/Point"),
        types.Field("g", "foo/action/X_Goal"),
        types.Field("uuid", "uint8", "array", 16),
    )
    assert [f.type_id() for f in flds] == [2, 117, 1, 1, 1, 51]
    with pytest.raises(ValueError):
        types.parse_msg("float64<=3 x\n", "p")
    with pytest.raises(ValueError):
        types.parse_msg("float64 x\nfloat64 x\n", "p")
    with pytest.raises(ValueError):
        types.parse_msg("float64\n", "p")


def test_empty_struct_gets_the_rosidl_placeholder_member() -> None:
    desc = types.type_description("rcl_interfaces/msg/ParameterType")
    assert desc["type_description"]["fields"] == [
        {
            "name": "structure_needs_at_least_one_member",
            "type": {"type_id": 3, "capacity": 0, "string_capacity": 0, "nested_type_name": ""},
        }
    ]
    assert types.type_hash("rcl_interfaces/msg/ParameterType") == JAZZY.hash_rihs01("rcl_interfaces/msg/ParameterType")


def test_unknown_type() -> None:
    with pytest.raises(KeyError):
        types.type_hash("std_msgs/msg/Nope")
    assert not types.is_known("std_msgs/msg/Nope")
    with pytest.raises(ValueError):
        types.full_definition("action_msgs/srv/CancelGoal")


# ------------------------------------------------------------------------------ MCAP schemas
def _read_back(data: bytes) -> list[Any]:
    return [m.ros_msg for m in read_ros2_messages(io.BytesIO(data))]


def test_full_definition_format() -> None:
    text = types.full_definition("nav_msgs/msg/Odometry")
    assert text.startswith("std_msgs/Header header\n")
    sections = text.split("=" * 80 + "\n")
    assert [s.splitlines()[0] for s in sections[1:]] == [
        f"MSG: {n}" for n in types.REGISTRY.dependencies("nav_msgs/msg/Odometry")
    ]
    assert "MSG: geometry_msgs/msg/Vector3" in sections[-1]


@pytest.mark.parametrize(
    ("name", "message"),
    [
        (
            "sensor_msgs/msg/JointState",
            {
                "header": {"stamp": {"sec": 3, "nanosec": 5}, "frame_id": "base"},
                "name": ["a", "b"],
                "position": [1.0, 2.0],
                "velocity": [0.5, -0.5],
                "effort": [],
            },
        ),
        (
            "nav_msgs/msg/Odometry",
            {
                "header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "odom"},
                "child_frame_id": "base_link",
                "pose": {
                    "pose": {"position": {"x": 1.0, "y": 2.0, "z": 0.0}, "orientation": {"w": 1.0}},
                    "covariance": [0.1] * 36,
                },
                "twist": {"twist": {"linear": {"x": 0.3}, "angular": {"z": -0.2}}, "covariance": [0.0] * 36},
            },
        ),
    ],
)
def test_full_definition_is_an_mcap_ros2msg_schema(name: str, message: dict[str, Any]) -> None:
    buf = io.BytesIO()
    writer = Ros2Writer(buf)
    schema = writer.register_msgdef(name, types.full_definition(name))
    writer.write_message("/t", schema, message, log_time=1, publish_time=1)
    writer.finish()
    (decoded,) = _read_back(buf.getvalue())
    if name == "sensor_msgs/msg/JointState":
        assert decoded.name == ["a", "b"] and list(decoded.position) == [1.0, 2.0]
        assert decoded.header.frame_id == "base" and decoded.header.stamp.nanosec == 5
    else:
        assert decoded.child_frame_id == "base_link" and decoded.pose.pose.position.y == 2.0
        assert list(decoded.pose.covariance) == [0.1] * 36 and decoded.twist.twist.angular.z == -0.2


def test_hilsim_bytes_decode_with_the_schema() -> None:
    """hilsim's own encoder and the MCAP schema agree on the wire (CDR payload recorded as is)."""
    samples = [
        msgs.JointState(header=msgs.header(7_000_000_123, "base"), name=["j1"], position=[0.25], velocity=[1.5]),
        msgs.Odometry(header=msgs.header(5, "odom"), child_frame_id="base_link"),
        msgs.Contacts(
            header=msgs.header(9, "world"),
            contacts=[msgs.Contact(body1="a", body2="b", geom1="g", geom2="h", depth=-0.001)],
        ),
        msgs.MoveResult(goal_id="g1", success=True, error_code=1, execution_error=[0.1, 0.2], planner="rrt"),
    ]
    buf = io.BytesIO()
    writer = McapWriter(buf)
    writer.start(profile="ros2", library="test")
    for i, sample in enumerate(samples):
        name = msgs.type_name(type(sample))
        sid = writer.register_schema(name, "ros2msg", types.full_definition(name).encode())
        cid = writer.register_channel(f"/t{i}", "cdr", sid)
        writer.add_message(cid, log_time=i, publish_time=i, data=msgs.encode(sample), sequence=i)
    writer.finish()
    decoded = _read_back(buf.getvalue())
    assert decoded[0].name == ["j1"] and list(decoded[0].velocity) == [1.5] and decoded[0].header.stamp.sec == 7
    assert decoded[1].child_frame_id == "base_link" and decoded[1].pose.pose.orientation.w == 1.0
    assert decoded[2].contacts[0].geom2 == "h" and decoded[2].contacts[0].depth == -0.001
    assert decoded[3].planner == "rrt" and list(decoded[3].execution_error) == [0.1, 0.2]


# ----------------------------------------------------------------------------------- DDS names
def test_dds_type_names() -> None:
    assert types.dds_type_name("sensor_msgs/msg/JointState") == "sensor_msgs::msg::dds_::JointState_"
    assert types.dds_type_name("std_msgs/String") == "std_msgs::msg::dds_::String_"
    assert types.dds_type_name("action_msgs/srv/CancelGoal") == "action_msgs::srv::dds_::CancelGoal_"
    assert types.dds_type_name("action_msgs/srv/CancelGoal_Request") == "action_msgs::srv::dds_::CancelGoal_Request_"
    assert (
        types.dds_type_name("control_msgs/action/FollowJointTrajectory_SendGoal")
        == "control_msgs::action::dds_::FollowJointTrajectory_SendGoal_"
    )
    assert (
        types.dds_type_name("control_msgs/action/FollowJointTrajectory_FeedbackMessage")
        == "control_msgs::action::dds_::FollowJointTrajectory_FeedbackMessage_"
    )
    with pytest.raises(ValueError):
        types.dds_type_name("JointState")


# ------------------------------------------------------------------------- hilsim's classes
def _message_classes() -> list[type[IdlStruct]]:
    classes = {
        obj
        for obj in vars(msgs).values()
        if isinstance(obj, type) and issubclass(obj, IdlStruct) and obj is not IdlStruct
    }
    return sorted(classes, key=lambda c: msgs.type_name(c))


def _cdr_field(annotation: Any) -> tuple[str, str, int]:
    """A pycdr2 annotation as (msg type, container, size)."""
    if typing.get_origin(annotation) is typing.Annotated:
        base, meta = typing.get_args(annotation)[0], typing.get_args(annotation)[1]
        if isinstance(meta, str):
            return meta, "", 0
        if isinstance(meta, cdr_array):
            return _cdr_field(meta.subtype)[0], "array", meta.length
        if isinstance(meta, cdr_sequence):
            bound = meta.max_length or 0
            return _cdr_field(meta.subtype)[0], "bounded_sequence" if bound else "sequence", bound
        return _cdr_field(base)
    if annotation is str:
        return "string", "", 0
    if annotation is bool:
        return "bool", "", 0
    if isinstance(annotation, type) and issubclass(annotation, IdlStruct):
        return msgs.type_name(annotation), "", 0
    raise AssertionError(f"unexpected annotation {annotation!r}")


#: where a hilsim class's CDR layout differs from the ROS definition (a real wire difference)
KNOWN_DEVIATIONS: dict[tuple[str, str], tuple[str, str]] = {}  # none: every class is wire-identical to ROS
#: the same bytes under another name (no wire difference)
_WIRE_SAME = {"byte": "uint8", "char": "uint8", "float": "float32", "double": "float64"}


@pytest.mark.parametrize("cls", _message_classes(), ids=lambda c: msgs.type_name(c))
def test_hilsim_class_matches_its_definition(cls: type[IdlStruct]) -> None:
    name = msgs.type_name(cls)
    assert types.is_known(name), name
    assert types.kind(name) == "msg"
    ours = types.fields(name)
    assert [f.name for f in dataclasses.fields(cls)] == [f.name for f in ours]
    hints = typing.get_type_hints(cls, include_extras=True)
    deviations = {}
    for f in ours:
        got = _cdr_field(hints[f.name])
        want = (_WIRE_SAME.get(f.type, f.type), f.container, f.size)
        if got != want:
            deviations[(name, f.name)] = (got[0], want[0])
    assert deviations == {k: v for k, v in KNOWN_DEVIATIONS.items() if k[0] == name}


def test_every_hilsim_class_is_covered() -> None:
    names = {msgs.type_name(c) for c in _message_classes()}
    assert len(names) >= 40
    assert set(OWN_MSGS) <= names
