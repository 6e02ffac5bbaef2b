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
_HDR = struct.Struct("<iII")  # a Header's stamp and its frame id's length
_D6 = struct.Struct("<6d")
_D7 = struct.Struct("<7d")
# Odometry after its strings: pose (position, orientation, 36 covariances), twist (linear,
# angular, 36 covariances): 85 doubles in a row, every one 8-aligned
_D85 = struct.Struct("<85d")
# Imu after its header: orientation, its covariance, angular velocity, its covariance, linear
# acceleration, its covariance: 37 doubles in a row, every one 8-aligned; one Struct per padding before
_IMU = [struct.Struct(f"<{p}x37d") for p in range(8)]
_D37 = _IMU[0]


def _tail(offset: int, counts: tuple[int, ...]) -> struct.Struct:
    """The layout of sequences of doubles with these ``counts``, starting ``offset`` bytes (mod 8) after
    the encapsulation header: each a u32 count (4-aligned) and its doubles (8-aligned), padding included,
    so a JointState's three arrays are packed and unpacked in one call."""
    fmt, o = "<", offset
    for n in counts:
        p = -o % 4
        fmt += f"{p}xI"
        o += p + 4
        if n:
            p = -o % 8
            fmt += f"{p}x{n}d"
            o += p + 8 * n
    return struct.Struct(fmt)


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
    # the header opens its message or follows a count or doubles (4-aligned): stamp and length in one
    b = h.frame_id.encode()
    buf += _HDR.pack(h.stamp.sec, h.stamp.nanosec, len(b) + 1)
    buf += b
    buf += b"\0"


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
        # stamp and the frame id's length in one unpack (a header starts 4-aligned)
        data, at = r.data, r.pos
        sec, ns, n = _HDR.unpack_from(data, at)
        end = at + 12 + n
        if n < 1 or end > len(data) or data[end - 1] != 0:
            raise ValueError(f"bad string of length {n} at byte {at + 12}")
        r.pos = end
        return Header(stamp=Time(sec=sec, nanosec=ns), frame_id=data[at + 12:end - 1].decode())

    # A robot's joint names are the same in every JointState: their encoded block is kept per
    # (names, alignment) and copied in, and a decoder that meets one of the last blocks it decoded
    # reuses their names (one bytes comparison instead of a u32 and a string per joint).
    name_blocks: dict[tuple[tuple[str, ...], int], bytes] = {}
    seen_names: list[tuple[int, bytes, tuple[str, ...]]] = []  # (alignment, block, names), newest first

    # Its arrays' layout is the same from message to message too (the counts, and where they start
    # modulo 8): one Struct per layout packs or unpacks all three at once (pre-built, bounded).
    tails: dict[tuple[int, int, int, int], struct.Struct] = {}

    def tail(off: int, a: int, b: int, c: int) -> struct.Struct:
        key = (off, a, b, c)
        t = tails.get(key)
        if t is None:
            t = _tail(off, (a, b, c))
            if len(tails) < 256:
                tails[key] = t
        return t

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
        pos, vel, eff = msg.position, msg.velocity, msg.effort
        buf += tail((len(buf) - 4) % 8, len(pos), len(vel), len(eff)).pack(
            len(pos), *pos, len(vel), *vel, len(eff), *eff)
        return bytes(buf)

    # the last layout met at each (offset, first count): tried first, its counts checked after
    seen_tails: dict[tuple[int, int], tuple[struct.Struct, int, int]] = {}

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
        off = (r.pos - 4) % 8
        first = r.pos + (-(r.pos - 4) % 4)
        n = _U32.unpack_from(data, first)[0] if first + 4 <= len(data) else -1
        known = seen_tails.get((off, n))
        if known is not None:
            t, b, c = known
            if t.size <= len(data) - r.pos:
                v = t.unpack_from(data, r.pos)
                if v[n + 1] == b and v[n + b + 2] == c:  # the layout it claims: one call for all three
                    msg = JointState(header=h, name=name, position=list(v[1:n + 1]),
                                     velocity=list(v[n + 2:n + b + 2]), effort=list(v[n + b + 3:]))
                    return msg, r.pos + t.size
        position, velocity, effort = r.dseq(), r.dseq(), r.dseq()
        if len(seen_tails) < 256:
            seen_tails[(off, len(position))] = (tail(off, len(position), len(velocity), len(effort)),
                                                len(velocity), len(effort))
        return JointState(header=h, name=name, position=position, velocity=velocity, effort=effort), r.pos

    def enc_imu(msg: Any) -> bytes:
        buf = bytearray(HEADER_LE)
        _w_header(buf, msg.header)
        o, av, la = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        buf += _IMU[-(len(buf) - 4) % 8].pack(o.x, o.y, o.z, o.w, *msg.orientation_covariance,
                                              av.x, av.y, av.z, *msg.angular_velocity_covariance,
                                              la.x, la.y, la.z, *msg.linear_acceleration_covariance)
        return bytes(buf)

    def dec_imu(data: bytes) -> tuple[Any, int]:
        r = _Reader(data)
        h = header(r)
        r.align(8)
        v = _D37.unpack_from(data, r.pos)
        msg = Imu(
            header=h,
            orientation=Quaternion(x=v[0], y=v[1], z=v[2], w=v[3]),
            orientation_covariance=list(v[4:13]),
            angular_velocity=Vector3(x=v[13], y=v[14], z=v[15]),
            angular_velocity_covariance=list(v[16:25]),
            linear_acceleration=Vector3(x=v[25], y=v[26], z=v[27]),
            linear_acceleration_covariance=list(v[28:37]),
        )
        return msg, r.pos + _D37.size

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
