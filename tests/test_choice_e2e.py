"""End to end: ``planner: auto`` in ``hilsim up arm`` (every service its own process, lockstep): the
learned choice plans each target, the arm reaches all three (judged by the physics truth), and what it
picked and why is in the results on the wire and in the recording's bag."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from test_e2e import hilsim_up
from util import Observer, finish

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.bag_read import open_bag

pytestmark = pytest.mark.e2e


def test_auto_planner_runs_the_arm_task(tmp_path: Path) -> None:
    out = tmp_path / "run"
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    ses = transport.open_session(transport.ZenohConfig(connect=[ep]))
    results: list[msgs.MoveResult] = []
    sub = ses.declare_subscriber(Keys().topic("planner/result"),
                                 lambda s: results.append(msgs.decode(msgs.MoveResult, s.payload.to_bytes())))
    p = hilsim_up("arm", "--set", "planner.planner=auto", "--set", "planner.criterion=length",
                  "--out", str(out), "--router", ep)
    try:
        stdout = finish(p, 300)
        time.sleep(0.3)
    finally:
        sub.undeclare()
        ses.close()
        obs.close()
        router.close()
    assert p.returncode == 0 and "targets reached: 3/3" in stdout, stdout
    sc = load_scenario("arm")
    for i, target in enumerate(sc.task.targets, 1):  # the truth, not the planner's word
        stamp, ok = obs.results[f"task-{i}"]
        assert ok and np.abs(obs.truth_at(stamp) - np.asarray(target)).max() <= sc.task.tolerance + 0.002, i
    steps = {r.goal_id: r for r in results if r.goal_id.startswith("task-")}
    assert sorted(steps) == ["task-1", "task-2", "task-3"], [r.goal_id for r in results]
    for r in steps.values():
        # the choice names the criterion and ranks every planner with its predicted score; the planner
        # that planned is the first of the ranking (or a fallback after it)
        assert r.choice.startswith("auto (length): ") and " < " in r.choice, r.choice
        ranked = [part.split()[0] for part in r.choice.split(": predicted score (success) ", 1)[1].split(" < ")]
        assert r.planner in ranked and r.planner != "auto", (r.planner, r.choice)
    # the recording: the bag holds the very results, choice included
    bag = open_bag(out / "bag")
    recorded = [msgs.decode(msgs.MoveResult, m.data) for m in bag.messages() if m.topic.endswith("planner/result")]
    assert {r.goal_id: r.choice for r in recorded if r.goal_id.startswith("task-")} == \
        {g: r.choice for g, r in steps.items()}
