"""A ROS 2 node on DDS as a lab's would be, without ROS: Cyclone DDS (the ``cyclonedds`` binding) with the
ROS 2 types written here from their ``.msg`` definitions, under the names rmw implementations give
them on DDS (``geometry_msgs::msg::dds_::Twist_`` on ``rt/<topic>``), XCDR1 and ROS 2's QoS. Nothing
of hilsim is imported: the bridge is judged by an independent reader and writer.

    python tests/dds_peer.py --domain N --robot rover [--timeout S]

Subscribes ``rt/<robot>/odom`` (reliable, keep-last 10), ``rt/<robot>/truth/odom``, ``rt/<robot>/scan``
(best effort, keep-last 5, as a lab subscribes a driver's scan; and a reliable reader, which must
not match a sensor topic), ``rt/<robot>/cmd_vel`` (what comes back of its own commands) and, as a
late joiner, ``rt/tf_static`` (transient local, as tf2 listens); waits for
odom, truth and scan; writes one Twist with a NaN (which the bridge must reject), then
``linear.x = 0.5`` until the truth has moved 0.5 m. Prints one JSON line of what it saw.
"""

# (no `from __future__ import annotations`: cyclonedds reads the field types of the classes at run time)
import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


# ------------------------------------------------------------------ ROS 2 (Jazzy) types, by hand
@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Point_(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose_(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point_ = field(default_factory=Point_)
    orientation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class PoseWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose_ = field(default_factory=Pose_)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Twist_(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3_ = field(default_factory=Vector3_)
    angular: Vector3_ = field(default_factory=Vector3_)


@dataclass
class TwistWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist_ = field(default_factory=Twist_)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Odometry_(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header_ = field(default_factory=Header_)
    child_frame_id: str = ""
    pose: PoseWithCovariance_ = field(default_factory=PoseWithCovariance_)
    twist: TwistWithCovariance_ = field(default_factory=TwistWithCovariance_)


@dataclass
class LaserScan_(IdlStruct, typename="sensor_msgs::msg::dds_::LaserScan_"):
    header: Header_ = field(default_factory=Header_)
    angle_min: t.float32 = 0.0
    angle_max: t.float32 = 0.0
    angle_increment: t.float32 = 0.0
    time_increment: t.float32 = 0.0
    scan_time: t.float32 = 0.0
    range_min: t.float32 = 0.0
    range_max: t.float32 = 0.0
    ranges: t.sequence[t.float32] = field(default_factory=list)
    intensities: t.sequence[t.float32] = field(default_factory=list)


@dataclass
class Transform_(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3_ = field(default_factory=Vector3_)
    rotation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class TransformStamped_(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header_ = field(default_factory=Header_)
    child_frame_id: str = ""
    transform: Transform_ = field(default_factory=Transform_)


@dataclass
class TFMessage_(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped_] = field(default_factory=list)


def qos(reliable: bool, depth: int, ignore_local: bool = False, transient_local: bool = False) -> Qos:
    """ROS 2's profiles on DDS (rmw_qos_profile_default / sensor_data; tf2's static listener), XCDR1 as
    the RMWs write."""
    p = [Policy.Reliability.Reliable(duration(milliseconds=100)) if reliable else Policy.Reliability.BestEffort,
         Policy.Durability.TransientLocal if transient_local else Policy.Durability.Volatile,
         Policy.History.KeepLast(depth), Policy.DataRepresentation(use_cdrv0_representation=True)]
    if ignore_local:
        p.append(Policy.IgnoreLocal.Participant)
    return Qos(*p)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--domain", type=int, required=True)
    ap.add_argument("--robot", default="rover")
    ap.add_argument("--timeout", type=float, default=90.0)
    a = ap.parse_args()
    ns = f"rt/{a.robot}"
    dp = DomainParticipant(a.domain)
    topics = {n: Topic(dp, f"{ns}/{n}", ty) for n, ty in
              (("odom", Odometry_), ("truth/odom", Odometry_), ("scan", LaserScan_), ("cmd_vel", Twist_))}
    tf_static = Topic(dp, "rt/tf_static", TFMessage_)
    readers = {
        "odom": DataReader(dp, topics["odom"], qos=qos(True, 10)),
        "truth": DataReader(dp, topics["truth/odom"], qos=qos(True, 10)),
        "scan": DataReader(dp, topics["scan"], qos=qos(False, 5)),
        "scan_reliable": DataReader(dp, topics["scan"], qos=qos(True, 10)),
        "cmd_vel_back": DataReader(dp, topics["cmd_vel"], qos=qos(True, 10, ignore_local=True)),
        # sent once, long before this reader came: transient local keeps it for late joiners
        "tf_static": DataReader(dp, tf_static, qos=qos(True, 100, transient_local=True)),
    }
    cmd = DataWriter(dp, topics["cmd_vel"], qos=qos(True, 10))
    last: dict[str, object] = {}
    count = dict.fromkeys(readers, 0)
    end = time.monotonic() + a.timeout
    out: dict[str, object] = {"stage": "start"}

    def poll() -> None:
        for name, r in readers.items():
            for s in r.take(64):
                if isinstance(s, IdlStruct):
                    last[name] = s
                    count[name] += 1

    def say(stage: str) -> int:
        out.update(stage=stage, counts=count)
        print(json.dumps(out), flush=True)
        return 0

    while not all(count[k] > 2 for k in ("odom", "truth", "scan")):
        if time.monotonic() > end:
            return say("no odom, truth or scan")
        poll()
        time.sleep(0.02)
    start = last["truth"].pose.pose.position  # type: ignore[attr-defined]
    while not cmd.get_matched_subscriptions():
        if time.monotonic() > end:
            return say("cmd_vel not matched")
        poll()
        time.sleep(0.02)
    cmd.write(Twist_(linear=Vector3_(x=math.nan)))  # bad input: rejected, the bridge goes on
    go = Twist_(linear=Vector3_(x=0.5))
    moved = 0.0
    next_put = 0.0
    while moved < 0.5:
        if time.monotonic() > end:
            out["moved"] = moved
            return say("did not move")
        now = time.monotonic()
        if now >= next_put:
            cmd.write(go)
            next_put = now + 0.25
        poll()
        p = last["truth"].pose.pose.position  # type: ignore[attr-defined]
        moved = math.hypot(p.x - start.x, p.y - start.y)
        time.sleep(0.02)
    time.sleep(0.5)
    poll()
    odom, scan, truth, static = last["odom"], last["scan"], last["truth"], last.get("tf_static")
    out.update(
        moved=moved,
        odom={"frame_id": odom.header.frame_id, "child_frame_id": odom.child_frame_id,  # type: ignore[attr-defined]
              "vx": odom.twist.twist.linear.x, "stamp": odom.header.stamp.sec + odom.header.stamp.nanosec * 1e-9,  # type: ignore[attr-defined]
              "x": odom.pose.pose.position.x, "qw": odom.pose.pose.orientation.w},  # type: ignore[attr-defined]
        truth={"frame_id": truth.header.frame_id, "x": truth.pose.pose.position.x,  # type: ignore[attr-defined]
               "y": truth.pose.pose.position.y},  # type: ignore[attr-defined]
        scan={"frame_id": scan.header.frame_id, "n": len(scan.ranges), "angle_min": scan.angle_min,  # type: ignore[attr-defined]
              "angle_max": scan.angle_max, "angle_increment": scan.angle_increment,  # type: ignore[attr-defined]
              "range_min": scan.range_min, "range_max": scan.range_max,  # type: ignore[attr-defined]
              "in_range": sum(1 for r in scan.ranges if scan.range_min <= r <= scan.range_max),  # type: ignore[attr-defined]
              "nan": sum(1 for r in scan.ranges if math.isnan(r))},  # type: ignore[attr-defined]
        tf_static=sorted(f"{x.header.frame_id}->{x.child_frame_id}" for x in static.transforms) if static else [],  # type: ignore[attr-defined]
    )
    return say("done")


if __name__ == "__main__":
    sys.exit(main())
