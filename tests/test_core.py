"""Keys, messages and scenario validation: the contracts every service relies on."""

from __future__ import annotations

import math
import re
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


def test_given_once_keys_and_sessions_without_shared_memory() -> None:
    """Issue 36: on a loaded machine a trajectory or a result must not be lost on the way. Samples given
    once are the key table's (never dropped when congested: hilsim.core.publisher); and no session hands
    a sample over as a shared-memory buffer (Zenoh's watchdog overran under load and receivers lost such
    samples or got their bytes zeroed): every kind of session, the router's too."""
    from hilsim.core import keys as keyscheme
    from hilsim.core import transport
    from hilsim.core.config import ZenohConfig

    k = Keys()
    assert keyscheme.given_once(k.topic("joint_trajectory")) and keyscheme.given_once(k.topic("task/result"))
    assert not keyscheme.given_once(k.topic("joint_states")) and not keyscheme.given_once(k.clock)
    assert not keyscheme.given_once(k.health("planner"))
    for mode in ("client", "peer", "router"):
        conf = transport.zenoh_config(ZenohConfig(), mode=mode)
        assert conf.get_json("transport/shared_memory/enabled") == "false", mode


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
    assert "logger" in load_scenario("arm").services
    assert "logger" not in load_scenario("arm", {"logger.enabled": False}).services
    assert load_scenario("arm", {"clock.controller_lag": 1}).clock.controller_lag == 1
    with pytest.raises(ConfigError, match=r"clock\.controller_lag"):
        load_scenario("arm", {"clock.controller_lag": 2})


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
    with pytest.raises(ConfigError, match="no such scenario file") as e:
        load_scenario(tmp_path / "nope.yaml")
    # every scenario of config/ is offered, those that extend another too (arm-lean), overlays not
    avail = str(e.value).split("available in config/: ")[1].rstrip(")").split(", ")
    assert avail == ["arm", "arm-lean", "rover", "rover-outdoor"], avail
    (tmp_path / "x.yaml").write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scenario(tmp_path / "x.yaml")


def test_an_unknown_planner_is_refused_before_anything_starts() -> None:
    with pytest.raises(ConfigError, match=r"^--set planner\.planner=rrtstr: planner\.planner: unknown planner "
                       r"'rrtstr'.*available: .*auto.*rrtstar"):
        load_scenario("arm", {"planner.planner": "rrtstr"})
    assert load_scenario("arm", {"planner.planner": "auto"}).planner.planner == "auto"


def _arm_edited(tmp_path: Path, *edits: tuple[str, str]) -> Path:
    text = (REPO / "config" / "arm.yaml").read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("../models", str(REPO / "models")))
    return bad


@pytest.mark.parametrize(
    "edits, field, expected",
    [
        ([("- [0.866, -0.789, -0.399, 0.0, -0.382, 0.0]", "- [0.866, -0.789]")], "task.targets[0]",
         "expected 6 values, one per joint of tabletop.xml (joint_1, joint_2, joint_3, joint_4, joint_5, joint_6), "
         "got 2"),
        ([("joint_3: {kp: 19.94", "joint_7: {kp: 19.94")], "controller.gains.joint_7",
         "not a joint of the model (joints of tabletop.xml: joint_1"),
        ([("    default: {kp: 100.0, ki: 5.0, kd: 5.0, i_limit: 2.0, feedforward: 0.0}\n", ""),
          ("    joint_3: {kp: 19.94, ki: 0, kd: 2.413, i_limit: 1.2}\n", "")], "controller.gains",
         "no gains for joint_3 and no 'default' entry"),
        ([("default: {interface: effort, server: sim}", "elbow: {interface: position}")], "joints.elbow",
         "no actuated joint of that name"),
    ],
)
def test_fields_shaped_by_the_robot_are_checked_against_its_model(tmp_path: Path, edits: list[tuple[str, str]],
                                                                  field: str, expected: str) -> None:
    """A target of the wrong length once passed validation and the run never ended (the planner met a
    numpy broadcast error at every tick): every field whose shape depends on the robot is checked
    against the model's actuated joints when the scenario is read, one line naming file and field."""
    bad = _arm_edited(tmp_path, *edits)
    with pytest.raises(ConfigError) as e:
        load_scenario(bad)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{bad}: {field}: ") and expected in msg, msg


def test_a_robots_override_and_the_planner_library_are_checked_against_the_model(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"robot_overrides\.arm1\.task\.targets\[0\]: expected 6 values"):
        load_scenario("arm", {"robots": 2, "robot_overrides": {"arm1": {"task.targets": [[0.1, 0.2, 0.3]]}}})
    with pytest.raises(ConfigError, match=r"task\.targets\[1\]: a rover target is \[x, y\] or \[x, y, yaw\]"):
        load_scenario("rover", {"task.targets": [[1.0, 2.0], [1.0]]})
    lib = tmp_path / "planners.yaml"
    shipped = (REPO / "config" / "planners.yaml").read_text()
    lib.write_text(re.sub(r"\n  velocity: [^\n]*", "\n  velocity: [1.0, 1.0, 1.0, 1.5, 1.5]", shipped))
    assert lib.read_text() != shipped
    with pytest.raises(ConfigError) as e:
        load_scenario("arm", {"planner.library": str(lib)})
    assert str(e.value).startswith(f"{lib}: limits.velocity: expected a number or 6 values"), e.value
    # what the shipped scenarios say fits their models
    for name in ("arm", "arm-lean", "rover", "rover-outdoor"):
        load_scenario(name)
    assert load_scenario("arm", {"robots": 2, "robot_overrides": {"arm1": {"task.targets": [[0.0] * 6]}}}).robots == 2


@pytest.mark.parametrize(
    "override, expected",
    [
        ({"controler.rate_hz": 5}, "--set controler.rate_hz=5: unknown field 'controler' (not a scenario field"),
        ({"seed": 1, "controller.rate_hz": "fast"},
         "--set controller.rate_hz=fast: controller.rate_hz: Input should be a valid number"),
        ({"controller.rate_hz": 300}, "--set controller.rate_hz=300: controller.rate_hz (300.0) must divide"),
        ({"task.targets": [[0.1, 0.2]]}, "--set task.targets=[[0.1, 0.2]]: task.targets[0]: expected 6 values"),
        ({"clock.dt.x": 1}, "--set clock.dt.x=1: dt is not a section"),
        ({"world.model": "nope.xml"}, "--set world.model=nope.xml: world.model: file "),
    ],
)
def test_an_error_caused_by_a_set_names_the_set_not_the_file(override: dict[str, object], expected: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_scenario("arm", override)
    assert str(e.value).startswith(expected) and "arm.yaml" not in str(e.value), e.value


def test_an_error_is_blamed_on_its_origin_file_overlay_or_option(tmp_path: Path) -> None:
    bad = _arm_edited(tmp_path, ("dt: 0.001", "dt: -1"))
    with pytest.raises(ConfigError, match=f"^{bad}: clock.dt: "):  # the file's own error, whatever is set on it
        load_scenario(bad, {"seed": 3})
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("controller:\n  rate_hz: 300\n")
    with pytest.raises(ConfigError, match=f"^{overlay}: controller.rate_hz"):
        load_scenario("arm", {"seed": 3}, overlays=[overlay])
    # a --set that repairs the file is not blamed, and an option is named as the user gave it
    assert load_scenario(bad, {"clock.dt": 0.001}).clock.dt == 0.001
    with pytest.raises(ConfigError, match=r"^--duration -1: duration: Input should be greater than 0"):
        load_scenario("arm", {"duration": -1.0}, origins={"duration": "--duration -1"})


def test_hilsim_up_will_not_record_a_run_over_another(tmp_path: Path) -> None:
    """No lost data: ``--out`` naming the directory of an earlier run is refused before anything
    starts (its bag would be counted with the new run's, its recording overwritten)."""
    import subprocess
    import sys

    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "bag_0.mcap").write_bytes(b"x")
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", "--out", str(tmp_path)], capture_output=True,
                       text=True, timeout=60, cwd=REPO)
    assert r.returncode == 2 and r.stderr.strip() == (
        f"error: --out {tmp_path}: already holds a run's recording (bag); give a new directory or remove it"), r
    assert (tmp_path / "bag" / "bag_0.mcap").read_bytes() == b"x" and not (tmp_path / "recording.rrd").exists()


def test_hilsim_up_says_a_bad_set_in_one_line_and_exits_2() -> None:
    import subprocess
    import sys

    cases = ((["--set", "controler.rate_hz=5"], "error: --set controler.rate_hz=5: unknown field 'controler'"),
             (["--set", "task.targets=[[1, 2]]"],
              "error: --set task.targets=[[1, 2]]: task.targets[0]: expected 6 values"))
    for args, line in cases:
        r = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", *args], capture_output=True, text=True,
                           timeout=60, cwd=REPO)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith(line), (r.returncode, r.stderr)
        assert "arm.yaml" not in lines[0] and not r.stdout, r.stdout


def test_a_services_last_health_is_never_dropped_in_realtime() -> None:
    """A realtime service's streams, health and log are DROP on a congested link (a blocking health or log put
    slowed a realtime loop whose recorder fell behind: test_logger_stall), but its last health is not: it is
    its last word (its end state: without it the panel saw a stopped service as dead, stop 47's CI)."""
    from typing import Any

    import zenoh

    from hilsim.core import transport
    from hilsim.core.config import ZenohConfig
    from hilsim.core.publisher import Publisher
    from hilsim.core.scenario import load_scenario
    from hilsim.core.service import instantiate

    class Spy:  # the service's session, with the puts made on it (not through a publisher) seen
        def __init__(self, real: Any) -> None:
            self.real, self.puts = real, []

        def put(self, key: str, data: bytes, **kw: Any) -> None:
            self.puts.append((key, kw.get("congestion_control")))
            self.real.put(key, data, **kw)

        def __getattr__(self, name: str) -> Any:
            return getattr(self.real, name)

    svc = instantiate("controller", load_scenario("arm", {"clock": {"mode": "realtime"}}))
    ses = transport.open_session(ZenohConfig(connect=[], listen=[]))  # alone: no router, no peer
    try:
        svc.attach(ses)
        pubs = {p.key: p._pub.congestion_control for p in svc._declared if isinstance(p, Publisher)}
        for key in (svc.keys.health("controller"), svc.keys.log("controller"), svc.keys.topic("joint_commands")):
            assert pubs[key] == zenoh.CongestionControl.DROP, key
        spy = svc.session = Spy(ses)
        listener = ses.declare_subscriber(svc.keys.health("controller"), lambda s: None)  # someone listens
        try:
            svc._health_pub.matching = True
            svc.publish_health()
            assert spy.puts == []  # an ordinary one: through its publisher (DROP)
            svc.final = True
            svc.publish_health()
            assert spy.puts == [(svc.keys.health("controller"), zenoh.CongestionControl.BLOCK)]
        finally:
            listener.undeclare()
    finally:
        for d in reversed(svc._declared):
            d.undeclare()
        ses.close()
