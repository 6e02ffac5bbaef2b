"""A real ROS 2 node (rclpy, Kilted, rmw_fastrtps_cpp) that commands the arm with stamped trajectories.

Runs under a ROS 2 venv's Python and imports nothing of hilsim (tests/test_ros2_timing.py starts it in a
network namespace beside ``hilsim up arm --hil config/ros2/dds.yaml``). It reads the physics truth
(``/arm/truth/joint_states``, every sample with its sim-time stamp) and publishes on
``/arm/joint_trajectory``:

- ``--mode wall``: as a lab's node *not* on sim time does, one trajectory stamped with its wall clock
  (``use_sim_time`` false), to 0.4 rad beyond where joint_1 is; then it watches the truth until it is at
  ``--until`` (the planner's task's last target);
- ``--mode timing`` (``use_sim_time`` true): one trajectory stamped 2 s of sim time after the truth's
  latest stamp (``ahead``); once done, one to a far target over 3 s (``long``) and, 1 s of sim time into
  it, a newer one stamped 0 (now) to a near target (``newer``).

Prints one JSON line: the truth it saw (stamps and joint_1), what it sent and when, and the truth at the end.
"""

import argparse
import json
import sys
import time

import rclpy
import rclpy.clock
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint


def ns(t):
    return t.sec * 1_000_000_000 + t.nanosec


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["wall", "timing"], required=True)
    ap.add_argument("--seconds", type=float, default=150.0)
    ap.add_argument("--until", type=float, nargs="*", default=[], help="wall mode: watch until the truth is "
                    "within 0.01 rad of these joint positions (the task's last target)")
    a = ap.parse_args()
    rclpy.init()
    sim = a.mode == "timing"
    node = Node("lab_timing_node", parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, sim)])
    truth = []  # (stamp ns, positions)
    names = []

    def on_truth(m):
        if not names:
            names.extend(m.name)
        truth.append((ns(m.header.stamp), list(m.position)))

    node.create_subscription(JointState, "/arm/truth/joint_states", on_truth, 100)
    pub = node.create_publisher(JointTrajectory, "/arm/joint_trajectory", 10)
    sent = {}
    state = {"t0": time.monotonic(), "phase": "wait", "done": False}

    def trajectory(stamp_ns, target, seconds):
        m = JointTrajectory()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        m.joint_names = list(names)
        m.points = [JointTrajectoryPoint(positions=list(target))]
        m.points[0].time_from_start.sec, m.points[0].time_from_start.nanosec = divmod(round(seconds * 1e9),
                                                                                       1_000_000_000)
        return m

    def send(name, stamp_ns, target, seconds):
        now = truth[-1][0]
        pub.publish(trajectory(stamp_ns, target, seconds))
        sent[name] = {"stamp": stamp_ns, "sim_at_send": now, "start": truth[-1][1], "target": list(target),
                      "seconds": seconds}

    def tick():
        if time.monotonic() - state["t0"] > a.seconds:
            raise SystemExit
        if len(truth) < 10 or pub.get_subscription_count() == 0:
            return
        now, q = truth[-1]
        ph = state["phase"]
        if a.mode == "wall":
            if ph == "wait":
                wall = node.get_clock().now().nanoseconds  # not on sim time: the wall clock
                send("wall", wall, [q[0] + 0.4, *q[1:]], 1.0)
                state["phase"] = "watch"
            elif max(abs(x - y) for x, y in zip(q, a.until, strict=True)) < 0.01:
                state["phase"] = "reached"
                raise SystemExit
            return
        if ph == "wait":
            send("ahead", now + 2_000_000_000, [q[0] + 0.3, *q[1:]], 0.5)
            state["phase"] = "ahead"
        elif ph == "ahead" and now >= sent["ahead"]["stamp"] + 1_500_000_000:
            send("long", now + 100_000_000, [q[0] - 0.8, *q[1:]], 3.0)
            state["phase"] = "long"
        elif ph == "long" and now >= sent["long"]["stamp"] + 1_000_000_000:
            send("newer", 0, [q[0] + 0.2, *q[1:]], 1.0)
            state["phase"] = "newer"
        elif ph == "newer" and now >= sent["newer"]["sim_at_send"] + 4_000_000_000:
            raise SystemExit

    node.create_timer(0.02, tick, clock=rclpy.clock.Clock())  # wall clock: sim time may run at any pace
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        ex.spin()
    except SystemExit:
        pass
    done = (a.mode == "wall" and state["phase"] == "reached") or (a.mode == "timing" and state["phase"] == "newer")
    # joint_1 only, every sample (the others do not move): what the test judges
    print(json.dumps({"stage": "done" if done else f"timeout in {state['phase']}", "names": names, "sent": sent,
                      "truth": [(t, p[0]) for t, p in truth], "last": truth[-1][1] if truth else None}), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
