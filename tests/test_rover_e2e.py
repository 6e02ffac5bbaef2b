"""The rover end to end, real processes (physics, sensors, four_wheel_steer controller): a test
drives it over cmd_vel and judges the motion by the physics truth; scan and gps/fix come at their
rates; two lockstep runs with the same seed and a scripted drive give identical truth/odom."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from util import Capture, finish, up, yaw_of

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parent.parent
KEYS = Keys("hilsim", "rover")
# the rover without its navigator (which would drive it to the scenario's goals): these tests drive it
NO_NAVIGATION = "services=[physics,sensors,controller]"




def test_rover_drives_as_commanded_over_cmd_vel(router: str, tmp_path: Path) -> None:
    """Forward 0.5 m/s from t=0.5 to 3.5 s, then turn in place at 0.8 rad/s until 6 s (phases chosen
    by the sim time the test sees in truth/odom); outdoor world, so the GPS is on. At wall-clock pace
    (realtime), as a teleoperator drives: in lockstep the sim raced ahead of this test's commands whenever
    the test stalled (a loaded CI runner once left 1.5 s of the turn without its command)."""
    cap = Capture(router, ["truth/odom", "scan", "gps/fix", "odom"])
    pub = cap.session.declare_publisher(KEYS.topic("cmd_vel"))
    latest = {"t": 0.0}
    done = threading.Event()

    def drive() -> None:
        while not done.wait(0.02):
            with cap.lock:
                if cap.raw["truth/odom"]:
                    latest["t"] = msgs.seconds(msgs.decode(msgs.Odometry, cap.raw["truth/odom"][-1]).header.stamp)
            t = latest["t"]
            tw = msgs.Twist()
            if 0.5 <= t < 3.5:
                tw.linear.x = 0.5
            elif 3.5 <= t < 6.0:
                tw.angular.z = 0.8
            pub.put(msgs.encode(tw))

    th = threading.Thread(target=drive, daemon=True)
    th.start()
    try:
        p = up("config/rover-outdoor.yaml", "--router", router, "--no-logger", "--duration", "7.5",
               "--clock", "realtime", "--set", NO_NAVIGATION, "--out", str(tmp_path / "run"))
        out = finish(p, 240)
    finally:
        done.set()
        th.join(5)
        time.sleep(0.3)
        pub.undeclare()
        cap.close()
    assert p.returncode == 0, out
    truth = {msgs.ns_of(o.header.stamp): o for o in cap.decoded("truth/odom", msgs.Odometry)}
    assert len(truth) > 3000, len(truth)

    def at(t: float) -> msgs.Odometry:
        return truth[min(truth, key=lambda k: abs(k - round(t * 1e9)))]

    start, mid, end = at(0.4), at(3.5), at(7.5)
    # The command follows the sim time this test last saw, late by its own wall latency, and stops for
    # cmd_timeout (0.5 s) when this test stalls (under load it does): judged by the rates where each
    # command held, 0.5 s inside its phase, in windows of 0.1 s: most at the command, none above it
    def rates(t0: float, t1: float, of: Callable[[msgs.Odometry], float]) -> np.ndarray:
        ts = np.arange(t0, t1, 0.1)
        return np.array([(of(at(t + 0.1)) - of(at(t))) / 0.1 for t in ts])

    speed = rates(1.0, 3.0, lambda o: o.pose.pose.position.x)
    assert 0.45 < float(np.median(speed)) < 0.55 and speed.max() < 0.56, speed
    dx = mid.pose.pose.position.x - start.pose.pose.position.x
    assert 0.8 < dx < 1.8, dx
    assert abs(mid.pose.pose.position.y - start.pose.pose.position.y) < 0.05
    assert abs(yaw_of(mid) - yaw_of(start)) < 0.03
    # turn in place: 0.8 rad/s (from 4.0 to 5.5 s), staying where it was, and still again once told (7 s on)
    c = at(4.0)
    yaw_rate = rates(4.0, 5.5, yaw_of)
    assert 0.7 < float(np.median(yaw_rate)) < 0.9 and yaw_rate.max() < 0.9, yaw_rate
    turned = yaw_of(end) - yaw_of(mid)
    assert 1.0 < turned < 2.8, turned
    assert abs(yaw_of(end) - yaw_of(at(7.0))) < 0.02, yaw_of(end) - yaw_of(at(7.0))
    moved = math.hypot(end.pose.pose.position.x - c.pose.pose.position.x,
                       end.pose.pose.position.y - c.pose.pose.position.y)
    assert moved < 0.15, moved
    # wheel odometry of the controller agrees with the truth on the straight part
    odom = {msgs.ns_of(o.header.stamp): o for o in cap.decoded("odom", msgs.Odometry)}
    o_mid = odom[min(odom, key=lambda k: abs(k - 3_500_000_000))]
    assert o_mid.pose.pose.position.x == pytest.approx(mid.pose.pose.position.x, abs=0.1)
    o_end = odom[max(odom)]  # and on the turn (yaw rate from the IMU)
    assert yaw_of(o_end) - yaw_of(o_mid) == pytest.approx(turned, abs=0.1)
    # the sensors at their rates: scan 10 Hz, gps/fix 5 Hz over 7.5 s of sim
    scans = cap.decoded("scan", msgs.LaserScan)
    fixes = cap.decoded("gps/fix", msgs.NavSatFix)
    assert abs(len(scans) - 76) <= 2 and abs(len(fixes) - 38) <= 2, (len(scans), len(fixes))
    assert all(len(s.ranges) == 541 for s in scans)
    assert any(math.isfinite(r) for r in scans[-1].ranges)  # the buildings and rocks are in range
    assert all(abs(f.latitude - 41.17788) < 1e-3 and abs(f.longitude + 8.59779) < 1e-3 for f in fixes)


def test_lockstep_rover_runs_are_identical(tmp_path: Path) -> None:
    """Same seed, lockstep, a scripted drive (forward, then an Ackermann-like turn): the truth/odom
    streams of two runs are equal byte for byte."""
    streams = []
    script = "controller.params.script=[[0.2,0.6,0,0],[1.2,0.5,0,0.6]]"
    for i in range(2):
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        router = transport.open_router(ep)
        cap = Capture(ep, ["truth/odom"])
        try:
            p = up("rover", "--router", ep, "--no-logger", "--duration", "2.5", "--seed", "5", "--set", script,
                   "--set", NO_NAVIGATION, "--out", str(tmp_path / f"run{i}"))
            out = finish(p, 180)
            assert p.returncode == 0, out
            time.sleep(0.3)
        finally:
            cap.close()
            router.close()
        with cap.lock:
            streams.append({msgs.ns_of(msgs.decode(msgs.Odometry, b).header.stamp): b for b in cap.raw["truth/odom"]})
    common = sorted(set(streams[0]) & set(streams[1]))
    assert len(common) >= 1200, len(common)
    assert [streams[0][t] for t in common] == [streams[1][t] for t in common]
    first, last = (msgs.decode(msgs.Odometry, streams[0][t]) for t in (common[0], common[-1]))
    assert last.pose.pose.position.x - first.pose.pose.position.x > 0.8  # it really drove
    assert yaw_of(last) > 0.3  # and turned
