"""The task runner on its own: goals in order, one per call, and the task's result at the end."""

from __future__ import annotations

import numpy as np

from hilsim.core import msgs
from hilsim.sim.tasks import TaskGoal, TaskRunner, is_reserved


def test_goals_in_order_then_one_result() -> None:
    submitted: list[TaskGoal] = []
    reported: list[msgs.MoveResult] = []
    r = TaskRunner([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]], submitted.append, reported.append, planner="rrtstar")
    assert not r.started and not submitted
    r.on_tick()
    r.on_tick()  # only the first tick starts the task
    assert [g.goal_id for g in submitted] == ["task-1"] and np.array_equal(submitted[0].target, [0.1, 0.2])
    assert r.active
    r.on_goal_result(True, 1_000, [0.001, 0.0])
    r.on_goal_result(False, 2_000, [0.5, 0.0])  # a failed step does not stop the task
    assert [g.goal_id for g in submitted] == ["task-1", "task-2", "task-3"] and not reported
    r.on_goal_result(True, 3_500_000_000, [0.002, 0.003])
    (res,) = reported
    assert res.goal_id == "task" and not res.success and res.error_code == msgs.FAILURE
    assert res.message == "2/3 targets reached" and res.planner == "rrtstar"
    assert res.execution_error == [0.002, 0.003] and msgs.ns_of(res.header.stamp) == 3_500_000_000
    assert not r.active and r.result is res
    msgs.decode(msgs.MoveResult, msgs.encode(res))  # a valid message


def test_no_targets_no_task() -> None:
    submitted: list[TaskGoal] = []
    r = TaskRunner([], submitted.append, lambda _r: None)
    r.on_tick()
    assert not submitted and not r.started and not r.active


def test_reserved_goal_ids() -> None:
    assert is_reserved("task") and is_reserved("task-3")
    assert not is_reserved("tasks") and not is_reserved("goal-1") and not is_reserved("cli-123")
