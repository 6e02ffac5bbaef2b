"""The planner's goals: the goal record, its checks, the goal and cancel queries, its feedback and result.

A part of :class:`hilsim.services.planner.PlannerService` (one of its bases, not a service of its own).
A goal is checked before it is accepted: a known planner, a target (joints, or a pose solved by IK)
within the joint limits and free of collision; a rejection says why (INVALID_GOAL, NO_IK_SOLUTION,
GOAL_OUT_OF_LIMITS, GOAL_IN_COLLISION …). A new goal preempts the active one; a cancel drops a queued
goal, lets the worker drop a plan (:mod:`hilsim.services.planner_worker`), or brakes an executing
trajectory to rest on its segment. A goal's end is its MoveResult, also the action's result
(:mod:`hilsim.services.planner_action`) and, for a step of the scenario task, the task runner's.

Serves ``planner/goal`` (MoveGoal → GoalResponse) and ``planner/cancel`` (CancelRequest → GoalResponse)
(the planner's setup declares them). Writes ``planner/joint_trajectory`` (a canceled goal's braking),
``planner/feedback`` (MoveFeedback, 10 Hz sim) and ``planner/result`` (MoveResult).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hilsim.core import msgs
from hilsim.core.publisher import Publisher
from hilsim.core.service import Service
from hilsim.planning.collision import ArmModel
from hilsim.planning.ik import IKError, solve_ik
from hilsim.planning.library import PlannerConfigError, PlannerLibrary, UnknownPlanner
from hilsim.planning.trajectory import TimedTrajectory, stop_on_segment, to_msg
from hilsim.services.ros2_action import ActionServer
from hilsim.sim.tasks import TaskRunner, is_reserved

FEEDBACK_PERIOD_NS = 100_000_000  # 10 Hz sim


@dataclass
class Goal:
    goal_id: str
    target: np.ndarray
    planner: str
    planning_time: float
    execute: bool = True
    task: bool = False  # a step of the scenario task (its end is reported to the task runner)
    state: str = "queued"  # queued | planning | executing | settling | done
    canceled: bool = False
    start_ns: int = 0
    duration_ns: int = 0
    deadline_ns: int = 0
    settle_since: int | None = None
    last_feedback_ns: int = -FEEDBACK_PERIOD_NS
    traj: TimedTrajectory | None = None
    traj_msg: msgs.JointTrajectory = field(default_factory=msgs.JointTrajectory)
    planning_wall: float = 0.0
    invalid: tuple[int, str] | None = None  # a task target that fails validation: reported in turn
    used: str = ""  # the planner that plans (planner: auto: the one it picked), once known
    choice: str = ""  # planner: auto: what it picked and why


class PlannerGoals(Service):
    """The planner's goals (:class:`hilsim.services.planner.PlannerService` sets these attributes)."""

    library: PlannerLibrary
    default_planner: str
    criterion: str
    arm: ArmModel
    n: int
    q: np.ndarray | None  # latest measured joint positions (model order)
    last_target: np.ndarray | None  # target of the last goal reached
    vmax: np.ndarray
    amax: np.ndarray
    jmax: np.ndarray
    active: Goal | None
    pending: list[Goal]
    goal_counter: int
    goals_rejected: int
    task_runner: TaskRunner
    move: ActionServer | None
    action_goals: dict[str, bytes]  # hilsim goal id -> action goal id, while the goal runs
    pub_traj: Publisher
    pub_feedback: Publisher
    pub_result: Publisher

    # ------------------------------------------------------------------ goal validation
    def _reject(self, reason: str, goal_id: str = "") -> msgs.GoalResponse:
        self.goals_rejected += 1
        return msgs.GoalResponse(goal_id=goal_id, accepted=False, reason=reason)

    def _target_of(self, g: msgs.MoveGoal) -> tuple[np.ndarray | None, str]:
        """Joint target of a goal (IK for a pose), or (None, reason)."""
        if g.target_kind == "pose":
            p = g.pose.position
            rot = None
            if g.use_orientation:
                o = g.pose.orientation
                quat = np.array([o.w, o.x, o.y, o.z])
                if abs(np.linalg.norm(quat) - 1.0) > 1e-3:
                    return None, f"INVALID_GOAL: orientation quaternion is not unit (norm {np.linalg.norm(quat):.4f})"
                import mujoco

                mat = np.empty(9)
                mujoco.mju_quat2Mat(mat, quat)
                rot = mat.reshape(3, 3)
            try:
                q = solve_ik(self.arm, np.array([p.x, p.y, p.z]), rot, self.q, seed=self.sc.seed)
            except IKError as e:
                return None, f"NO_IK_SOLUTION: {e}"
            return q, ""
        q = np.array(g.joint_positions, float)
        if g.joint_names:
            if sorted(g.joint_names) != sorted(self.arm.joint_names):
                return None, f"INVALID_GOAL: joint names {list(g.joint_names)} are not {self.arm.joint_names}"
            q = np.array([q[list(g.joint_names).index(n)] for n in self.arm.joint_names])
        return q, ""

    def check_target(self, q: np.ndarray) -> tuple[int, str] | None:
        """(error code, reason) if a joint target is unusable."""
        if q.shape != (self.n,) or not np.all(np.isfinite(q)):
            return msgs.INVALID_GOAL, f"INVALID_GOAL: expected {self.n} finite joint positions"
        bad = self.arm.why_invalid(q)
        if bad is None:
            return None
        kind, reason = bad
        if kind == "limits":
            return msgs.GOAL_OUT_OF_LIMITS, f"GOAL_OUT_OF_LIMITS: {reason}"
        return msgs.GOAL_IN_COLLISION, f"GOAL_IN_COLLISION: {reason}"

    # ------------------------------------------------------------------ queries
    def on_goal(self, g: msgs.MoveGoal) -> msgs.GoalResponse:
        self.goal_counter += 1
        gid = g.goal_id or f"goal-{self.goal_counter}"
        if is_reserved(gid):
            return self._reject(f"INVALID_GOAL: goal id {gid!r} is reserved for the scenario task", gid)
        name = g.planner or self.default_planner
        try:
            self.library.create(name, criterion=self.criterion)
        except (UnknownPlanner, PlannerConfigError) as e:
            return self._reject(f"INVALID_GOAL: {e}", gid)
        q, reason = self._target_of(g)
        if q is None:
            return self._reject(reason, gid)
        if (bad := self.check_target(q)) is not None:
            return self._reject(bad[1], gid)
        goal = Goal(gid, q, name, g.planning_time or self.sc.planner.planning_time, bool(g.execute))
        self._preempt(f"preempted by goal {gid}")
        self.pending.append(goal)
        return msgs.GoalResponse(goal_id=gid, accepted=True, reason="accepted")

    def on_cancel(self, req: msgs.CancelRequest) -> msgs.GoalResponse:
        goals = ([self.active] if self.active else []) + self.pending
        for goal in goals:
            if goal.goal_id == req.goal_id or (req.goal_id == "" and goal is goals[0]):
                self._cancel(goal, "canceled by request")
                return msgs.GoalResponse(goal_id=goal.goal_id, accepted=True, reason="canceling")
        return msgs.GoalResponse(goal_id=req.goal_id, accepted=False, reason=f"no active goal {req.goal_id!r}")

    def _preempt(self, why: str) -> None:
        for goal in [*self.pending, *([self.active] if self.active else [])]:
            self._cancel(goal, why)

    def _cancel(self, goal: Goal, why: str) -> None:
        """Planning: the worker drops the plan. Executing: the trajectory is cut at its next
        waypoint, where it is at rest, so the arm stops smoothly without leaving the checked path."""
        goal.canceled = True
        if goal in self.pending:
            self.pending.remove(goal)
            self._finish(goal, False, msgs.CANCELED, why)
        elif goal.state in ("executing", "settling"):
            if goal.state == "executing" and goal.traj is not None:
                # brake from the reference state one step ahead, on the segment being travelled
                now_ns = self.sim_ns + self.sc.dt_ns
                t = max(0.0, (now_ns - goal.start_ns) * 1e-9)
                stop = stop_on_segment(goal.traj, t, self.vmax, self.amax, self.jmax)
                self.pub_traj.put(to_msg(stop, self.arm.joint_names, goal.start_ns + round(t * 1e9)))
                why = f"{why}; braking to rest in {stop.duration:.2f} s"
            self._finish(goal, False, msgs.CANCELED, why)

    # ------------------------------------------------------------------ results / feedback
    def _error(self, goal: Goal) -> list[float]:
        return [float(x) for x in np.abs(self.q - goal.target)] if self.q is not None else []

    def _finish(self, goal: Goal, success: bool, code: int, message: str) -> None:
        goal.state = "done"
        if success and goal.execute:
            self.last_target = goal.target
        err = self._error(goal)
        result = msgs.MoveResult(
            header=msgs.header(self.sim_ns),
            goal_id=goal.goal_id,
            success=success,
            error_code=code,
            message=message,
            trajectory=goal.traj_msg,
            planning_time=goal.planning_wall,
            execution_error=err,
            planner=goal.used or goal.planner,
            choice=goal.choice,
        )
        self.pub_result.put(result)
        action_id = self.action_goals.pop(goal.goal_id, None)
        if action_id is not None and self.move is not None:
            self.move.finish(action_id, result, success)
        if self.active is goal:
            self.active = None
        if goal.task:
            self.task_runner.on_goal_result(success, self.sim_ns, err)

    def _feedback(self, goal: Goal, progress: float, now_ns: int) -> None:
        goal.last_feedback_ns = now_ns
        fb = msgs.MoveFeedback(header=msgs.header(now_ns), goal_id=goal.goal_id, state=goal.state, progress=progress,
                               planner=goal.used or goal.planner, choice=goal.choice)
        self.pub_feedback.put(fb)
        action_id = self.action_goals.get(goal.goal_id)
        if action_id is not None and self.move is not None:
            self.move.feedback(action_id, fb)
