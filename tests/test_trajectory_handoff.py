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
    def on_planner_trajectory(self, msg, key):
        def late():
            time.sleep(0.08)
            with self.lock:
                ControllerService.on_planner_trajectory(self, msg, key)

        threading.Thread(target=late, daemon=True).start()
'''


def _plugin(where: Path, law: str = "slow", module: str = "slow_law", source: str = SLOW_LAW,
            cls: str = "SlowTrajectoryController") -> Path:
    """A control law installed as a plug-in would be: a module and its entry point (a dist-info)."""
    where.mkdir()
    (where / f"{module}.py").write_text(textwrap.dedent(source))
    info = where / f"{module}-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 0\n")
    (info / "entry_points.txt").write_text(f"[hilsim.controllers]\n{law} = {module}:{cls}\n")
    return where


def test_a_trajectory_that_reaches_the_controller_late_changes_nothing(tmp_path: Path) -> None:
    keys = Keys()
    plugin = _plugin(tmp_path / "plugin")
    truths: list[dict[int, bytes]] = []
    for i, law in enumerate(["joint_trajectory", "slow"]):
        env = {"PYTHONPATH": os.pathsep.join([str(plugin), os.environ.get("PYTHONPATH", "")])}
        rc, stdout, cap = up_captured(
            tmp_path / f"run{i}", {"truth": keys.topic("truth/joint_states"),
                                   "trajs": keys.topic("planner/joint_trajectory"), "health": keys.health("planner")},
            "arm", "--duration", "1.2", "--seed", "7", "--no-logger", "--set", f"controller.type={law}", env=env)
        assert rc == 3 and "result: STOPPED (duration)" in stdout, stdout
        truth, trajs, health = cap["truth"], cap["trajs"], cap["health"]
        assert len(trajs) == 1, stdout  # task-1's trajectory, which starts within the run
        start = msgs.ns_of(msgs.decode(msgs.JointTrajectory, trajs[0]).header.stamp)
        assert start < 200_000_000, start
        # the planner waited for the controller to hold it: the slow law's 80 ms show
        last = {kv.key: kv.value for kv in msgs.decode(msgs.DiagnosticArray, health[-1]).status[0].values}
        assert last["handovers"] == "1", last
        # (the plain law's wait is no measure: on a loaded machine it took 108 ms too)
        assert law != "slow" or float(last["handover_wait_max_s"]) >= 0.07, last
        truths.append({msgs.ns_of(msgs.decode(msgs.JointState, b).header.stamp): b for b in truth})
    common = sorted(set(truths[0]) & set(truths[1]))
    assert len(common) >= 1150, len(common)
    differ = [t for t in common if truths[0][t] != truths[1][t]]
    assert not differ, f"{len(differ)} of {len(common)} steps differ, the first at {differ[0] / 1e6:.0f} ms"
    # and the arm moved on its trajectory: the comparison is not of two arms at rest
    first, last = (msgs.decode(msgs.JointState, truths[0][t]) for t in (common[0], common[-1]))
    assert max(abs(a - b) for a, b in zip(first.position, last.position, strict=True)) > 0.05


LOSSY_LAW = '''
"""A joint_trajectory controller that never gets the first trajectory sent to it (lost on the way)."""
from hilsim.services.controller import ControllerService


class LossyTrajectoryController(ControllerService):
    lost = 0

    def on_planner_trajectory(self, msg, key):
        if not self.lost:
            self.lost += 1
            return
        ControllerService.on_planner_trajectory(self, msg, key)
'''


@pytest.mark.serial  # realtime: task-1 is planned in 1 s of wall time and reached within the 8 s run
def test_realtime_a_trajectory_lost_on_the_way_is_sent_again(tmp_path: Path) -> None:
    """Realtime: a trajectory that never reached the controller (dropped under load, issue 36) would leave
    the arm still for the rest of the goal's time; the planner asks the controller whether it holds it
    and sends it again. Judged by the physics truth: the arm reaches task-1's target."""
    keys = Keys()
    plugin = _plugin(tmp_path / "plugin", "lossy", "lossy_law", LOSSY_LAW, "LossyTrajectoryController")
    env = {"PYTHONPATH": os.pathsep.join([str(plugin), os.environ.get("PYTHONPATH", "")])}
    rc, stdout, cap = up_captured(
        tmp_path / "run", {"truth": keys.topic("truth/joint_states"), "trajs": keys.topic("planner/joint_trajectory"),
                           "health": keys.health("planner")},
        "arm", "--clock", "realtime", "--duration", "8", "--no-logger", "--set", "controller.type=lossy",
        # the controller answers "not reached" after a third of this: a second, not ten
        "--set", "clock.ack_timeout=3", env=env)
    assert rc == 3 and "task-1: reached" in stdout, stdout
    log = (tmp_path / "run" / "planner.log").read_text()
    assert "task-1: the controller does not hold the trajectory: no joint_trajectory starting at" in log, log
    assert "; sent again" in log, log
    trajs = [msgs.decode(msgs.JointTrajectory, b) for b in cap["trajs"]]
    assert len(trajs) >= 2 and trajs[0] == trajs[1], [t.header for t in trajs]  # the same trajectory, again
    last = {kv.key: kv.value for kv in msgs.decode(msgs.DiagnosticArray, cap["health"][-1]).status[0].values}
    assert last["trajectories_resent"] == "1", last
    # the physics truth: the arm came to the trajectory's last point (then went on to task-2's)
    goal = dict(zip(trajs[0].joint_names, trajs[0].points[-1].positions, strict=True))
    errs = [max(abs(p - goal[n]) for n, p in zip(js.name, js.position, strict=True) if n in goal)
            for js in (msgs.decode(msgs.JointState, b) for b in cap["truth"])]
    assert min(errs) < 0.01, min(errs)
