"""A real ROS 2 node (rclpy on the distribution's default RMW, rmw_fastrtps_cpp), as a lab would write it.

It runs under a ROS 2 venv's Python (Kilted or Jazzy wheels, ``scripts/ros2-venvs.sh``), imports nothing
of hilsim, and subscribes with the QoS ROS 2 code uses for each topic: reliable keep-last 10 (the default)
for joint states and odometry, ``qos_profile_sensor_data`` for ``/clock``, the IMU, the laser and the GPS,
transient-local keep-last 1 for ``robot_description`` (a late joiner: it starts after the bridge
published it). With ``use_sim_time`` its clock is the simulation's.

    python tests/ros2_real_node.py --robot arm [--drive trajectory --target J1 … J6] [--seconds S]
    python tests/ros2_real_node.py --robot rover [--drive cmd_vel --distance M] [--seconds S]

``--drive trajectory`` publishes one trajectory_msgs/JointTrajectory to ``--target`` on
``/<robot>/joint_trajectory`` once hilsim's subscription is matched, and waits until the truth
(``/<robot>/truth/joint_states``) is there; ``--drive cmd_vel`` publishes geometry_msgs/Twist
(``linear.x = 0.5``) at 10 Hz on ``/<robot>/cmd_vel`` until the truth (``/<robot>/truth/odom``) moved
``--distance``. Prints one JSON line of what it saw: counts, values, the graph as rclpy sees it.
"""

import argparse
import hashlib
import json
import math
import sys
import time

import rclpy
import rclpy.clock
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, LaserScan, NavSatFix
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def ns(t):  # builtin_interfaces/Time -> ns
    return t.sec * 1_000_000_000 + t.nanosec


def endpoint(info):
    return {"node": info.node_name, "namespace": info.node_namespace, "type": info.topic_type,
            "hash": str(info.topic_type_hash), "reliability": info.qos_profile.reliability.name,
            "durability": info.qos_profile.durability.name, "depth": info.qos_profile.depth}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", required=True)
    ap.add_argument("--seconds", type=float, default=60.0, help="give up after this long (wall clock)")
    ap.add_argument("--settle", type=float, default=3.0, help="read this long after everything arrived")
    ap.add_argument("--drive", choices=["none", "trajectory", "cmd_vel"], default="none")
    ap.add_argument("--target", type=float, nargs="*", default=[])
    ap.add_argument("--distance", type=float, default=0.5)
    a = ap.parse_args()
    r = "/" + a.robot
    rclpy.init()
    node = Node("lab_node", parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, True)])
    seen = {"counts": {}, "truth_pairs": 0, "max_encoder_error": 0.0, "clock_checks": []}
    truth_by_stamp = {}
    js_by_stamp = {}
    last = {}

    def count(name):
        seen["counts"][name] = seen["counts"].get(name, 0) + 1

    clock_values: set[int] = set()  # every /clock the simulation sent us

    def on_clock(m):
        count("clock")
        last["clock"] = ns(m.clock)
        clock_values.add(last["clock"])

    def pair(encoders, truth):
        if len(truth) == len(encoders):
            seen["truth_pairs"] += 1
            seen["max_encoder_error"] = max(seen["max_encoder_error"],
                                            max(abs(x - y) for x, y in zip(encoders, truth, strict=True)))

    def remember(by_stamp, stamp, position):
        by_stamp[stamp] = position
        if len(by_stamp) > 2000:
            by_stamp.pop(next(iter(by_stamp)))

    # the two topics of one physics step arrive in either order (two writers): paired by stamp either way
    def on_truth_js(m):
        count("truth_joint_states")
        last["truth_js"] = m
        stamp = ns(m.header.stamp)
        if stamp in js_by_stamp:
            pair(js_by_stamp.pop(stamp), list(m.position))
        else:
            remember(truth_by_stamp, stamp, list(m.position))

    def on_js(m):
        count("joint_states")
        last["js"] = m
        stamp = ns(m.header.stamp)
        if stamp in truth_by_stamp:
            pair(list(m.position), truth_by_stamp.pop(stamp))
        else:
            remember(js_by_stamp, stamp, list(m.position))

    def keep(name):
        def cb(m):
            count(name)
            last[name] = m
        return cb

    node.create_subscription(Clock, "/clock", on_clock, qos_profile_sensor_data)
    node.create_subscription(JointState, f"{r}/joint_states", on_js, 10)
    node.create_subscription(JointState, f"{r}/truth/joint_states", on_truth_js, 10)
    node.create_subscription(Imu, f"{r}/imu", keep("imu"), qos_profile_sensor_data)
    node.create_subscription(String, f"{r}/robot_description", keep("robot_description"), LATCHED)
    wanted = ["clock", "joint_states", "truth_joint_states", "imu", "robot_description"]
    if a.robot.startswith("rover"):
        node.create_subscription(Odometry, f"{r}/odom", keep("odom"), 10)
        node.create_subscription(Odometry, f"{r}/truth/odom", keep("truth_odom"), 10)
        node.create_subscription(LaserScan, f"{r}/scan", keep("scan"), qos_profile_sensor_data)
        node.create_subscription(NavSatFix, f"{r}/gps/fix", keep("gps"), qos_profile_sensor_data)
        wanted += ["odom", "truth_odom", "scan", "gps"]
    traj = node.create_publisher(JointTrajectory, f"{r}/joint_trajectory", 10)
    twist = node.create_publisher(Twist, f"{r}/cmd_vel", 10)

    state = {"t0": time.monotonic(), "done_at": None, "sent": False, "start_xy": None}

    def tick():  # 20 Hz: the checks and the driving, as a lab's node does it in a timer
        now = time.monotonic()
        sim_now = node.get_clock().now().nanoseconds
        # the node's own clock (use_sim_time) against the last /clock it was given; 0 until rclpy's own
        # /clock subscription has taken its first one (on a loaded machine, after ours had)
        if "clock" in last and sim_now and len(seen["clock_checks"]) < 20:
            seen["clock_checks"].append([sim_now, last["clock"]])
        have_all = all(seen["counts"].get(w, 0) > 0 for w in wanted)
        drive_done = True
        if a.drive == "trajectory":
            drive_done = False
            if "truth_js" in last:
                if not state["sent"] and traj.get_subscription_count() > 0:
                    m = JointTrajectory()
                    m.joint_names = list(last["truth_js"].name)
                    m.points = [JointTrajectoryPoint(positions=list(a.target))]
                    m.points[0].time_from_start.sec = 2
                    traj.publish(m)
                    state["sent"] = True
                err = max(abs(x - y) for x, y in zip(last["truth_js"].position, a.target, strict=True))
                seen["trajectory_error"] = err
                drive_done = state["sent"] and err < 0.01
        if a.drive == "cmd_vel":
            drive_done = False
            if "truth_odom" in last:
                p = last["truth_odom"].pose.pose.position
                if state["start_xy"] is None:
                    state["start_xy"] = (p.x, p.y)
                seen["moved"] = math.hypot(p.x - state["start_xy"][0], p.y - state["start_xy"][1])
                drive_done = seen["moved"] >= a.distance
                if not drive_done and twist.get_subscription_count() > 0:
                    m = Twist()
                    m.linear.x = 0.5
                    twist.publish(m)
                    count("twist_sent")
        if have_all and drive_done and state["done_at"] is None:
            state["done_at"] = now
        if (state["done_at"] is not None and now - state["done_at"] > a.settle) or now - state["t0"] > a.seconds:
            raise SystemExit  # out of rclpy.spin

    node.create_timer(0.05, tick, clock=rclpy.clock.Clock())  # wall clock: sim time may run at any pace
    try:
        rclpy.spin(node)
    except SystemExit:
        pass
    done_at = state["done_at"]
    seen["stage"] = "done" if done_at is not None else "timeout"
    seen["node_clock_ns"] = node.get_clock().now().nanoseconds
    seen["last_clock_ns"] = last.get("clock")
    # rclpy's time is set from /clock messages (no interpolation): each reading is a value the simulation sent,
    # whichever of rclpy's subscription and ours took a given message first (or within what it sent, should
    # one best-effort reader have missed a message the other got, or before our first: rclpy's time source
    # matched the writer a moment before our subscription did, CI: 1.368 s read, our first /clock 1.374 s);
    # never beyond the newest, and never the wall clock
    hi = max(clock_values) if clock_values else -1
    seen["clock_checks_sent"] = [now in clock_values or 0 < now <= hi for now, _ in seen["clock_checks"]]
    if "js" in last:
        seen["joint_states"] = {"names": list(last["js"].name), "position": list(last["js"].position)}
    if "truth_js" in last:
        seen["truth_joint_states"] = {"names": list(last["truth_js"].name),
                                      "position": list(last["truth_js"].position)}
    if "imu" in last:
        m = last["imu"]
        q = m.orientation
        seen["imu"] = {"frame_id": m.header.frame_id, "q_norm": math.sqrt(q.x**2 + q.y**2 + q.z**2 + q.w**2),
                       "accel_norm": math.sqrt(m.linear_acceleration.x**2 + m.linear_acceleration.y**2
                                               + m.linear_acceleration.z**2)}
    if "robot_description" in last:
        text = last["robot_description"].data
        seen["robot_description"] = {"bytes": len(text), "robot": "<robot " in text,
                                     "whole": text.rstrip().endswith("</robot>"),
                                     "sha256": hashlib.sha256(text.encode()).hexdigest()}
    for k in ("odom", "truth_odom"):
        if k in last:
            m = last[k]
            seen[k] = {"frame_id": m.header.frame_id, "child_frame_id": m.child_frame_id,
                       "x": m.pose.pose.position.x, "y": m.pose.pose.position.y, "vx": m.twist.twist.linear.x}
    if "scan" in last:
        m = last["scan"]
        seen["scan"] = {"frame_id": m.header.frame_id, "n": len(m.ranges), "range_min": m.range_min,
                        "range_max": m.range_max, "angle_min": m.angle_min, "angle_max": m.angle_max,
                        "angle_increment": m.angle_increment,
                        "in_range": sum(1 for x in m.ranges if m.range_min <= x <= m.range_max)}
    if "gps" in last:
        m = last["gps"]
        seen["gps"] = {"latitude": m.latitude, "longitude": m.longitude, "altitude": m.altitude,
                       "status": m.status.status, "stamp": ns(m.header.stamp)}
    # the graph, as rclpy builds it
    seen["nodes"] = sorted(f"{n_ns.rstrip('/')}/{n}" for n, n_ns in node.get_node_names_and_namespaces())
    seen["publishers"] = {t: [endpoint(i) for i in node.get_publishers_info_by_topic(t)]
                          for t in ("/clock", f"{r}/joint_states", f"{r}/imu")}
    seen["subscriptions"] = {t: [endpoint(i) for i in node.get_subscriptions_info_by_topic(t)]
                             for t in (f"{r}/joint_trajectory", f"{r}/cmd_vel")}
    print(json.dumps(seen), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
