"""The recorder's fast path (``RowWriter.raw``/``learn``/``drain``): clock, joint state and IMU
payloads read straight into columns give exactly the rows of the per-message path (decode,
validate, ``RowWriter.message``), a non-finite sample in the middle of a batch included."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

from hilsim.core import msgs
from hilsim.record.rows import RowWriter
from hilsim.sim.kinematics import RobotModel

ROOT = Path(__file__).resolve().parents[1]

PREFIX = "hilsim"
JOINTS = [f"joint_{i}" for i in range(1, 7)]


class _Rec:
    """Stands in for a RecordingStream: keeps what ``send_columns`` sent, as plain rows."""

    def __init__(self) -> None:
        self.rows: dict[str, list[tuple[int, Any]]] = {}

    def send_columns(self, entity: str, indexes: Any, columns: Any) -> None:
        times = indexes[0].as_arrow_array().cast("int64").to_pylist()
        cols = [c.as_arrow_array().flatten().to_pylist() for c in columns]
        self.rows.setdefault(entity, []).extend(zip(times, zip(*cols, strict=True), strict=True))

    def log(self, *args: Any, **kwargs: Any) -> None:
        pass

    def set_time(self, *args: Any, **kwargs: Any) -> None:
        pass


Rows = dict[str, list[tuple[int, Any]]]


def _feed(samples: list[tuple[str, bytes]], fast: bool, model: RobotModel | None = None) -> tuple[Rows, list[str]]:
    """Rows and rejected keys of ``samples`` as the recorder turns them into rows, with or without the fast path."""
    rec = _Rec()
    w = RowWriter(rec, "arm", model, lambda *a, **k: None)  # type: ignore[arg-type]
    rejected: list[str] = []
    for i, (key, data) in enumerate(samples):
        if not (fast and w.raw(key, data)):
            cls = msgs.Clock if key.count("/") == 1 else (msgs.Imu if key.endswith("imu") else msgs.JointState)
            try:
                msg = msgs.decode(cls, data)
            except msgs.BadMessage as e:
                rejected.append(key)
                w.rejected(key, len(data), e)
                continue
            w.message(key, msg)
            if fast:
                w.learn(key, data, msg)
        if i % 97 == 0:  # several batches
            w.flush()
    w.flush()
    rejected += [k for k, _ in w.rejections]
    return {e: sorted(r) for e, r in rec.rows.items()}, sorted(rejected)


def _samples(seed: int) -> list[tuple[str, bytes]]:
    rnd = random.Random(seed)
    out: list[tuple[str, bytes]] = []
    for k in range(400):
        t = 1_000_000 * k + rnd.randrange(1000)
        out.append((f"{PREFIX}/clock", msgs.encode(msgs.Clock(clock=msgs.Time(sec=t // 10**9, nanosec=t % 10**9)))))
        q = [rnd.uniform(-3, 3) for _ in JOINTS]
        for topic in ("truth/joint_states", "joint_states"):
            js = msgs.JointState(header=msgs.header(t), name=list(JOINTS), position=list(q),
                                 velocity=[rnd.gauss(0, 1) for _ in JOINTS], effort=[rnd.gauss(0, 5) for _ in JOINTS])
            if k in (150, 151) and topic == "joint_states":
                js.velocity[2] = float("nan")  # rejected, in the middle of a batch
            out.append((f"{PREFIX}/arm/{topic}", msgs.encode(js)))
        cmd = msgs.JointState(header=msgs.header(t), name=list(JOINTS), effort=[rnd.gauss(0, 5) for _ in JOINTS])
        if k == 200:
            cmd.name = ["a", "b"]  # another layout: the ordinary way (and rejected there: 2 names, 6 efforts)
        out.append((f"{PREFIX}/arm/joint_commands", msgs.encode(cmd)))
        imu = msgs.Imu(header=msgs.header(t, "imu_link"),
                       orientation=msgs.Quaternion(x=rnd.random(), y=rnd.random(), z=rnd.random(), w=rnd.random()),
                       angular_velocity=msgs.Vector3(x=rnd.gauss(0, 1), y=rnd.gauss(0, 1), z=rnd.gauss(0, 1)),
                       linear_acceleration=msgs.Vector3(x=rnd.gauss(0, 1), y=rnd.gauss(0, 1), z=9.81))
        if k == 300:
            imu.linear_acceleration_covariance = [float("inf")] + [0.0] * 8  # not recorded, but checked
        if k == 310:
            imu.header.frame_id = "other_link"  # another layout, valid: recorded the ordinary way
        out.append((f"{PREFIX}/other/imu", msgs.encode(imu)))
    return out


def test_fast_path_gives_the_rows_of_the_message_path() -> None:
    samples = _samples(7)
    model = RobotModel.load(ROOT / "models/arm/arm.urdf")
    slow, slow_rejected = _feed(samples, fast=False, model=model)
    fast, fast_rejected = _feed(samples, fast=True, model=model)
    assert fast_rejected == slow_rejected == sorted(
        [f"{PREFIX}/arm/joint_states"] * 2 + [f"{PREFIX}/arm/joint_commands", f"{PREFIX}/other/imu"])
    assert fast.keys() == slow.keys()
    for entity in slow:
        assert fast[entity] == slow[entity], entity
    # the rows are there: 400 clocks, 6 joints x 3 quantities, the robot "other"'s IMU
    assert len(slow["clock"]) == 400
    assert len(slow["joints/joint_3/velocity/measured"]) == 398
    assert len(slow["robots/other/imu/measured/linear_acceleration/z"]) == 399
    assert len(slow["rejected/hilsim\\/arm\\/joint_states"]) == 2
    assert 30 <= len(slow["robot/joint_transforms/joint_2"]) <= 40  # the truth every 10 ms of 400 ms


def test_fast_path_rejects_like_decode() -> None:
    """The reason a fast-path sample is rejected for is the one decode gives."""
    js = msgs.JointState(header=msgs.header(5), name=list(JOINTS), position=[0.0] * 6)
    bad = msgs.JointState(header=msgs.header(6), name=list(JOINTS), position=[0.0] * 5 + [float("nan")])
    w = RowWriter(_Rec(), "arm", None, lambda *a, **k: None)  # type: ignore[arg-type]
    key = f"{PREFIX}/arm/joint_states"
    data = msgs.encode(js)
    w.message(key, msgs.decode(msgs.JointState, data))
    w.learn(key, data, js)
    assert w.raw(key, msgs.encode(bad))
    w.flush()
    assert [(k, str(e)) for k, e in w.rejections] == [(key, "position contains a non-finite value (nan)")]
    assert w.raw(key, data[:-8]) is False  # another size: the ordinary way
