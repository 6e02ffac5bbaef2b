"""The ROS 2 side of ``hilsim bench ros2``: run by a ROS 2 Python (rclpy), never imported by hilsim.

    python ros2_probe.py sub --count N [--seconds S]       # subscribe /bench/joint_states, print latencies
    python ros2_probe.py pub --count N --rate HZ --cdr HEX  # publish the CDR bytes as they are (rclpy's raw publish)

A sample's header stamp is the wall-clock time it was written (both writers patch it into the same CDR
bytes before each write), so the subscriber's latency is its arrival time minus the stamp. ``pub``
measures the CPU its writes cost (process time around the publish calls): the DDS half of a bridge
built on rclpy, against the Cyclone DDS bridge's own write (``hilsim.tools.bench.ros2``). Prints one
JSON line.
"""

import argparse
import json
import struct
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState

TOPIC = "/bench/joint_states"
QOS = QoSProfile(depth=1000)  # reliable, volatile; deep enough that nothing is lost at the bench's rates


def stamp(cdr: bytearray, t_ns: int) -> None:
    """header.stamp (int32 sec, uint32 nanosec, little endian, right after the 4-byte encapsulation)."""
    struct.pack_into("<iI", cdr, 4, t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def sub(a: argparse.Namespace) -> dict:
    node = Node("bench_sub")
    lat: list[int] = []

    def on(m: JointState) -> None:
        lat.append(time.time_ns() - (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec))

    node.create_subscription(JointState, TOPIC, on, QOS)
    print(json.dumps({"ready": True}), flush=True)
    end = time.monotonic() + a.seconds
    while len(lat) < a.count and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    return {"received": len(lat), "latency_ns": lat}


def pub(a: argparse.Namespace) -> dict:
    node = Node("bench_pub")
    p = node.create_publisher(JointState, TOPIC, QOS)
    end = time.monotonic() + 30
    while p.get_subscription_count() == 0 and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    time.sleep(1.0)  # let the match settle on both sides, as the Cyclone writer gets it
    cdr = bytearray(bytes.fromhex(a.cdr))
    period = 1.0 / a.rate
    cpu = 0.0
    t_next = time.monotonic()
    for _ in range(a.count):
        t_next += period
        c0 = time.process_time()
        stamp(cdr, time.time_ns())
        p.publish(bytes(cdr))
        cpu += time.process_time() - c0
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(1.0)  # the last samples' acknowledgements
    return {"written": a.count, "cpu_s": cpu}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["sub", "pub"])
    ap.add_argument("--count", type=int, required=True)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--cdr", default="")
    a = ap.parse_args()
    rclpy.init()
    out = sub(a) if a.mode == "sub" else pub(a)
    print(json.dumps(out), flush=True)
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
