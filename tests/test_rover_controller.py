"""The four_wheel_steer controller in process: it is the lockstep participant via joint_commands,
answers every joint_states with every joint and every field, follows cmd_vel (held for
cmd_timeout, then stop) or its script, limits the twist, and refuses bad settings in one line."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario
from hilsim.services.rover_controller import FourWheelSteerController

WHEELS = ("fl", "fr", "rl", "rr")


class Sink:
    def __init__(self) -> None:
        self.got: list[Any] = []

    def put(self, m: Any) -> None:
        self.got.append(m)


def controller(**over: Any) -> FourWheelSteerController:
    # realtime: a control step runs on its joint_states alone (in lockstep it also waits for its imu,
    # test_lockstep_step_waits_for_its_imu)
    c = FourWheelSteerController(load_scenario("config/rover.yaml", {"clock.mode": "realtime", **over}))
    c.cmd_pub, c.odom_pub = Sink(), Sink()  # type: ignore[assignment]
    return c


def states(c: FourWheelSteerController, t_ns: int, angle: float = 0.0, speed: float = 0.0) -> msgs.JointState:
    pos = [angle if n.endswith("steering") else 0.0 for n in c.names]
    vel = [speed if n.endswith("traction") else 0.0 for n in c.names]
    return msgs.JointState(header=msgs.header(t_ns), name=c.names, position=pos, velocity=vel, effort=[0.0] * 8)


def test_resolved_by_type_and_a_lockstep_participant_via_joint_commands() -> None:
    sc = load_scenario("config/rover.yaml")
    assert registry.service_class("controller", sc) is FourWheelSteerController
    assert FourWheelSteerController.lockstep_period(sc) == 5  # 100 Hz over 500 Hz physics
    assert FourWheelSteerController.ack_via == "joint_commands"
    c = controller()
    assert c.geom.positions == ((0.35, 0.4), (0.35, -0.4), (-0.35, 0.4), (-0.35, -0.4))
    assert c.geom.radius == pytest.approx(0.15) and c.geom.upper == pytest.approx(math.pi / 2)
    assert c.max_wheel_speed == 12.0  # the traction joints' URDF velocity limit


def test_every_joint_every_field_and_the_wheels_follow_cmd_vel() -> None:
    c = controller()
    c.sim_ns = 0
    c.on_cmd_vel(msgs.Twist(angular=msgs.Vector3(z=1.0)), "k")  # turn in place
    c.on_joint_states(states(c, 10_000_000), "k")
    cmd = c.cmd_pub.got[-1]  # type: ignore[attr-defined]
    assert cmd.name == c.names and len(cmd.position) == len(cmd.velocity) == len(cmd.effort) == 8
    assert msgs.ns_of(cmd.header.stamp) == 10_000_000
    ref = dict(zip(cmd.name, cmd.position, strict=True))
    d = math.atan2(0.35, 0.4)
    assert [ref[f"{w}_steering"] for w in WHEELS] == pytest.approx([-d, d, d, -d])
    eff = dict(zip(cmd.name, cmd.effort, strict=True))
    assert eff["fl_steering"] < 0 < eff["fr_steering"]  # PIDs push towards the references
    # the wheels still point straight: no traction until they have turned (cos of the error)
    vel = dict(zip(cmd.name, cmd.velocity, strict=True))
    assert abs(vel["fl_traction"]) < abs(math.cos(d) * math.hypot(0.4, 0.35) / 0.15) + 1e-9
    assert c.odom_pub.got and c.odom_pub.got[-1].child_frame_id == "base_link"  # type: ignore[attr-defined]


def test_cmd_vel_held_for_its_timeout_then_stop_and_limits() -> None:
    c = controller(**{"controller.params.max_speed": 0.5})
    c.sim_ns = 1_000_000_000
    c.on_cmd_vel(msgs.Twist(linear=msgs.Vector3(x=3.0, y=4.0), angular=msgs.Vector3(z=9.0)), "k")
    vx, vy, wz = c.target(1_400_000_000)
    assert (vx, vy) == pytest.approx((0.3, 0.4)) and wz == 1.5  # max_speed 0.5, max_yaw_rate 1.5
    assert c.target(1_600_000_000) == (0.0, 0.0, 0.0)  # older than cmd_timeout 0.5 s: stop


def test_script_gives_the_twist_by_sim_time() -> None:
    c = controller(**{"controller.params.script": [[1.0, 0.5, 0, 0], [2.0, 0, 0, 0.5]]})
    assert c.target(500_000_000) == (0.0, 0.0, 0.0)
    assert c.target(1_500_000_000) == (0.5, 0.0, 0.0)
    assert c.target(2_000_000_000) == (0.0, 0.0, 0.5)


def test_wheel_odometry_integrates_the_measured_wheels() -> None:
    c = controller()
    for k in range(101):  # wheels straight, 2 rad/s = 0.3 m/s, for 1 s
        c.on_joint_states(states(c, k * 10_000_000, speed=2.0), "k")
    o = c.odom_pub.got[-1]  # type: ignore[attr-defined]
    assert o.pose.pose.position.x == pytest.approx(0.3) and o.twist.twist.linear.x == pytest.approx(0.3)
    # with a gyro sample of the same step its yaw rate wins (wheels straight, yet turning: slip)
    c.on_imu(msgs.Imu(header=msgs.header(1_010_000_000), angular_velocity=msgs.Vector3(z=0.2)), "k")
    c.on_joint_states(states(c, 1_010_000_000, speed=2.0), "k")
    assert c.odom_pub.got[-1].twist.twist.angular.z == pytest.approx(0.2)  # type: ignore[attr-defined]
    c.on_joint_states(states(c, 1_020_000_000, speed=2.0), "k")  # the sample is a step old: wheels again
    assert c.odom_pub.got[-1].twist.twist.angular.z == pytest.approx(0.0)  # type: ignore[attr-defined]


def test_lockstep_step_waits_for_its_imu() -> None:
    """Lockstep: joint_states and imu are two keys in no guaranteed order; a control step whose imu
    is due (every 5 physics steps at 100 Hz) is held until that imu comes, then uses its gyro, so the
    odometry is the same whichever arrived first."""
    c = controller(**{"clock.mode": "lockstep", "services": ["physics", "sensors", "controller"]})
    c.on_joint_states(states(c, 10_000_000, speed=2.0), "k")
    assert c.odom_pub.got == [] and c.cmd_pub.got == []  # type: ignore[attr-defined]
    c.on_imu(msgs.Imu(header=msgs.header(10_000_000), angular_velocity=msgs.Vector3(z=0.2)), "k")
    assert len(c.cmd_pub.got) == 1 and msgs.ns_of(c.cmd_pub.got[0].header.stamp) == 10_000_000  # type: ignore[attr-defined]
    assert c.odom_pub.got[-1].twist.twist.angular.z == pytest.approx(0.2)  # type: ignore[attr-defined]
    # imu first (the usual order): the step runs at once, with the same result
    c.on_imu(msgs.Imu(header=msgs.header(20_000_000), angular_velocity=msgs.Vector3(z=0.2)), "k")
    c.on_joint_states(states(c, 20_000_000, speed=2.0), "k")
    assert len(c.cmd_pub.got) == 2 and c.odom_pub.got[-1].twist.twist.angular.z == pytest.approx(0.2)  # type: ignore[attr-defined]


def test_lockstep_step_waits_for_the_navigators_cmd_vel() -> None:
    """Lockstep with the navigator (one cmd_vel per 20 Hz decision, after the controller's step of
    that time): a control step is held until the cmd_vel of every earlier decision has come, and the
    command then counts from the previous control step, whichever arrived first."""
    c = controller(**{"clock.mode": "lockstep", "controller.params.imu_yaw_rate": False})
    assert c.cmd_every == 25  # 20 Hz over 500 Hz physics
    c.on_joint_states(states(c, 0), "k")  # step 0: no decision before it
    assert len(c.cmd_pub.got) == 1  # type: ignore[attr-defined]
    c.on_joint_states(states(c, 10_000_000), "k")  # needs the decision of t = 0
    assert len(c.cmd_pub.got) == 1  # type: ignore[attr-defined]
    c.on_cmd_vel(msgs.Twist(linear=msgs.Vector3(x=0.5)), "k")
    assert len(c.cmd_pub.got) == 2 and c.twist == (0.5, 0.0, 0.0)  # type: ignore[attr-defined]
    assert c.cmd_ns == 0  # counted from the control step it followed, not from its arrival
    for k in range(2, 6):  # up to t = 50 ms: still only the decision of t = 0 is due
        c.on_joint_states(states(c, k * 10_000_000), "k")
    assert len(c.cmd_pub.got) == 6  # type: ignore[attr-defined]
    c.on_cmd_vel(msgs.Twist(linear=msgs.Vector3(x=0.2)), "k")  # decision of t = 50 ms, arrived early
    c.on_joint_states(states(c, 60_000_000), "k")
    assert len(c.cmd_pub.got) == 7 and c.twist == (0.2, 0.0, 0.0)  # type: ignore[attr-defined]


@pytest.mark.parametrize(("over", "field"), [
    ({"controller.gains.wheel_9": {"kp": 1.0}}, "controller.gains.wheel_9"),
    ({"controller.params.wheels": ["fl", "xx"]}, "controller.params.wheels"),
    ({"controller.params.max_speed": -1}, "controller.params.max_speed"),
    ({"controller.params.script": [[2, 0, 0, 0], [1, 0, 0, 0]]}, "controller.params.script"),
    ({"controller.params.top_speed": 2}, "controller.params.top_speed"),
])
def test_bad_settings_are_one_line(over: dict[str, Any], field: str) -> None:
    with pytest.raises(ConfigError) as e:
        FourWheelSteerController(load_scenario("config/rover.yaml", over))
    assert field in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_non_effort_joints_get_references_not_torques() -> None:
    c = controller(**{"joints.default.interface": "velocity", "joints.fl_steering.interface": "position"})
    c.on_cmd_vel(msgs.Twist(linear=msgs.Vector3(x=0.3)), "k")
    c.on_joint_states(states(c, 0), "k")
    cmd = c.cmd_pub.got[-1]  # type: ignore[attr-defined]
    assert np.allclose(cmd.effort, 0.0)
    vel = dict(zip(cmd.name, cmd.velocity, strict=True))
    assert vel["fl_traction"] == pytest.approx(2.0)
    c.on_cmd_vel(msgs.Twist(linear=msgs.Vector3(x=0.3, y=0.3)), "k")  # crab at 45°
    c.on_joint_states(states(c, 10_000_000), "k")
    vel = dict(zip(c.cmd_pub.got[-1].name, c.cmd_pub.got[-1].velocity, strict=True))  # type: ignore[attr-defined]
    assert vel["fr_steering"] == pytest.approx(10.0 * math.pi / 4)  # velocity_gain · angle error
    assert vel["fl_steering"] == 0.0  # a position joint: its reference is in position
