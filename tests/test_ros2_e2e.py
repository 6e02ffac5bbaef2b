"""ROS 2 on the wire, end to end: a ROS-free rmw_zenoh node sees and drives the robots of `hilsim up`.

The node (tests/ros2_node.py) shares no code with hilsim: its keys, graph tokens, gids and attachment
come from rmw_zenoh's specification, its types, hashes and CDR from ``rosbags``. Against real
``hilsim up`` processes it must find the nodes and topics as ``ros2 node list`` / ``ros2 topic list -t``
would, decode every robot topic with correct values, and move the robot by publishing
``/arm/joint_trajectory`` or ``/rover/cmd_vel``, judged by the physics truth.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
from ros2_node import STORE, Ros2Node, dds_name, msg
from util import UpRun, wait_until

ARM_JOINTS = [f"joint_{i}" for i in range(1, 7)]


class Seen:
    """What the node received per topic: messages and attachments (seq, source time, gid)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.msgs: dict[str, list[Any]] = defaultdict(list)
        self.atts: dict[str, list[tuple[int, int, bytes]]] = defaultdict(list)

    def on(self, topic: str) -> Any:
        def cb(m: Any, att: tuple[int, int, bytes]) -> None:
            with self.lock:
                self.msgs[topic].append(m)
                self.atts[topic].append(att)
        return cb

    def last(self, topic: str) -> Any:
        with self.lock:
            return self.msgs[topic][-1] if self.msgs[topic] else None

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.msgs[topic])


def check_graph(node: Ros2Node, nodes: set[str], topics: dict[str, str]) -> None:
    """``ros2 node list`` and ``ros2 topic list -t`` as read from the tokens; the hashes are rosbags'."""
    assert wait_until(lambda: nodes <= node.node_list(), 30), node.node_list()
    for topic, ros_type in topics.items():
        want = f"{dds_name(ros_type)}/{STORE.hash_rihs01(ros_type)}"
        assert wait_until(lambda t=topic: bool(node.publishers(t)), 15), (topic, sorted(node.topic_list()))
        assert node.topic_list()[topic] == {want}, (topic, node.topic_list()[topic])


def check_attachments(node: Ros2Node, seen: Seen, topic: str) -> None:
    """Every sample carries rmw_zenoh's attachment: its writer's gid is the hash of its graph token,
    sequence numbers grow by one, source times are the wall clock."""
    tokens = ["/".join(p) for p in node.publishers(topic)]
    gids = {xxhash.xxh3_128_intdigest(t.encode()).to_bytes(16, "little") for t in tokens}
    with seen.lock:
        atts = list(seen.atts[topic])
    assert atts, topic
    assert {a[2] for a in atts} <= gids, f"{topic}: a sample from a writer without a graph token"
    seqs = [a[0] for a in atts]
    assert all(b == a + 1 for a, b in itertools.pairwise(seqs)), (topic, seqs[:20])
    assert all(abs(a[1] - time.time_ns()) < 600e9 for a in atts)


@pytest.mark.e2e
def test_a_ros2_node_sees_the_arm_and_moves_it_with_a_joint_trajectory(router: str, tmp_path: Path) -> None:
    target = [0.4, -0.3, 0.25, 0.2, 0.35, -0.2]
    node = Ros2Node(router)
    seen = Seen()
    for topic, ros_type in (("/clock", "rosgraph_msgs/msg/Clock"), ("/arm/joint_states", "sensor_msgs/msg/JointState"),
                            ("/arm/truth/joint_states", "sensor_msgs/msg/JointState"),
                            ("/arm/joint_commands", "sensor_msgs/msg/JointState"), ("/arm/imu", "sensor_msgs/msg/Imu")):
        node.subscribe(topic, ros_type, seen.on(topic))
    node.subscribe("/tf", "tf2_msgs/msg/TFMessage", seen.on("/tf"))
    run = UpRun(["arm", "--set", "services=[physics,sensors,controller]", "--duration", "60"], router, tmp_path)
    out = ""
    try:
        check_graph(node, {"/arm/physics", "/arm/sensors", "/arm/controller", "/lab/lab_node"}, {
            "/clock": "rosgraph_msgs/msg/Clock", "/arm/joint_states": "sensor_msgs/msg/JointState",
            "/arm/truth/joint_states": "sensor_msgs/msg/JointState", "/arm/imu": "sensor_msgs/msg/Imu"})
        assert wait_until(lambda: seen.count("/arm/truth/joint_states") > 50, 30)
        # the controller's subscription is in the graph too (ros2 topic info: 1 subscription)
        subs = [p for p in node.tokens() if p[5] == "MS" and p[9] == "%arm%joint_trajectory"]
        assert subs and subs[0][8] == "controller", subs

        Time = STORE.types["builtin_interfaces/msg/Time"]
        Dur = STORE.types["builtin_interfaces/msg/Duration"]
        point = msg("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.array(target),
                    velocities=np.zeros(6), accelerations=np.array([], dtype=float), effort=np.array([], dtype=float),
                    time_from_start=Dur(sec=1, nanosec=500_000_000))
        traj = msg("trajectory_msgs/msg/JointTrajectory",
                   header=msg("std_msgs/msg/Header", stamp=Time(sec=0, nanosec=0), frame_id=""),  # 0: on receipt
                   joint_names=ARM_JOINTS, points=[point])
        put = node.publisher("/arm/joint_trajectory", "trajectory_msgs/msg/JointTrajectory")
        time.sleep(0.5)  # the publisher's token reaches the controller before its sample
        put(traj)

        def reached() -> bool:
            truth = seen.last("/arm/truth/joint_states")
            return truth is not None and max(abs(a - b) for a, b in zip(truth.position, target, strict=True)) < 0.01

        assert wait_until(reached, 60), seen.last("/arm/truth/joint_states")
        # the sensors' joint_states say what the truth of the same step says (within their noise), in ROS 2's
        # layout (the same step: under load the two topics' latest samples can be 200 ms of motion apart)
        def stamp(m: Any) -> int:
            return m.header.stamp.sec * 10**9 + m.header.stamp.nanosec

        with seen.lock:  # the latest step of which both arrived (two keys: either may come first)
            truths = {stamp(t): t for t in seen.msgs["/arm/truth/joint_states"]}
            js = next(j for j in reversed(seen.msgs["/arm/joint_states"]) if stamp(j) in truths)
        truth = truths[stamp(js)]
        assert list(js.name) == ARM_JOINTS and list(truth.name) == ARM_JOINTS
        assert np.allclose(js.position, truth.position, atol=0.02), (js.position, truth.position)
        imu = seen.last("/arm/imu")
        assert math.isfinite(imu.linear_acceleration.z) and imu.header.frame_id
        clocks = [c.clock.sec * 10**9 + c.clock.nanosec for c in seen.msgs["/clock"]]
        assert clocks == sorted(clocks) and clocks[-1] > 1e9
        for topic in ("/clock", "/arm/joint_states", "/arm/truth/joint_states"):
            check_attachments(node, seen, topic)
        # /tf from the URDF's moving joints: joint_1 turns shoulder_link about z by its angle
        # (/tf is its own key at 50 Hz: its latest sample may be a few steps behind the truth's, so wait for it)
        def tf_now() -> dict[str, Any]:
            with seen.lock:
                return {tr.child_frame_id: tr for m in seen.msgs["/tf"][-5:] for tr in m.transforms}

        def tf_there() -> bool:
            r = tf_now().get("shoulder_link")
            q = r.transform.rotation if r is not None else None
            return q is not None and abs(2 * math.atan2(q.z, q.w) - target[0]) < 0.02

        assert wait_until(tf_there, 10), tf_now().get("shoulder_link")
        tf = tf_now()
        assert {"shoulder_link", "arm_link", "elbow_link", "forearm_link", "wrist_link", "hand_link"} <= set(tf), tf
        assert tf["shoulder_link"].header.frame_id == "base_link"
        # transient-local, as rviz2 gets them however late it comes: /tf_static and the URDF
        late = Ros2Node(router, name="rviz2", namespace="/")
        statics: list[Any] = []
        description: list[Any] = []
        late.subscribe_latched("/tf_static", "tf2_msgs/msg/TFMessage", statics.append)
        late.subscribe_latched("/arm/robot_description", "std_msgs/msg/String", description.append)
        try:
            assert wait_until(lambda: bool(statics) and bool(description), 15), (statics, description)
        finally:
            late.close()
        assert any(tr.child_frame_id == "tool_link" and tr.header.frame_id == "hand_link"
                   for tr in statics[0].transforms), statics[0]
        assert "<robot" in description[0].data and 'joint name="joint_1"' in description[0].data
    finally:
        out = run.stop()
        node.close()
    assert "ready:" in out, out


@pytest.mark.e2e
def test_a_ros2_node_drives_the_rover_with_cmd_vel(router: str, tmp_path: Path) -> None:
    node = Ros2Node(router, name="teleop", namespace="/")
    seen = Seen()
    for topic, ros_type in (("/rover/truth/odom", "nav_msgs/msg/Odometry"), ("/rover/odom", "nav_msgs/msg/Odometry"),
                            ("/rover/scan", "sensor_msgs/msg/LaserScan"), ("/rover/imu", "sensor_msgs/msg/Imu")):
        node.subscribe(topic, ros_type, seen.on(topic))
    run = UpRun(["rover", "--set", "services=[physics,sensors,controller]", "--set",
                 "controller.params.cmd_timeout=100", "--duration", "60"], router, tmp_path)
    try:
        check_graph(node, {"/rover/physics", "/rover/sensors", "/rover/controller", "/teleop"}, {
            "/rover/odom": "nav_msgs/msg/Odometry", "/rover/scan": "sensor_msgs/msg/LaserScan",
            "/rover/truth/odom": "nav_msgs/msg/Odometry"})
        assert wait_until(lambda: seen.count("/rover/truth/odom") > 20 and seen.count("/rover/scan") > 2, 30)
        start = seen.last("/rover/truth/odom").pose.pose.position
        V3 = STORE.types["geometry_msgs/msg/Vector3"]
        put = node.publisher("/rover/cmd_vel", "geometry_msgs/msg/Twist")
        time.sleep(0.5)
        put(msg("geometry_msgs/msg/Twist", linear=V3(x=0.5, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)))

        def moved() -> float:
            p = seen.last("/rover/truth/odom").pose.pose.position
            return math.hypot(p.x - start.x, p.y - start.y)

        assert wait_until(lambda: moved() > 0.5, 60), moved()
        scan = seen.last("/rover/scan")
        assert len(scan.ranges) > 10 and scan.angle_max > scan.angle_min
        # the wheel odometry felt it too (still driving: one command held for cmd_timeout; its stream can
        # reach this node later than the truth's on a loaded machine)
        assert wait_until(lambda: seen.last("/rover/odom").twist.twist.linear.x > 0.2, 15), \
            seen.last("/rover/odom").twist.twist.linear
        check_attachments(node, seen, "/rover/truth/odom")
    finally:
        out = run.stop()
        node.close()
    assert "ready:" in out, out
