"""Hand-unrolled CDR for the few message types that cross the wire every physics step.

pycdr2 stays the definition of every type and the codec for everything else; it is pure
Python and walks a type tree per message, which made encoding and decoding the largest share
of the lockstep loop's CPU time (see docs/performance.md). For ``rosgraph_msgs/Clock``,
``sensor_msgs/JointState`` and ``sensor_msgs/Imu`` (the arm's steps) and ``nav_msgs/Odometry``,
``tf2_msgs/TFMessage`` and ``geometry_msgs/Twist`` (the rover's) these functions produce and
accept exactly the bytes pycdr2 does (XCDR1, little-endian, 4-byte encapsulation header; alignment counted
from the end of the header) — ``tests/test_fastcdr.py`` holds them to that, byte for byte.

Decoders return ``(message, bytes consumed)`` and raise ``ValueError`` (or ``struct.error``)
on anything malformed; :func:`hilsim.core.msgs.decode` turns that into ``BadMessage``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from hilsim.core.msgs.builtin import Clock, Header, Time
from hilsim.core.msgs.geometry import (
    Odometry,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    TFMessage,
    Transform,
    TransformStamped,
    Twist,
    TwistWithCovariance,
    Vector3,
)
from hilsim.core.msgs.sensor import Imu, JointState

HEADER_LE = b"\x00\x01\x00\x00"
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")
_D4 = struct.Struct("<4d")
_D3 = struct.Struct("<3d")
_D9 = struct.Struct("<9d")
_D6 = struct.Struct("<6d")
_D7 = struct.Struct("<7d")
# Odometry after its strings: pose (position, orientation, 36 covariances), twist (linear,
# angular, 36 covariances): 85 doubles in a row, every one 8-aligned
_D85 = struct.Struct("<85d")


# ---------------------------------------------------------------- writing
def _pad(buf: bytearray, n: int) -> None:
    p = -(len(buf) - 4) % n
    if p:
        buf += b"\0" * p


def _w_u32(buf: bytearray, v: int) -> None:
    _pad(buf, 4)
    buf += _U32.pack(v)


def _w_str(buf: bytearray, s: str) -> None:
    b = s.encode()
    _w_u32(buf, len(b) + 1)
    buf += b
    buf += b"\0"


def _w_header(buf: bytearray, h: Any) -> None:
    buf += _TIME.pack(h.stamp.sec, h.stamp.nanosec)
    _w_str(buf, h.frame_id)


def _w_dseq(buf: bytearray, xs: Any) -> None:
    n = len(xs)
    _w_u32(buf, n)
    if n:
        _pad(buf, 8)
        buf += struct.pack(f"<{n}d", *xs)


def _w_darr(buf: bytearray, xs: Any, s: struct.Struct) -> None:
    _pad(buf, 8)
    buf += s.pack(*xs)


# ---------------------------------------------------------------- reading
class _Reader:
    __slots__ = ("data", "pos")

    def __init__(self, data: bytes) -> None:
        if data[:4] != HEADER_LE:
            raise ValueError("not little-endian XCDR1")
        self.data = data
        self.pos = 4

    def align(self, n: int) -> None:
        self.pos += -(self.pos - 4) % n

    def u32(self) -> int:
        self.align(4)
        v = _U32.unpack_from(self.data, self.pos)[0]
        self.pos += 4
        return int(v)

    def string(self) -> str:
        n = self.u32()
        end = self.pos + n
        if n < 1 or end > len(self.data) or self.data[end - 1] != 0:
            raise ValueError(f"bad string of length {n} at byte {self.pos}")
        s = self.data[self.pos:end - 1].decode()
        self.pos = end
        return s

    def time(self) -> tuple[int, int]:
        v = _TIME.unpack_from(self.data, self.pos)
        self.pos += 8
        return v

    def dseq(self) -> list[float]:
        n = self.u32()
        if not n:
            return []
        self.align(8)
        if self.pos + 8 * n > len(self.data):
            raise ValueError(f"sequence of {n} doubles runs past the end")
        v = list(struct.unpack_from(f"<{n}d", self.data, self.pos))
        self.pos += 8 * n
        return v

    def darr(self, s: struct.Struct) -> tuple[float, ...]:
        self.align(8)
        v = s.unpack_from(self.data, self.pos)
        self.pos += s.size
        return v

    def strseq(self) -> list[str]:
        n = self.u32()
        if n > len(self.data):
            raise ValueError(f"sequence of {n} strings in {len(self.data)} bytes")
        return [self.string() for _ in range(n)]


# ---------------------------------------------------------------- the hot types
def build() -> tuple[dict[type, Callable[[Any], bytes]], dict[type, Callable[[bytes], tuple[Any, int]]]]:
    """Encoders and decoders keyed by message class."""

    def enc_clock(msg: Any) -> bytes:
        return HEADER_LE + _TIME.pack(msg.clock.sec, msg.clock.nanosec)

    def dec_clock(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        sec, ns = r.time()
        return Clock(clock=Time(sec=sec, nanosec=ns)), r.pos

    def header(r: _Reader) -> Any:
        sec, ns = r.time()
        return Header(stamp=Time(sec=sec, nanosec=ns), frame_id=r.string())

    # A robot's joint names are the same in every JointState: their encoded block is kept per
    # (names, alignment) and copied in, and a decoder that meets one of the last blocks it decoded
    # reuses their names (one bytes comparison instead of a u32 and a string per joint).
    name_blocks: dict[tuple[tuple[str, ...], int], bytes] = {}
    seen_names: list[tuple[int, bytes, tuple[str, ...]]] = []  # (alignment, block, names), newest first

    def enc_joint_state(msg: Any) -> bytes:
        buf = bytearray(HEADER_LE)
        _w_header(buf, msg.header)
        key = (tuple(msg.name), (len(buf) - 4) % 4)
        block = name_blocks.get(key)
        if block is None:
            start = len(buf)
            _w_u32(buf, len(msg.name))
            for s in msg.name:
                _w_str(buf, s)
            if len(name_blocks) < 64:  # a bound: names that change every message are not cached
                name_blocks[key] = bytes(buf[start:])
        else:
            buf += block
        _w_dseq(buf, msg.position)
        _w_dseq(buf, msg.velocity)
        _w_dseq(buf, msg.effort)
        return bytes(buf)

    def dec_joint_state(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        h = header(r)
        start = r.pos
        align = (start - 4) % 4
        for a, block, names in seen_names:  # a few: truth, measurements, commands, references
            if a == align and data.startswith(block, start):
                r.pos = start + len(block)
                name = list(names)
                break
        else:
            name = r.strseq()
            seen_names.insert(0, (align, data[start:r.pos], tuple(name)))
            del seen_names[4:]
        msg = JointState(header=h, name=name, position=r.dseq(), velocity=r.dseq(), effort=r.dseq())
        return msg, r.pos

    def enc_imu(msg: Any) -> bytes:
        buf = bytearray(HEADER_LE)
        _w_header(buf, msg.header)
        o = msg.orientation
        _w_darr(buf, (o.x, o.y, o.z, o.w), _D4)
        _w_darr(buf, msg.orientation_covariance, _D9)
        for v, cov in ((msg.angular_velocity, msg.angular_velocity_covariance),
                       (msg.linear_acceleration, msg.linear_acceleration_covariance)):
            _w_darr(buf, (v.x, v.y, v.z), _D3)
            _w_darr(buf, cov, _D9)
        return bytes(buf)

    def dec_imu(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        h = header(r)
        q = r.darr(_D4)
        oc = list(r.darr(_D9))
        av = r.darr(_D3)
        avc = list(r.darr(_D9))
        la = r.darr(_D3)
        lac = list(r.darr(_D9))
        msg = Imu(
            header=h,
            orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
            orientation_covariance=oc,
            angular_velocity=Vector3(x=av[0], y=av[1], z=av[2]),
            angular_velocity_covariance=avc,
            linear_acceleration=Vector3(x=la[0], y=la[1], z=la[2]),
            linear_acceleration_covariance=lac,
        )
        return msg, r.pos

    def enc_odometry(msg: Any) -> bytes:
        buf = bytearray(HEADER_LE)
        _w_header(buf, msg.header)
        _w_str(buf, msg.child_frame_id)
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
        _w_darr(buf, (p.x, p.y, p.z, o.x, o.y, o.z, o.w, *msg.pose.covariance,
                      lin.x, lin.y, lin.z, ang.x, ang.y, ang.z, *msg.twist.covariance), _D85)
        return bytes(buf)

    def dec_odometry(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        h = header(r)
        child = r.string()
        v = r.darr(_D85)
        msg = Odometry(
            header=h, child_frame_id=child,
            pose=PoseWithCovariance(pose=Pose(position=Point(x=v[0], y=v[1], z=v[2]),
                                              orientation=Quaternion(x=v[3], y=v[4], z=v[5], w=v[6])),
                                    covariance=list(v[7:43])),
            twist=TwistWithCovariance(twist=Twist(linear=Vector3(x=v[43], y=v[44], z=v[45]),
                                                  angular=Vector3(x=v[46], y=v[47], z=v[48])),
                                      covariance=list(v[49:85])),
        )
        return msg, r.pos

    def enc_tf(msg: Any) -> bytes:
        buf = bytearray(HEADER_LE)
        _w_u32(buf, len(msg.transforms))
        for t in msg.transforms:  # each starts 4-aligned: after the count, or after 8-aligned doubles
            _w_header(buf, t.header)
            _w_str(buf, t.child_frame_id)
            tr, q = t.transform.translation, t.transform.rotation
            _w_darr(buf, (tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w), _D7)
        return bytes(buf)

    def dec_tf(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        n = r.u32()
        if n > len(data) // 24:  # a transform takes 24 bytes at the least: refuse a lying count early
            raise ValueError(f"sequence of {n} transforms in {len(data)} bytes")
        out = []
        for _ in range(n):
            r.align(4)
            h = header(r)
            child = r.string()
            v = r.darr(_D7)
            out.append(TransformStamped(header=h, child_frame_id=child, transform=Transform(
                translation=Vector3(x=v[0], y=v[1], z=v[2]), rotation=Quaternion(x=v[3], y=v[4], z=v[5], w=v[6]))))
        return TFMessage(transforms=out), r.pos

    def enc_twist(msg: Any) -> bytes:
        lin, ang = msg.linear, msg.angular
        return HEADER_LE + _D6.pack(lin.x, lin.y, lin.z, ang.x, ang.y, ang.z)

    def dec_twist(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        v = r.darr(_D6)
        return Twist(linear=Vector3(x=v[0], y=v[1], z=v[2]), angular=Vector3(x=v[3], y=v[4], z=v[5])), r.pos

    encoders = {Clock: enc_clock, JointState: enc_joint_state, Imu: enc_imu,
                Odometry: enc_odometry, TFMessage: enc_tf, Twist: enc_twist}
    decoders = {Clock: dec_clock, JointState: dec_joint_state, Imu: dec_imu,
                Odometry: dec_odometry, TFMessage: dec_tf, Twist: dec_twist}
    return encoders, decoders
