"""The rover navigates end to end, real processes (physics, sensors, four_wheel_steer controller,
navigator), lockstep: every goal of each world's scenario task is reached, judged by the physics
truth (truth/odom within 0.2 m of the goal, and its yaw, at the moment the navigator reports it);
``hilsim goal rover --xy`` drives it to a goal given on the command line; two runs with navigation
and the same seed give identical truth."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from util import REPO, Capture, finish, up, yaw_of

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.planning.client import MoveClient

pytestmark = pytest.mark.e2e
KEYS = Keys("hilsim", "rover")
TOLERANCE = 0.2  # m: what a goal is judged by (the "reached within 0.2 m")




def judge(truth: dict[int, msgs.Odometry], result: msgs.MoveResult, goal: list[float]) -> tuple[float, float]:
    """Distance and yaw error of the truth at the result's stamp from the goal."""
    t = msgs.ns_of(result.header.stamp)
    assert t in truth, f"no truth/odom at {t} ns"
    o = truth[t]
    d = math.hypot(o.pose.pose.position.x - goal[0], o.pose.pose.position.y - goal[1])
    dyaw = abs(math.remainder(yaw_of(o) - goal[2], 2 * math.pi)) if len(goal) == 3 else 0.0
    return d, dyaw


@pytest.mark.parametrize("world", ["indoor", "outdoor"])
def test_rover_reaches_every_goal(world: str, router: str, tmp_path: Path) -> None:
    """``hilsim up rover --world W``: 'targets reached: 3/3', exit code 0, and at each goal's
    reported moment the physics truth is within 0.2 m (and 0.1 rad) of it; the map and the plans
    were published; the navigator's odometry error at each goal is its own (not the truth)."""
    sc = load_scenario(REPO / "config" / ("rover.yaml" if world == "indoor" else "rover-outdoor.yaml"))
    goals = sc.task.targets
    assert len(goals) >= 3
    cap = Capture(router, ["truth/odom", "navigator/result", "map", "plan"])
    try:
        p = up("rover", "--world", world, "--router", router, "--no-logger", "--out", str(tmp_path / "run"))
        out = finish(p, 240)
        time.sleep(0.3)
    finally:
        cap.close()
    assert p.returncode == 0, out
    assert f"targets reached: {len(goals)}/{len(goals)}" in out, out
    for i in range(1, len(goals) + 1):
        assert re.search(rf"task-{i}: reached at t=", out), out
    truth = {msgs.ns_of(o.header.stamp): o for o in cap.decoded("truth/odom", msgs.Odometry)}
    results = {r.goal_id: r for r in cap.decoded("navigator/result", msgs.MoveResult)}
    for i, goal in enumerate(goals, start=1):
        r = results[f"task-{i}"]
        assert r.success, r.message
        d, dyaw = judge(truth, r, goal)
        print(f"{world} task-{i}: truth {d:.3f} m / {dyaw:.3f} rad from the goal, odometry says "
              f"{r.execution_error[0]:.3f} m at t={msgs.seconds(r.header.stamp):.2f} s")
        assert d <= TOLERANCE, f"task-{i}: truth {d:.3f} m from the goal {goal} ({out})"
        assert dyaw <= 0.1, f"task-{i}: truth yaw {dyaw:.3f} rad off"
        # the navigator judged by its odometry, which differs from the truth (it never saw it)
        assert r.execution_error[0] != pytest.approx(d, abs=1e-9)
    assert results["task"].success and results["task"].message == f"{len(goals)}/{len(goals)} targets reached"
    grids = cap.decoded("map", msgs.OccupancyGrid)
    assert grids and grids[0].info.width * grids[0].info.height == len(grids[0].data)
    assert any(v == 100 for v in grids[0].data) and any(v == 0 for v in grids[0].data)
    plans = [pl for pl in cap.decoded("plan", msgs.Path) if pl.poses]
    assert len(plans) == len(goals)
    # each plan ends on its goal and starts where the rover was
    for pl, goal in zip(plans, goals, strict=True):
        end = pl.poses[-1].pose.position
        assert math.hypot(end.x - goal[0], end.y - goal[1]) < 1e-6


def test_goal_rover_xy_drives_to_the_goal(router: str, tmp_path: Path) -> None:
    """A rover scenario without a task, and ``hilsim goal rover --xy 2.5 -1.0 --yaw 1.57``: accepted,
    succeeded, exit code 0; the truth ends within 0.2 m of it. A goal inside a wall is rejected, a
    malformed one answered with the reason; a goal canceled while driving ends CANCELED and the
    rover stops."""
    cap = Capture(router, ["truth/odom", "navigator/result"])
    p = up("rover", "--router", router, "--no-logger", "--duration", "36", "--set", "task.targets=[]",
           "--out", str(tmp_path / "run"))
    try:
        # send once every service has announced itself (the launcher says "ready:")
        head = []
        assert p.stdout is not None
        for line in p.stdout:
            head.append(line)
            if line.startswith(("ready:", "summary:")):
                break
        assert head and head[-1].startswith("ready:"), "".join(head)
        goal = subprocess.run(
            [sys.executable, "-m", "hilsim.cli", "goal", "rover", "--xy", "2.5", "-1.0", "--yaw", "1.57",
             "--connect", router, "--timeout", "120"],
            capture_output=True, text=True, cwd=REPO, timeout=150)
        bad = subprocess.run(
            [sys.executable, "-m", "hilsim.cli", "goal", "rover", "--xy", "4.0", "2.4", "--connect", router],
            capture_output=True, text=True, cwd=REPO, timeout=60)
        # a goal canceled while the rover drives: CANCELED, and the rover stops
        client = MoveClient(cap.session, KEYS, service="navigator")
        try:
            assert client.send(msgs.MoveGoal(goal_id="far", target_kind="pose",
                                             pose=msgs.Pose(position=msgs.Point(x=-1.0, y=0.0)))).accepted
            assert client.wait_for_state("far", "executing", 60)
            time.sleep(0.5)
            assert client.cancel("far").accepted
            canceled = client.wait("far", 30)
            garbage = client.send_raw(b"\x00\x01\x00\x00garbage")
        finally:
            client.close()
        out = finish(p, 120)
        time.sleep(0.3)
    finally:
        cap.close()
        if p.poll() is None:
            p.kill()
    assert goal.returncode == 0, goal.stdout + goal.stderr
    assert "accepted" in goal.stdout and "succeeded" in goal.stdout, goal.stdout
    assert "(code" not in goal.stdout and "position error" in goal.stdout, goal.stdout  # not "succeeded (code 1)"
    # hilsim up's line per goal: the rover's errors in m and rad, not as joints
    assert "cli-" in out and "position error" in out and "joint error" not in out, out
    assert bad.returncode == 1 and "rejected: GOAL_IN_COLLISION" in bad.stdout, bad.stdout + bad.stderr
    assert p.returncode == 0, out
    truth = {msgs.ns_of(o.header.stamp): o for o in cap.decoded("truth/odom", msgs.Odometry)}
    res = [r for r in cap.decoded("navigator/result", msgs.MoveResult) if r.success]
    assert len(res) == 1
    d, dyaw = judge(truth, res[0], [2.5, -1.0, 1.57])
    assert d <= TOLERANCE and dyaw <= 0.1, (d, dyaw)
    assert canceled is not None and not canceled.success and canceled.error_code == msgs.CANCELED
    assert not garbage.accepted and garbage.reason  # a malformed goal is answered, and nothing breaks
    t_cancel = msgs.ns_of(canceled.header.stamp)
    later = [o for t, o in sorted(truth.items()) if t >= t_cancel + 1_500_000_000]
    assert later, "the run ended too soon after the cancel"
    speed = math.hypot(later[0].twist.twist.linear.x, later[0].twist.twist.linear.y)
    assert speed < 0.05, speed  # stopped within 1.5 s of the cancel


def test_lockstep_rover_navigation_is_deterministic(tmp_path: Path) -> None:
    """Same seed, lockstep, navigating to the first goal of the indoor task: the truth/odom and the
    cmd_vel streams of two runs are equal byte for byte."""
    streams = []
    for i in range(2):
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        router = transport.open_router(ep)
        cap = Capture(ep, ["truth/odom", "cmd_vel", "plan"])
        try:
            p = up("rover", "--router", ep, "--no-logger", "--duration", "6", "--seed", "3",
                   "--out", str(tmp_path / f"run{i}"))
            out = finish(p, 180)
            assert p.returncode == 3 and "result: STOPPED (duration)" in out, out  # --duration cut the task
            time.sleep(0.3)
        finally:
            cap.close()
            router.close()
        with cap.lock:
            truth = {msgs.ns_of(msgs.decode(msgs.Odometry, b).header.stamp): b for b in cap.raw["truth/odom"]}
            streams.append((truth, list(cap.raw["cmd_vel"]), list(cap.raw["plan"])))
    common = sorted(set(streams[0][0]) & set(streams[1][0]))
    assert len(common) >= 2900, len(common)
    assert [streams[0][0][t] for t in common] == [streams[1][0][t] for t in common]
    assert streams[0][2] == streams[1][2] and streams[0][2]  # the same plan
    n = min(len(streams[0][1]), len(streams[1][1]))
    assert n > 50 and streams[0][1][:n] == streams[1][1][:n]
    first, last = (msgs.decode(msgs.Odometry, streams[0][0][t]) for t in (common[0], common[-1]))
    moved = math.hypot(last.pose.pose.position.x - first.pose.pose.position.x,
                       last.pose.pose.position.y - first.pose.pose.position.y)
    assert moved > 1.0, moved  # it really drove
