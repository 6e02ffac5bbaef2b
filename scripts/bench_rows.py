"""Records/s of the recorder's worker on one core: decoding plus turning messages into Rerun rows.

A synthetic message mix per physics step, as the real services publish it (the rover at 500 Hz
physics: truth/imu, truth/odom, tf, truth/joint_states, clock every step; joint_states, imu,
joint_commands, odom at 100 Hz; scan at 10 Hz; gps/fix at 5 Hz; the arm: its 1 kHz mix), is
encoded first, then decoded and written by ``hilsim.record.rows.RowWriter`` to a file, batched as
the logger does. No Zenoh: this measures what the worker thread costs per message, in its own CPU
time (records per CPU second of that thread).

    .venv/bin/python scripts/bench_rows.py rover 10000     # robot, physics steps

``HILSIM_SRC=/path/to/another/checkout`` measures that checkout's hilsim instead (before/after).
"""

from __future__ import annotations

import inspect
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, os.environ.get("HILSIM_SRC", str(REPO)))

from hilsim.core import msgs  # noqa: E402
from hilsim.core.keys import message_type  # noqa: E402
from hilsim.record.rows import RowWriter, rr  # noqa: E402
from hilsim.sim.kinematics import RobotModel  # noqa: E402

FLUSH_ROWS = 20_000  # as services/logger_worker.py


def rover_mix(steps: int, prefix: str) -> list[tuple[str, Any]]:
    joints = [f"{w}_{k}" for w in ("fl", "fr", "rl", "rr") for k in ("steering", "traction")]
    out: list[tuple[str, Any]] = []
    for k in range(steps):
        t = k * 2_000_000
        x = 0.0005 * k
        q = msgs.Quaternion(w=math.cos(0.0001 * k), z=math.sin(0.0001 * k))
        pose = msgs.Pose(position=msgs.Point(x=x, y=0.1 * x, z=0.25), orientation=q)
        js = msgs.JointState(header=msgs.header(t), name=joints, position=[0.01 * k] * 8, velocity=[0.1] * 8,
                             effort=[0.2] * 8)
        tfs = [msgs.TransformStamped(header=msgs.header(t, "world"), child_frame_id="base_link",
                                     transform=msgs.Transform(translation=msgs.Vector3(x=x, z=0.25), rotation=q))]
        tfs += [msgs.TransformStamped(header=msgs.header(t, "base_link"), child_frame_id=s, transform=msgs.Transform(
            translation=msgs.Vector3(x=0.3, z=0.1), rotation=msgs.Quaternion(w=1.0))) for s in ("imu", "laser", "gps")]
        out += [
            (prefix + "truth/imu", msgs.Imu(header=msgs.header(t))),
            (prefix + "truth/odom", msgs.Odometry(header=msgs.header(t, "world"), child_frame_id="base_link",
                                                  pose=msgs.PoseWithCovariance(pose=pose))),
            (prefix + "tf", msgs.TFMessage(transforms=tfs)),
            (prefix + "truth/joint_states", js),
            ("hilsim/clock", msgs.Clock(clock=msgs.stamp(t))),
        ]
        if k % 5 == 0:
            out += [
                (prefix + "joint_states", js),
                (prefix + "imu", msgs.Imu(header=msgs.header(t))),
                (prefix + "joint_commands", js),
                (prefix + "odom", msgs.Odometry(header=msgs.header(t, "odom"), child_frame_id="base_link",
                                                pose=msgs.PoseWithCovariance(pose=pose))),
            ]
        if k % 50 == 0:
            r = (5 + np.sin(np.arange(541) * 0.05)).tolist()
            r[3] = math.inf
            out.append((prefix + "scan", msgs.LaserScan(
                header=msgs.header(t, "laser"), angle_min=-2.356, angle_max=2.356, angle_increment=0.00872665,
                range_min=0.1, range_max=20.0, ranges=r)))
        if k % 100 == 0:
            out.append((prefix + "gps/fix", msgs.NavSatFix(header=msgs.header(t, "gps"), latitude=41.17788 + 1e-7 * k,
                                                           longitude=-8.59779, altitude=90.0)))
    return out


def arm_mix(steps: int, prefix: str) -> list[tuple[str, Any]]:
    joints = [f"joint_{i}" for i in range(1, 7)]
    out: list[tuple[str, Any]] = []
    for k in range(steps):
        t = k * 1_000_000
        js = msgs.JointState(header=msgs.header(t), name=joints, position=[0.001 * k] * 6, velocity=[0.1] * 6,
                             effort=[0.2] * 6)
        out += [(prefix + "truth/imu", msgs.Imu(header=msgs.header(t))), (prefix + "truth/joint_states", js),
                ("hilsim/clock", msgs.Clock(clock=msgs.stamp(t))), (prefix + "joint_states", js),
                (prefix + "joint_commands", js), (prefix + "sync/planner", msgs.Clock(clock=msgs.stamp(t)))]
        if k % 5 == 0:
            out.append((prefix + "imu", msgs.Imu(header=msgs.header(t))))
    return out


def main() -> None:
    robot = sys.argv[1] if len(sys.argv) > 1 else "rover"
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 10_000
    prefix = f"hilsim/{robot}/"
    if robot == "rover":
        urdf, world = REPO / "models/rover/rover.urdf", REPO / "models/worlds/outdoor.xml"
        batch = rover_mix(steps, prefix)
    else:
        urdf, world = REPO / "models/arm/arm.urdf", REPO / "models/arm/tabletop.xml"
        batch = arm_mix(steps, prefix)
    encoded = [(key, message_type(key), msgs.encode(m)) for key, m in batch]
    rec = rr.RecordingStream("bench_rows")
    rec.save(Path(tempfile.mkdtemp()) / "bench.rrd")
    model = RobotModel.load(urdf)
    extra: dict[str, Any] = {}
    if "scene" in inspect.signature(RowWriter.__init__).parameters:  # a checkout with hilsim.sim.scene
        from hilsim.sim.scene import Scene

        extra["scene"] = Scene.load(world, model.links, model.root)
    rows = RowWriter(rec, robot, model, lambda text, exc=None: print("fault:", text), **extra)
    rows.log_model()
    # CPU time of this thread (the logger's worker), not wall time: others' load on a shared
    # machine does not count, rerun's own file-writing threads neither
    t0 = time.thread_time()
    decoded = [(key, msgs.decode(cls, payload)) for key, cls, payload in encoded]
    t1 = time.thread_time()
    for key, m in decoded:
        rows.message(key, m)
        if rows.buffered >= FLUSH_ROWS:
            rows.flush()
    rows.flush()
    t2 = time.thread_time()
    rec.flush()
    n = len(encoded)
    print(f"{robot}: {n} messages ({steps} physics steps): {n / (t2 - t0):,.0f} records/s "
          f"(decode {t1 - t0:.2f} s, rows {t2 - t1:.2f} s: {n / (t2 - t1):,.0f} messages/s through the rows alone)")


if __name__ == "__main__":
    main()
