"""builtin_interfaces / std_msgs / rosgraph_msgs, and the sim-time helpers.

Sim time is integer nanoseconds everywhere in hilsim; :func:`stamp` and :func:`ns_of` convert
to and from ROS ``Time``.
"""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import int32, uint32


@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Duration(IdlStruct, typename="builtin_interfaces/msg/Duration"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs/msg/String"):
    data: str = ""


@dataclass
class Clock(IdlStruct, typename="rosgraph_msgs/msg/Clock"):
    clock: Time = field(default_factory=Time)


# ---------------------------------------------------------------- time helpers
def stamp(ns: int) -> Time:
    """Sim time in integer nanoseconds -> ROS Time."""
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def ns_of(t: Time | Duration) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def seconds(t: Time | Duration) -> float:
    return int(t.sec) + int(t.nanosec) * 1e-9


def duration(s: float) -> Duration:
    ns = round(s * 1e9)
    return Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(ns: int, frame_id: str = "") -> Header:
    return Header(stamp=stamp(ns), frame_id=frame_id)
