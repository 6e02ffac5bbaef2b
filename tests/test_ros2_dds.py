"""ROS 2 on DDS (bridges/ros2_dds.py): a lab's node on Fast DDS or Cyclone DDS sees the rover and drives it.

End to end, inside a network namespace this test makes (DDS never reaches a real interface): ``hilsim
up rover --hil config/ros2/dds.yaml`` with the bridge on its default, loopback-only Cyclone DDS
configuration, and a separate process, tests/dds_peer.py, a DDS node written without hilsim (its own
ROS 2 types under rmw's DDS names, ROS 2's QoS, a loopback CYCLONEDDS_URI of its own): it reads
``rt/rover/odom`` and ``rt/rover/scan`` with correct values, writes ``rt/rover/cmd_vel`` (first a NaN,
which the bridge must reject and survive), and the rover moves in the physics truth
(``rt/rover/truth/odom``, bridged for the test). cmd_vel is bridged both ways here, so a command the
bridge took from DDS coming back to DDS would be seen by the peer: it must not be.

Without ``ip netns`` (root, iproute2) the end-to-end test skips and says so. The unit tests check the
DDS types against hilsim's bytes, and rejection and loop prevention without DDS.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from util import network_namespace

from hilsim.bridges import ros2_dds
from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
OVERLAY = REPO / "config" / "ros2" / "dds.yaml"
PEER = Path(__file__).resolve().parent / "dds_peer.py"
DOMAIN = 42
# the peer's own Cyclone configuration: loopback, no multicast, unicast discovery on 127.0.0.1; and it
# matches the bridge by type name, as a lab's node on rmw_cyclonedds does (that RMW gives Cyclone no type
# information, so Cyclone compares names): the cyclonedds binding always has XTypes type information, and the
# bridge announces the type objects Fast DDS 3 writes (bridges/dds_types.py), which Cyclone's own
# assignability check does not take, so the peer ignores the type information of Cyclone (vendor 1.16) peers
PEER_URI = ('<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
            "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
            '<Peers><Peer address="127.0.0.1"/></Peers></Discovery><Compatibility><IgnoreTypeInformation>1.16'
            "</IgnoreTypeInformation></Compatibility></Domain></CycloneDDS>")


def bridge(**overrides: Any) -> ros2_dds.Ros2DdsBridgeService:
    return ros2_dds.Ros2DdsBridgeService(load_scenario("rover", overrides, overlays=[OVERLAY]))


# ---------------------------------------------------------------------------------------- no DDS
def test_topics_types_and_qos_are_ros2s_on_dds_and_hilsims_bytes_fit_them() -> None:
    b = bridge()
    got = {r.name: (r.dds_topic, ros2_dds.dds_struct(msgs.type_name(r.cls)).__idl_typename__, r.qos)
           for r in [*b.out, *b.inn]}
    assert got["odom"] == ("rt/rover/odom", "nav_msgs::msg::dds_::Odometry_", "default")
    assert got["scan"] == ("rt/rover/scan", "sensor_msgs::msg::dds_::LaserScan_", "sensor_data")
    assert got["imu"] == ("rt/rover/imu", "sensor_msgs::msg::dds_::Imu_", "sensor_data")
    assert got["/clock"] == ("rt/clock", "rosgraph_msgs::msg::dds_::Clock_", "clock")
    assert got["cmd_vel"] == ("rt/rover/cmd_vel", "geometry_msgs::msg::dds_::Twist_", "default")
    assert got["joint_trajectory"][1] == "trajectory_msgs::msg::dds_::JointTrajectory_"
    # hilsim's CDR, sent as it is, is exactly what the DDS type writes
    for m in (msgs.Odometry(header=msgs.header(1_500_000_000, "odom"), child_frame_id="base_link"),
              msgs.LaserScan(header=msgs.header(7, "laser"), angle_min=-1.0, angle_max=1.0, ranges=[1.0, math.inf]),
              msgs.Clock(clock=msgs.stamp(3)), msgs.Twist(linear=msgs.Vector3(x=0.5))):
        data = msgs.encode(m)
        again = ros2_dds.dds_struct(msgs.type_name(type(m))).deserialize(data).serialize(use_version_2=False)
        assert again.ljust(len(data), b"\0")[:len(data)] == data and len(again) - len(data) < 4, type(m).__name__


def test_bad_configuration_is_one_line() -> None:
    with pytest.raises(ConfigError, match=r"bridge-ros2-dds\.to_dds: unknown topic 'odometry'"):
        bridge(**{"bridge-ros2-dds.to_dds": ["odometry"]})
    with pytest.raises(ConfigError, match=r"from_dds: /clock is written by physics"):
        bridge(**{"bridge-ros2-dds.from_dds": ["/clock"]})
    with pytest.raises(ConfigError, match=r"qos: imu not in to_dds or from_dds"):
        bridge(**{"bridge-ros2-dds.to_dds": ["odom"], "bridge-ros2-dds.qos": {"imu": "default"}})


class _Pub:
    gid = b"\x07" * 16

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def put(self, m: Any) -> None:
        self.sent.append(m)


def test_bad_input_from_dds_is_counted_and_nothing_goes_round_in_a_loop() -> None:
    b = bridge()
    r = next(r for r in b.inn if r.name == "cmd_vel")
    r.pub = pub = _Pub()
    good = msgs.encode(msgs.Twist(linear=msgs.Vector3(x=0.5)))
    nan = msgs.encode(msgs.Twist(linear=msgs.Vector3(x=math.nan)))
    for data in (b"\x00\x01\x00\x00\xff", b"garbage!" * 3, nan, good[:20]):
        assert not b.from_dds(r, data)
    assert b.rejected["rt/rover/cmd_vel"] == 4
    assert b.from_dds(r, good) and pub.sent[-1].linear.x == 0.5
    # what this bridge's own DDS writer wrote is not taken back, what it put on Zenoh not sent to DDS again
    b._own_writers.add(99)
    assert not b.from_dds(r, good, writer=99)
    b._own_gids.add(pub.gid)
    b._to_dds(b.out[0], b.out[0].key, good, transport.Attachment(1, 0, pub.gid))
    assert b.loop_dropped == 2 and len(pub.sent) == 1


# ---------------------------------------------------------------------------------------- end to end
def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


LAN = "lan0"


def lan_tx(ns: str) -> int:
    """Packets sent on the namespace's stand-in LAN interface."""
    return int(json.loads(_ip("-n", ns, "-j", "-s", "link", "show", LAN).stdout)[0]["stats64"]["tx"]["packets"])


@pytest.fixture
def netns() -> Iterator[str]:
    """A network namespace where whatever DDS does stays: ``lo``, and a stand-in for the machine's LAN
    interface (a veth pair inside the namespace, with an address and the multicast route, as eth0 has;
    IPv6 off so the kernel sends nothing of its own), on which nothing may be sent."""
    with network_namespace("dds", ipv6=False) as ns:
        _ip("-n", ns, "link", "add", LAN, "type", "veth", "peer", "name", "lan1")
        _ip("-n", ns, "addr", "add", "10.99.0.1/24", "dev", LAN)
        _ip("-n", ns, "link", "set", "lan1", "up")
        _ip("-n", ns, "link", "set", LAN, "up")
        _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", LAN)
        yield ns
    assert ns not in _ip("netns", "list", check=False).stdout


@pytest.mark.e2e
def test_a_dds_node_reads_odom_and_scan_and_drives_the_rover_with_cmd_vel(netns: str, tmp_path: Path) -> None:
    # the bridge kept to this machine as a ROS 2 node is (bridges/dds_discovery.py), the peer on its own loopback
    env = {**{k: v for k, v in os.environ.items() if k != "CYCLONEDDS_URI"},
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    trace = tmp_path / "peer-dds.log"  # what the peer's Cyclone saw of the bridge's endpoints (SEDP)
    peer_uri = PEER_URI.replace("</Domain>", "<Tracing><Category>discovery</Category>"
                                f"<OutputFile>{trace}</OutputFile></Tracing></Domain>")
    run = subprocess.Popen(
        ["ip", "netns", "exec", netns, sys.executable, "-m", "hilsim.cli", "up", "rover", "--hil", str(OVERLAY),
         "--set", "services=[physics,sensors,controller,bridge-ros2-dds]",
         "--set", "controller.params.cmd_timeout=100", "--set", f"ros2.domain_id={DOMAIN}",
         "--set", "bridge-ros2-dds.to_dds=[odom,scan,truth/odom,cmd_vel,/clock,/tf_static]",
         "--duration", "300", "--out", str(tmp_path / "run")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=env, start_new_session=True)
    try:
        peer = subprocess.run(["ip", "netns", "exec", netns, sys.executable, str(PEER), "--domain", str(DOMAIN),
                               "--timeout", "90"], capture_output=True, text=True, timeout=150,
                              env={**env, "CYCLONEDDS_URI": peer_uri})
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGINT)
        try:
            out, _ = run.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(run.pid, signal.SIGKILL)
            out, _ = run.communicate()
    assert peer.returncode == 0 and peer.stdout.strip(), (peer.stdout, peer.stderr, out)
    seen = json.loads(peer.stdout.strip().splitlines()[-1])
    log = "".join(p.read_text() for p in (tmp_path / "run").rglob("bridge-ros2-dds.log"))
    assert seen["stage"] == "done", (seen, out, log[-3000:])
    assert seen["moved"] >= 0.5, seen  # the truth: the rover drove on the peer's cmd_vel
    odom, scan = seen["odom"], seen["scan"]
    assert odom["frame_id"] and odom["child_frame_id"] and odom["stamp"] > 0 and abs(odom["qw"]) > 0.5, odom
    assert odom["vx"] > 0.2, odom  # the wheel odometry felt it too
    assert scan["frame_id"] == "laser" and scan["n"] > 100 and scan["in_range"] > 10 and scan["nan"] == 0, scan
    assert scan["range_min"] == pytest.approx(0.1) and scan["range_max"] == pytest.approx(20.0), scan
    assert scan["angle_max"] > scan["angle_min"] and scan["angle_increment"] > 0, scan
    counts = seen["counts"]
    assert counts["scan_reliable"] == 0, counts  # a sensor topic is best effort, as a driver publishes it
    assert counts["cmd_vel_back"] == 0, counts  # what the bridge took from DDS did not come back
    assert "base_link->laser_link" in seen["tf_static"], seen["tf_static"]  # sent once, before the peer came
    # the NaN: rejected, counted, said; the bridge went on
    assert log.count("rejected payload on rt/rover/cmd_vel: linear.x is not finite") == 1, log
    assert re.search(r"bridge-ros2-dds: [1-9]\d* rejected, 0 errors", out), out
    assert "died" not in out, out
    # on the wire, as the peer discovered them: ROS 2's names, types, QoS and XCDR1
    seen_eps = remote_endpoints(trace.read_text())
    want = {
        ("writer", "rt/rover/odom"): ("nav_msgs::msg::dds_::Odometry_", "reliable", "volatile", 10),
        ("writer", "rt/rover/scan"): ("sensor_msgs::msg::dds_::LaserScan_", "best effort", "volatile", 5),
        ("writer", "rt/clock"): ("rosgraph_msgs::msg::dds_::Clock_", "best effort", "volatile", 1),
        ("writer", "rt/tf_static"): ("tf2_msgs::msg::dds_::TFMessage_", "reliable", "transient local", 1),
        ("writer", "rt/rover/cmd_vel"): ("geometry_msgs::msg::dds_::Twist_", "reliable", "volatile", 10),
        ("reader", "rt/rover/cmd_vel"): ("geometry_msgs::msg::dds_::Twist_", "reliable", "volatile", 10),
        ("reader", "rt/rover/joint_trajectory"): ("trajectory_msgs::msg::dds_::JointTrajectory_", "reliable",
                                                  "volatile", 10),
    }
    for ep, w in want.items():
        assert seen_eps.get(ep) == (*w, "XCDR1"), (ep, seen_eps.get(ep), sorted(seen_eps))
    assert lan_tx(netns) == 0, "DDS (or anything) left through the LAN interface: LOCALHOST must stay on lo"


_SEDP = re.compile(r"SEDP ST0 \S+ .*?(writer|reader) .*? NEW .*?topic_name=\"([^\"]+)\",type_name=\"([^\"]+)\""
                   r".*?durability=(\d),.*?reliability=(\d):.*?history=\d:(-?\d+)"
                   r".*?data_representation=\d\(([\d,]+)\)")


def remote_endpoints(trace: str) -> dict[tuple[str, str], tuple[str, str, str, int, str]]:
    """(writer|reader, topic) -> (type name, reliability, durability, depth, data representation) of every
    remote endpoint in a Cyclone discovery trace (QoS as Cyclone prints it: reliability 0 best effort,
    1 reliable; durability 0 volatile, 1 transient local; data representation 0 XCDR1, 2 XCDR2)."""
    out = {}
    for m in _SEDP.finditer(trace):
        kind, topic, type_name, dur, rel, depth, rep = m.groups()
        out[(kind, topic)] = (type_name, "reliable" if rel == "1" else "best effort",
                              {"0": "volatile", "1": "transient local"}.get(dur, dur), int(depth),
                              "XCDR1" if rep == "0" else rep)
    return out


def test_one_overlay_adds_the_bridge_to_any_scenario() -> None:
    """``services+: [bridge-ros2-dds]``: the scenario's own services and the bridge, whatever they are."""
    arm, rover = (load_scenario(n, overlays=[OVERLAY]) for n in ("arm", "rover"))
    assert arm.services == ["physics", "sensors", "controller", "planner", "logger", "bridge-ros2-dds"]
    assert rover.services == ["physics", "sensors", "controller", "navigator", "logger", "bridge-ros2-dds"]
    fleet = load_scenario("arm", {"robots": 2}, overlays=[OVERLAY])
    assert [p for p in fleet.processes() if p.startswith("bridge")] == ["bridge-ros2-dds@arm0", "bridge-ros2-dds@arm1"]
    # what each robot's bridge offers by default: what it publishes
    assert ros2_dds.default_to_dds(arm) == ["joint_states", "tf", "/tf_static", "/clock", "robot_description", "imu"]
    assert {"scan", "odom"} <= set(ros2_dds.default_to_dds(rover)) and "gps/fix" not in ros2_dds.default_to_dds(rover)


@pytest.mark.e2e
def test_a_fleet_runs_a_bridge_per_robot_in_one_process(tmp_path: Path) -> None:
    with network_namespace("ddsfleet") as ns:
        out = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m", "hilsim.cli", "up", "arm", "--set",
                              "robots=2", "--hil", str(OVERLAY), "--duration", "0.2", "--out", str(tmp_path / "run")],
                             capture_output=True, text=True, cwd=tmp_path, timeout=240)
    log = "".join(p.read_text() for p in (tmp_path / "run").glob("bridge-ros2-dds*.log"))
    assert out.returncode == 3 and "died" not in out.stdout, out.stdout[-3000:]  # STOPPED (duration), nothing failed
    assert "as node /arm0/bridge_ros2_dds" in log and "as node /arm1/bridge_ros2_dds" in log, log
