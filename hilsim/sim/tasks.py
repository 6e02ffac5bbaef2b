"""A task: several goals run one after another, and one result for the whole.

The scenario's task (``task.targets``) is the first kind: goals ``task-1`` … ``task-N``, one
per joint target, in order, then a MoveResult with goal id ``task`` saying how many targets
were reached. :class:`TaskRunner` holds that sequence and its bookkeeping; the service that
executes goals (today the planner) *hosts* it:

- on each of its decision ticks it calls :meth:`TaskRunner.on_tick` (the first one starts the
  task), so in lockstep a task goal starts on a tick the host chose, as any goal does;
- the runner hands each goal to the host's ``submit`` callback (the host queues it like any other
  goal, started on the tick after the previous one ended);
- the host calls :meth:`TaskRunner.on_goal_result` when a task goal ends; after the last one the
  runner passes the task's MoveResult to the host's ``report`` callback, which publishes it on
  ``planner/result`` and on the generic ``task/result`` (what ``hilsim up`` ends the run on).

The runner never touches Zenoh or the clock: it is deterministic given the order of the calls.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hilsim.core import msgs

TASK_ID = "task"  # goal id of the whole task's result
GOAL_PREFIX = "task-"  # goal ids of its steps: task-1 … task-N


def is_reserved(goal_id: str) -> bool:
    """Goal ids that belong to the task and may not be sent by clients."""
    return goal_id == TASK_ID or goal_id.startswith(GOAL_PREFIX)


@dataclass(frozen=True)
class TaskGoal:
    """One step of a task: reach ``target`` (joint positions, model order)."""

    goal_id: str
    target: np.ndarray


class TaskRunner:
    def __init__(
        self,
        targets: Sequence[Sequence[float]],
        submit: Callable[[TaskGoal], None],
        report: Callable[[msgs.MoveResult], None],
        *,
        planner: str = "",
    ) -> None:
        self.targets = [np.asarray(t, float) for t in targets]
        self.submit = submit
        self.report = report
        self.planner = planner  # named in the task's result
        self.next_index = 0  # next target to hand out
        self.reached = 0
        self.started = False
        self.result: msgs.MoveResult | None = None

    @property
    def active(self) -> bool:
        return self.started and self.result is None

    def on_tick(self) -> None:
        """A decision tick of the host: the first one starts the task (if it has targets)."""
        if not self.started and self.targets:
            self.started = True
            self._submit_next()

    def on_goal_result(self, success: bool, now_ns: int, execution_error: Sequence[float]) -> None:
        """The task goal handed out last has ended: hand out the next one, or report the task."""
        self.reached += int(success)
        if self.next_index < len(self.targets):
            self._submit_next()
        else:
            self._finish(now_ns, execution_error)

    def _submit_next(self) -> None:
        i = self.next_index
        self.next_index += 1
        self.submit(TaskGoal(f"{GOAL_PREFIX}{i + 1}", self.targets[i]))

    def _finish(self, now_ns: int, execution_error: Sequence[float]) -> None:
        n = len(self.targets)
        ok = self.reached == n
        self.result = msgs.MoveResult(
            header=msgs.header(now_ns),
            goal_id=TASK_ID,
            success=ok,
            error_code=msgs.SUCCESS if ok else msgs.FAILURE,
            message=f"{self.reached}/{n} targets reached",
            execution_error=list(execution_error),
            planner=self.planner,
        )
        self.report(self.result)
