"""A trajectory's time, with a real ROS 2 node (rclpy Kilted on rmw_fastrtps_cpp: tests/ros2_timing_node.py)
commanding the arm through ``bridge-ros2-dds``, judged by the physics truth the node reads. As
tests/test_ros2_real.py, everything runs in a network namespace with multicast on ``lo`` only.

- a node not on sim time stamps its trajectory with the wall clock: refused, the reason naming
  ``use_sim_time`` in the controller's log and the summary, and the planner's next trajectories are
  followed (the task's last target reached in the truth: 3/3);
- a trajectory stamped 2 s of sim time ahead starts then (the truth does not move before its stamp and
  moves within 0.1 s after it);
- a newer trajectory (stamp 0) replaces an older one mid-motion: the arm turns back before the older
  one's target and ends at the newer one's.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from util import LEAN, REPO, lan_netns, ros2_python, until_ready

from hilsim.core.scenario import load_scenario

NODE = Path(__file__).resolve().parent / "ros2_timing_node.py"
OVERLAY = str(REPO / "config" / "ros2" / "dds.yaml")
TO_DDS = "bridge-ros2-dds.to_dds=[truth/joint_states,/clock]"

pytestmark = [pytest.mark.e2e, pytest.mark.serial]  # realtime runs


@pytest.fixture
def netns() -> Iterator[str]:
    with lan_netns("ros2t") as ns:
        yield ns


def _up(ns: str, tmp_path: Path, *args: str) -> tuple[subprocess.Popen[str], list[str]]:
    env = {k: v for k, v in os.environ.items() if k not in ("CYCLONEDDS_URI", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    p = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "hilsim.cli", "up", LEAN, *args,
                          "--hil", OVERLAY, "--set", TO_DDS, "--out", str(tmp_path / "run")],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=env,
                         start_new_session=True)
    lines: list[str] = []
    until_ready(p, lines)
    return p, lines


def _finish(p: subprocess.Popen[str], lines: list[str], *, interrupt: bool) -> str:
    if interrupt and p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)
    try:
        out, _ = p.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, _ = p.communicate()
    return "".join(lines) + out


def _node(ns: str, *args: str) -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "CYCLONEDDS", "FASTDDS"))}
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    p = subprocess.run(["ip", "netns", "exec", ns, str(ros2_python("kilted")), str(NODE), *args],
                       capture_output=True, text=True, env=env, timeout=240)
    assert p.returncode == 0 and p.stdout.strip(), (p.stdout[-2000:], p.stderr[-3000:])
    seen = json.loads(p.stdout.strip().splitlines()[-1])
    assert seen["stage"] == "done", ({k: v for k, v in seen.items() if k != "truth"}, p.stderr[-2000:])
    return seen


def test_a_node_not_on_sim_time_is_refused_and_the_planner_still_drives(netns: str, tmp_path: Path) -> None:
    last = load_scenario(LEAN).task.targets[-1]
    run, lines = _up(netns, tmp_path, "--clock", "realtime")
    try:
        seen = _node(netns, "--mode", "wall", "--until", *map(str, last))
        out = _finish(run, lines, interrupt=False)
    finally:
        if run.poll() is None:
            _finish(run, lines, interrupt=True)
    # the physics truth, as the node read it: the task's last target, after its wall-stamped trajectory
    assert max(abs(a - b) for a, b in zip(seen["last"], last, strict=True)) < 0.01, seen["last"]
    assert seen["sent"]["wall"]["stamp"] > 1.7e18  # a wall-clock stamp, as rclpy gave it
    assert "targets reached: 3/3" in out and "result: OK" in out, out
    assert "trajectories refused (last: joint_trajectory: stamped" in out and "use_sim_time" in out, out
    log = (tmp_path / "run" / "controller.log").read_text()
    assert "wall-clock time, while sim time is" in log, log


def test_a_stamp_ahead_starts_then_and_a_newer_trajectory_replaces_an_older_mid_motion(netns: str,
                                                                                         tmp_path: Path) -> None:
    run, lines = _up(netns, tmp_path, "--clock", "realtime", "--interactive")
    try:
        seen = _node(netns, "--mode", "timing")
    finally:
        out = _finish(run, lines, interrupt=True)
    assert "died" not in out, out
    truth = seen["truth"]  # (sim stamp, joint_1)
    ahead, long, newer = (seen["sent"][k] for k in ("ahead", "long", "newer"))
    # stamped 2 s ahead: still until its stamp, moving within 0.1 s after it, at its target in the end
    q0 = ahead["start"][0]
    before = [q for t, q in truth if ahead["sim_at_send"] <= t < ahead["stamp"]]
    assert len(before) > 100 and max(abs(q - q0) for q in before) < 0.003, max(abs(q - q0) for q in before)
    moved = next(t for t, q in truth if t >= ahead["stamp"] and abs(q - q0) > 0.005)
    assert moved - ahead["stamp"] < 100_000_000, (moved - ahead["stamp"]) / 1e9
    at_long = min(truth, key=lambda x: abs(x[0] - long["sim_at_send"]))[1]
    assert abs(at_long - ahead["target"][0]) < 0.01, at_long
    # the newer one (stamp 0: now) replaced the long one mid-motion: the arm had gone part of the way,
    # never reached the long one's target, and ended at the newer one's
    at_newer = min(truth, key=lambda x: abs(x[0] - newer["sim_at_send"]))[1]
    way = (at_newer - long["start"][0]) / (long["target"][0] - long["start"][0])
    assert 0.1 < way < 0.9, way
    after = [q for t, q in truth if t >= newer["sim_at_send"]]
    assert min(after) > long["target"][0] + 0.2, min(after)
    assert abs(seen["last"][0] - newer["target"][0]) < 0.01, (seen["last"], newer["target"])
