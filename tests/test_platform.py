"""The platform seams: per-joint interfaces and servers, per-body gravity compensation, the
registry, and the rules that keep hardware safe (an external joint needs the realtime clock)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario
from hilsim.launch.launcher import stop_order
from hilsim.sim.world import World

REPO = Path(__file__).resolve().parent.parent
NAMES = [f"joint_{i}" for i in range(1, 7)]


def test_an_external_joint_refuses_the_lockstep_clock() -> None:
    with pytest.raises(ConfigError) as e:
        load_scenario("arm", {"joints.joint_1.server": "motor-model"})
    msg = str(e.value)
    # the origin of the bad value: the --set, not the file (README)
    assert "\n" not in msg and msg.startswith("--set joints.joint_1.server=motor-model: ") and "realtime" in msg, msg
    sc = load_scenario("arm", {"joints.joint_1.server": "motor-model", "clock.mode": "realtime"})
    assert sc.external_servers() == ["motor-model"]
    assert sc.processes() == [*sc.services, "motor-model"]


def test_hilsim_up_says_why_in_one_line_and_exits_2() -> None:
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", "--set", "joints.joint_1.server=motor-model"],
                       capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "clock.mode: realtime" in lines[0] and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize(
    ("overrides", "field", "expected"),
    [
        ({"joints.joint_1.server": "nobody", "clock.mode": "realtime"}, "joints.joint_1.server", "unknown server"),
        ({"joints.joint_1.interface": "torque"}, "joints.joint_1.interface", "effort"),
        ({"services": ["physics", "teleporter"]}, "services", "unknown service 'teleporter'"),
        ({"gripper": {"force": 1}}, "gripper", "unknown field"),
    ],
)
def test_bad_joint_and_service_config_is_one_line(overrides: dict[str, Any], field: str, expected: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_scenario("arm", overrides)
    msg = str(e.value)
    assert "\n" not in msg and expected in msg and msg.startswith("--set "), msg  # the origin: the --set
    assert field.split(".")[0] in msg, msg


def test_unknown_joint_and_body_names_are_config_errors() -> None:
    with pytest.raises(ConfigError, match=r"joints.elbow: no actuated joint of that name"):
        World(load_scenario("arm", {"joints.elbow": {"interface": "position"}}))
    with pytest.raises(ConfigError, match=r"physics.gravity_compensation: no body matches 'wheel_\*'"):
        World(load_scenario("arm", {"physics.gravity_compensation": ["wheel_*"]}))


def test_gravity_compensation_is_per_body() -> None:
    """Opt-in: the arm keeps it; without it the links fall (a wheeled base keeps its weight)."""
    held = World(load_scenario("arm"))
    free = World(load_scenario("arm", {"physics.gravity_compensation": []}))
    some = World(load_scenario("arm", {"physics.gravity_compensation": ["hand_link", "wrist_link"]}))
    for w in (held, free, some):
        for _ in range(300):
            w.step()
    assert np.abs(held.positions()).max() < 1e-6
    assert np.abs(free.positions()).max() > 0.01
    # only the listed bodies are compensated: the unlisted upper links still fall
    assert np.abs(some.positions()).max() > 0.01
    assert int(some.model.body_gravcomp.astype(bool).sum()) == 2


def test_mixed_interfaces_track_their_commands() -> None:
    """One robot: a position joint, a velocity joint and effort joints, in one command message."""
    sc = load_scenario("arm", {"joints.joint_1.interface": "position", "joints.joint_2.interface": "velocity"})
    w = World(sc)
    assert w.interfaces == ["position", "velocity", "effort", "effort", "effort", "effort"]
    cmd = msgs.JointState(name=NAMES, position=[0.4, 0.0, 0, 0, 0, 0], velocity=[0.0, 0.05, 0, 0, 0, 0],
                          effort=[99.0, 99.0, 0.5, 0, 0, 0])  # effort of non-effort joints is not read
    w.command(cmd)
    for _ in range(1500):
        w.step()
    assert w.positions()[0] == pytest.approx(0.4, abs=0.01)
    assert w.velocities()[1] == pytest.approx(0.05, abs=0.01)
    assert w.positions()[2] > 0.1  # the effort joint moved under its torque
    # a partial command names only some joints; the others keep theirs
    w.command(msgs.JointState(name=["joint_1"], position=[-0.2]))
    for _ in range(1500):
        w.step()
    assert w.positions()[0] == pytest.approx(-0.2, abs=0.01) and w.velocities()[1] == pytest.approx(0.05, abs=0.01)
    # a command without the field a joint's interface reads is refused whole
    with pytest.raises(msgs.BadMessage, match="no velocity values for joint 'joint_2'"):
        w.command(msgs.JointState(name=["joint_1", "joint_2"], position=[0.0, 0.0]))


def test_an_external_joint_follows_its_server_not_the_command() -> None:
    sc = load_scenario("arm", {"joints.joint_1.server": "motor-model", "clock.mode": "realtime"})
    w = World(sc)
    w.command(msgs.JointState(name=NAMES, effort=[12.0] * 6))  # joint_1's effort is the server's business
    for _ in range(50):
        w.step()
    assert w.positions()[0] == pytest.approx(0.0, abs=1e-9)  # held until its server reports
    w.follow(["joint_1"], [0.5], [0.1])
    w.step()
    assert w.positions()[0] == 0.5 and w.velocities()[0] == 0.1
    assert abs(w.positions()[1]) > 0  # the simulated joints moved under their commands
    with pytest.raises(msgs.BadMessage, match="not served externally"):
        w.follow(["joint_2"], [0.0], [])


def test_registry_lists_without_importing_and_names_what_is_available() -> None:
    assert {"physics", "sensors", "controller", "planner", "logger", "motor-model"} <= set(registry.names("services"))
    assert registry.names("controllers")[0] == "joint_trajectory"
    with pytest.raises(registry.UnknownName, match=r"unknown service 'nope'; available: physics, sensors"):
        registry.load("services", "nope")
    sc = load_scenario("arm", {"joints.joint_1.server": "motor-model", "clock.mode": "realtime"})
    # declared by the classes: physics stops first, the recorder last, the joint server after the loop
    order = stop_order(sc)
    assert order[0] == "physics" and order[-1] == "logger" and order.index("motor-model") > order.index("controller")
    assert registry.lockstep_participants(load_scenario("arm")) == {"controller": 1, "planner": 10}
    # composed: a group stops with its first-stopping member, a group holding the recorder last
    assert stop_order(load_scenario("arm", {"compose": [["physics", "sensors", "controller"]]})) == [
        "physics+sensors+controller", "planner", "logger"]
    assert stop_order(load_scenario("arm", {"compose": [["physics", "sensors", "controller", "logger"]]})) == [
        "planner", "physics+sensors+controller+logger"]


def test_controller_type_picks_the_control_law() -> None:
    sc = load_scenario("arm")
    from hilsim.services.controller import ControllerService

    assert registry.service_class("controller", sc) is ControllerService
    from hilsim.services.rover_controller import FourWheelSteerController

    assert registry.service_class("controller", load_scenario("rover")) is FourWheelSteerController
    sc2 = load_scenario("arm", {"controller.type": "skid_steer"})
    with pytest.raises(ConfigError, match="unknown controller 'skid_steer'; available: joint_trajectory, "
                       "four_wheel_steer"):
        registry.service_class("controller", sc2)


def test_in_process_pipeline_finds_its_lockstep_participants() -> None:
    """The services announce their lockstep role at run time; the in-process bus (bench loop's
    no-transport baseline) carries those announcements like Zenoh does, so physics steps."""
    from hilsim.tools.bench.pipeline import bench_in_process

    assert bench_in_process(0.05) > 0.0  # raises if the pipeline stalls


def test_planner_settings_are_explicit_fields() -> None:
    with pytest.raises(ConfigError, match=r"planner.iteratoins: Extra inputs are not permitted"):
        load_scenario("arm", {"planner.iteratoins": 10})
    sc = load_scenario("arm", {"planner.iterations": 10, "planner.library": "planners.yaml"})
    assert sc.planner.iterations == 10 and sc.planner.library == REPO / "config" / "planners.yaml"


def test_hil_overlay_and_extends_give_the_same_scenario() -> None:
    """`hilsim up arm --hil config/hil/motor-model.yaml` == `hilsim up config/hil/arm-motor-model.yaml`."""
    a = load_scenario("arm", overlays=[REPO / "config" / "hil" / "motor-model.yaml"]).dump()
    b = load_scenario(REPO / "config" / "hil" / "arm-motor-model.yaml").dump()
    assert a.pop("name") == "arm" and b.pop("name") == "arm-motor-model"
    assert a == b and a["joints"]["joint_1"]["server"] == "motor-model" and a["clock"]["mode"] == "realtime"
    with pytest.raises(ConfigError, match="no such overlay file"):
        load_scenario("arm", overlays=["config/hil/nope.yaml"])


def test_a_joint_entry_overrides_only_the_fields_it_sets() -> None:
    sc = load_scenario("arm", {"joints.default": {"interface": "position"}, "joints.joint_1": {"server": "motor-model"},
                               "clock.mode": "realtime"})
    assert sc.joint("joint_1").interface == "position" and sc.joint("joint_1").server == "motor-model"
    assert sc.joint("joint_2").interface == "position" and sc.joint("joint_2").server == "sim"


def test_follow_extrapolation_carries_a_report_forward_for_a_bounded_time() -> None:
    """A drive reporting every 10 ms: between reports the link moves on at the reported
    velocity (physics.follow_extrapolation), never further than that bound past the report."""
    over = {"joints.joint_1.server": "motor-model", "clock.mode": "realtime"}
    held = World(load_scenario("arm", over))
    moving = World(load_scenario("arm", {**over, "physics.follow_extrapolation": 0.01}))
    for w in (held, moving):
        w.follow(["joint_1"], [0.2], [1.0])
        for _ in range(25):
            w.step()
    assert held.positions()[0] == 0.2
    assert moving.positions()[0] == pytest.approx(0.2 + 1.0 * 0.01)  # capped at 10 ms, not 25 ms
