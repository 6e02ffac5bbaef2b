"""Lockstep: a trajectory that reaches the controller late changes nothing.

The planner publishes a trajectory at a decision tick and physics may run ``lockstep_lag`` steps past
that tick before it waits for the planner's acknowledgement; the trajectory starts later still. Zenoh
orders nothing between keys (and each subscriber has its own thread), so on a loaded machine the
controller could take the trajectory after the joint states of its start step: the run then differs
from another of the same seed (seen once in CI as a 1e-10 difference in velocities). The planner
therefore acknowledges the tick only once the controller says it holds the trajectory
(``controller/has_trajectory``).

The proof: the controller below (a plug-in control law, ``controller.type: slow``) takes every
trajectory 80 ms of wall time after it arrives, in a thread of its own, like a starved subscriber
thread. Its run must equal the plain controller's run bit for bit, judged by the physics truth.
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

from hilsim.core import msgs
from hilsim.core.keys import Keys
from tests.test_e2e import up_captured

pytestmark = pytest.mark.e2e

SLOW_LAW = '''
"""A joint_trajectory controller whose trajectories arrive 80 ms (wall) late."""
import threading
import time

from hilsim.services.controller import ControllerService


class SlowTrajectoryController(ControllerService):
    def on_trajectory(self, msg, key):
        def late():
            time.sleep(0.08)
            with self.lock:
                ControllerService.on_trajectory(self, msg, key)

        threading.Thread(target=late, daemon=True).start()
'''


def _plugin(where: Path) -> Path:
    """A control law installed as a plug-in would be: a module and its entry point (a dist-info)."""
    where.mkdir()
    (where / "slow_law.py").write_text(textwrap.dedent(SLOW_LAW))
    info = where / "slow_law-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: slow-law\nVersion: 0\n")
    (info / "entry_points.txt").write_text("[hilsim.controllers]\nslow = slow_law:SlowTrajectoryController\n")
    return where


def test_a_trajectory_that_reaches_the_controller_late_changes_nothing(tmp_path: Path) -> None:
    keys = Keys()
    plugin = _plugin(tmp_path / "plugin")
    truths: list[dict[int, bytes]] = []
    for i, law in enumerate(["joint_trajectory", "slow"]):
        env = {"PYTHONPATH": os.pathsep.join([str(plugin), os.environ.get("PYTHONPATH", "")])}
        rc, stdout, cap = up_captured(
            tmp_path / f"run{i}", {"truth": keys.topic("truth/joint_states"), "trajs": keys.topic("joint_trajectory"),
                                   "health": keys.health("planner")},
            "arm", "--duration", "1.2", "--seed", "7", "--no-logger", "--set", f"controller.type={law}", env=env)
        assert rc == 3 and "result: STOPPED (duration)" in stdout, stdout
        truth, trajs, health = cap["truth"], cap["trajs"], cap["health"]
        assert len(trajs) == 1, stdout  # task-1's trajectory, which starts within the run
        start = msgs.ns_of(msgs.decode(msgs.JointTrajectory, trajs[0]).header.stamp)
        assert start < 200_000_000, start
        # the planner waited for the controller to hold it: the slow law's 80 ms show
        last = {kv.key: kv.value for kv in msgs.decode(msgs.DiagnosticArray, health[-1]).status[0].values}
        assert last["handovers"] == "1", last
        assert (float(last["handover_wait_max_s"]) >= 0.07) == (law == "slow"), last
        truths.append({msgs.ns_of(msgs.decode(msgs.JointState, b).header.stamp): b for b in truth})
    common = sorted(set(truths[0]) & set(truths[1]))
    assert len(common) >= 1150, len(common)
    differ = [t for t in common if truths[0][t] != truths[1][t]]
    assert not differ, f"{len(differ)} of {len(common)} steps differ, the first at {differ[0] / 1e6:.0f} ms"
    # and the arm moved on its trajectory: the comparison is not of two arms at rest
    first, last = (msgs.decode(msgs.JointState, truths[0][t]) for t in (common[0], common[-1]))
    assert max(abs(a - b) for a, b in zip(first.position, last.position, strict=True)) > 0.05
