"""Keys, messages and scenario validation: the contracts every service relies on."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys, UnknownKey, message_type, topic_name
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent


JOINT_STATE = ("sensor_msgs::msg::dds_::JointState_/"
               "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e")
CLOCK = "rosgraph_msgs::msg::dds_::Clock_/RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564"


def test_key_scheme_and_types() -> None:
    """rmw_zenoh's keys: <domain>/<namespace>/<topic>/<DDS type>/<type hash> (published hashes)."""
    k = Keys("lab2", "arm", 7)
    assert k.topic("joint_states") == f"7/arm/joint_states/{JOINT_STATE}"
    assert k.truth("imu").startswith("7/arm/truth/imu/sensor_msgs::msg::dds_::Imu_/RIHS01_")
    assert k.clock == f"7/clock/{CLOCK}"
    assert k.topic_name("gps/fix") == "/arm/gps/fix"
    assert Keys("x", "arm0", 0, "/lab/{robot}").topic("joint_states") == f"0/lab/arm0/joint_states/{JOINT_STATE}"
    assert message_type(k.clock) is msgs.Clock
    assert message_type(k.topic("gps/fix")) is msgs.NavSatFix
    assert message_type(k.health("physics")) is msgs.DiagnosticArray
    assert topic_name(k.topic("cmd_vel")) == "/arm/cmd_vel"
    with pytest.raises(UnknownKey):
        k.topic("jointstates")
    with pytest.raises(UnknownKey):
        message_type("7/arm/nope")
    with pytest.raises(UnknownKey):
        message_type("7/arm/nope/pkg::msg::dds_::Nope_/RIHS01_00")


def test_cdr_round_trip_matches_ros_layout() -> None:
    m = msgs.JointState(header=msgs.header(1_500_000_001, "world"), name=["a"], position=[1.0], velocity=[], effort=[])
    b = msgs.encode(m)
    # CDR little-endian encapsulation header, then Time{sec=1, nanosec=500000001}
    assert b[:4] == b"\x00\x01\x00\x00"
    assert int.from_bytes(b[4:8], "little") == 1 and int.from_bytes(b[8:12], "little") == 500_000_001
    assert msgs.decode(msgs.JointState, b, n_joints=1) == m
    assert msgs.ns_of(m.header.stamp) == 1_500_000_001


@pytest.mark.parametrize(
    "payload, why",
    [
        (b"garbage", "not a valid"),
        (msgs.encode(msgs.JointState(name=["a", "b"], position=[1.0, 2.0]))[:-6], "not a valid"),
        (msgs.encode(msgs.JointState(name=["a"], position=[math.nan])), "non-finite"),
        (msgs.encode(msgs.JointState(name=["a", "b"], position=[1.0])), "1 values for 2 names"),
        (msgs.encode(msgs.JointState(name=["a", "b", "c"], position=[1.0, 2, 3])), "expected 2"),
    ],
)
def test_bad_joint_states_are_rejected(payload: bytes, why: str) -> None:
    with pytest.raises(msgs.BadMessage, match=why):
        msgs.decode(msgs.JointState, payload, n_joints=2)


def test_trajectory_validation() -> None:
    p = msgs.JointTrajectoryPoint
    ok = msgs.JointTrajectory(joint_names=["a"], points=[p([0.0], time_from_start=msgs.duration(0.0)),
                                                         p([1.0], time_from_start=msgs.duration(0.5))])
    assert msgs.decode(msgs.JointTrajectory, msgs.encode(ok), n_joints=1) == ok
    back = msgs.JointTrajectory(joint_names=["a"], points=[p([0.0], time_from_start=msgs.duration(1.0)),
                                                           p([1.0], time_from_start=msgs.duration(0.5))])
    with pytest.raises(msgs.BadMessage, match="not increasing"):
        msgs.decode(msgs.JointTrajectory, msgs.encode(back))


def test_scenario_loads_and_resolves_paths() -> None:
    sc = load_scenario("arm")
    assert sc.world.model.is_absolute() and sc.world.model.exists()
    assert registry.lockstep_participants(sc) == {"controller": 1, "planner": 10}
    sc.services = ["physics", "sensors", "planner"]
    assert registry.lockstep_participants(sc) == {"sensors": 1, "planner": 10}
    assert sc.dt_ns == 1_000_000 and sc.control_decimation == 1
    assert len(sc.task.targets) == 3


@pytest.mark.parametrize(
    "edit, field",
    [
        (("dt: 0.001", "dt: -1"), "clock.dt"),
        (("mode: lockstep", "mode: sometimes"), "clock.mode"),
        (("rate_hz: 1000\n  gains", "rate_hz: 300\n  gains"), "controller.rate_hz"),
        (("prefix: hilsim", "prefix: a/b"), "prefix"),
        (("planning_time: 1.0", "planning_time: soon"), "planner.planning_time"),
    ],
)
def test_bad_scenario_gives_one_line_naming_file_and_field(tmp_path: Path, edit: tuple[str, str], field: str) -> None:
    text = (REPO / "config" / "arm.yaml").read_text()
    assert edit[0] in text
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace(edit[0], edit[1]).replace("../models", str(REPO / "models")))
    with pytest.raises(ConfigError) as e:
        load_scenario(bad)
    msg = str(e.value)
    assert "\n" not in msg and str(bad) in msg and field in msg, msg


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such scenario file"):
        load_scenario(tmp_path / "nope.yaml")
    (tmp_path / "x.yaml").write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scenario(tmp_path / "x.yaml")
