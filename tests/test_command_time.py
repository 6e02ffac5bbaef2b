"""Who may command, and when (issue 41), end to end: a trajectory's time as ROS 2's joint_trajectory_controller
treats it, against a whole `hilsim up arm` with its own router and credentials.

A tool holding the run's tools' credentials (what a person's tools and ROS 2 nodes get) sends, as a ROS 2
node does (an announced publisher, rmw_zenoh's attachment), a trajectory stamped an hour ahead of sim time
and one stamped with the wall clock (a node not on sim time). Before, the first was taken and waited, and
every later trajectory of the planner was refused as "out of date": 1/3. Now both are refused with a
reason naming ``use_sim_time`` (in the summary), and the arm reaches its 3 targets, judged by the physics
truth.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from util import REPO, Observer, wait_until

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.tools.recording.play import Player


def _to(stamp_ns: int, target: list[float]) -> bytes:
    return msgs.encode(msgs.JointTrajectory(header=msgs.header(stamp_ns), joint_names=[f"joint_{i}" for i in
                                                                                      range(1, 7)],
                                            points=[msgs.JointTrajectoryPoint(positions=target,
                                                                              time_from_start=msgs.duration(1.0))]))


@pytest.mark.serial  # a whole run, timed alone
def test_a_far_stamped_trajectory_from_a_tool_no_longer_locks_the_planner_out(tmp_path: Path) -> None:
    run = tmp_path / "run"
    up = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--out", str(run), "--no-logger"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                          start_new_session=True)
    obs: Observer | None = None
    player: Player | None = None
    lines: list[str] = []
    try:
        assert up.stdout is not None
        for line in up.stdout:
            lines.append(line)
            if line.startswith("zenoh router:"):
                obs = Observer(line.split()[2], run / "zenoh-client.json5")
            if line.startswith("ready:"):
                break
        assert obs is not None, "".join(lines)
        keys = Keys()
        player = Player(obs.session, keys.domain)  # a node of its own: announced, as rclpy's publisher is
        pub, _, _ = player.publisher(keys.topic("joint_trajectory"))
        assert wait_until(lambda: pub.matching_status.matching, 10.0), "the controller does not subscribe"
        hour = 3600 * 1_000_000_000
        player.put(keys.topic("joint_trajectory"), _to(hour, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0]))
        player.put(keys.topic("joint_trajectory"), _to(time.time_ns(), [-0.5, 0.0, 0.0, 0.0, 0.0, 0.0]))
        out, _ = up.communicate(timeout=300)
        out = "".join(lines) + out
    finally:
        if player is not None:
            player.close()
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.communicate()
        if obs is not None:
            obs.close()
    assert up.returncode == 0 and "targets reached: 3/3" in out and "result: OK" in out, out
    # both refused, the reason said in the summary (the last one: the wall clock's)
    assert "controller: 2 trajectories refused (last: joint_trajectory: stamped" in out, out
    assert "wall-clock time" in out and "use_sim_time" in out, out
    log = (run / "controller.log").read_text()
    assert "more than controller.params.max_start_ahead (30 s)" in log, log
    # judged by the physics truth, not the planner's word
    sc = load_scenario("arm")
    for i, target in enumerate(sc.task.targets, 1):
        stamp, ok = obs.results[f"task-{i}"]
        assert ok and np.abs(obs.truth_at(stamp) - np.asarray(target)).max() <= sc.task.tolerance + 0.002
