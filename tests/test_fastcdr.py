"""The fast codec of the per-step message types (the arm's and the rover's) gives exactly pycdr2's bytes
and messages."""

from __future__ import annotations

import random
import struct

import pytest

from hilsim.core import msgs

NAMES = ["joint_1", "j", "", "ä-joint", "x" * 37]


def _random_messages(rng: random.Random) -> list[msgs.IdlStruct]:
    out: list[msgs.IdlStruct] = []
    for _ in range(200):
        n = rng.randrange(0, 8)
        h = msgs.Header(stamp=msgs.Time(sec=rng.randrange(-5, 10**6), nanosec=rng.randrange(10**9)),
                        frame_id=rng.choice(NAMES)[: rng.randrange(0, 12)])
        out.append(msgs.JointState(
            header=h,
            name=[rng.choice(NAMES) for _ in range(n)],
            position=[rng.uniform(-4, 4) for _ in range(rng.choice([0, n]))],
            velocity=[rng.uniform(-4, 4) for _ in range(rng.choice([0, n]))],
            effort=[rng.uniform(-4, 4) for _ in range(rng.choice([0, n]))],
        ))
        v = [rng.uniform(-10, 10) for _ in range(40)]
        out.append(msgs.Imu(
            header=h,
            orientation=msgs.Quaternion(*v[0:4]),
            orientation_covariance=v[4:13],
            angular_velocity=msgs.Vector3(*v[13:16]),
            angular_velocity_covariance=v[16:25],
            linear_acceleration=msgs.Vector3(*v[25:28]),
            linear_acceleration_covariance=v[28:37],
        ))
        out.append(msgs.Clock(clock=h.stamp))
        # the rover's: odometry, transforms (any number, frame ids of every length), body velocity
        w = [rng.uniform(-10, 10) for _ in range(85)]
        out.append(msgs.Odometry(
            header=h, child_frame_id=rng.choice(NAMES)[: rng.randrange(0, 12)],
            pose=msgs.PoseWithCovariance(pose=msgs.Pose(position=msgs.Point(*w[0:3]),
                                                        orientation=msgs.Quaternion(*w[3:7])),
                                         covariance=w[7:43]),
            twist=msgs.TwistWithCovariance(twist=msgs.Twist(linear=msgs.Vector3(*w[43:46]),
                                                            angular=msgs.Vector3(*w[46:49])),
                                           covariance=w[49:85]),
        ))
        out.append(msgs.TFMessage(transforms=[
            msgs.TransformStamped(
                header=msgs.Header(stamp=msgs.Time(sec=rng.randrange(10**6), nanosec=rng.randrange(10**9)),
                                   frame_id=rng.choice(NAMES)[: rng.randrange(0, 12)]),
                child_frame_id=rng.choice(NAMES)[: rng.randrange(0, 12)],
                transform=msgs.Transform(translation=msgs.Vector3(*w[0:3]), rotation=msgs.Quaternion(*w[3:7])))
            for _ in range(rng.randrange(0, 6))]))
        out.append(msgs.Twist(linear=msgs.Vector3(*w[10:13]), angular=msgs.Vector3(*w[13:16])))
    return out


def test_same_bytes_and_messages_as_pycdr2() -> None:
    for m in _random_messages(random.Random(1)):
        ref = msgs.encode_reference(m)
        assert msgs.encode(m) == ref, m
        assert msgs.decode(type(m), ref) == m
        assert type(m).deserialize(msgs.encode(m)) == m


@pytest.mark.parametrize("cls", [msgs.JointState, msgs.Imu, msgs.Clock, msgs.Odometry, msgs.TFMessage, msgs.Twist])
def test_every_truncation_and_trailing_garbage_is_rejected(cls: type) -> None:
    m = next(x for x in _random_messages(random.Random(2)) if isinstance(x, cls) and len(msgs.encode(x)) > 11)
    data = msgs.encode(m)
    for cut in range(len(data)):
        with pytest.raises(msgs.BadMessage):
            msgs.decode(cls, data[:cut])
    with pytest.raises(msgs.BadMessage):
        msgs.decode(cls, data + b"\x00" * 8)


def test_lying_lengths_are_rejected() -> None:
    data = bytearray(msgs.encode(msgs.JointState(name=["a"], position=[1.0])))
    assert struct.unpack_from("<I", data, 20)[0] == 1  # the names count, after stamp and frame_id
    struct.pack_into("<I", data, 20, 10**9)  # now it claims a billion strings
    with pytest.raises(msgs.BadMessage):
        msgs.decode(msgs.JointState, bytes(data))
    tf = bytearray(msgs.encode(msgs.TFMessage(transforms=[msgs.TransformStamped(child_frame_id="a")])))
    struct.pack_into("<I", tf, 4, 10**9)  # a billion transforms
    with pytest.raises(msgs.BadMessage):
        msgs.decode(msgs.TFMessage, bytes(tf))


@pytest.mark.parametrize("names", [["joint_1", "joint_2", "joint_3"], [], ["ä-joint", ""]])
def test_the_cached_joint_name_block_is_right_at_every_alignment(names: list[str]) -> None:
    """The codec keeps a robot's encoded names and the last decoded ones: the same names after
    frame ids of every length (so at every alignment), alternating with other names, still give
    pycdr2's bytes and the message back."""
    for i in range(24):
        frame = "f" * (i % 9)
        for ns in (names, ["other"], names):
            m = msgs.JointState(header=msgs.Header(stamp=msgs.Time(sec=i, nanosec=7), frame_id=frame),
                                name=list(ns), position=[0.0] * len(ns), velocity=[], effort=[1.5] * len(ns))
            raw = msgs.encode(m)
            assert raw == msgs.codec.encode_reference(m)
            assert msgs.decode(msgs.JointState, raw) == m
