"""The joint controller's ROS 2 action ``control_msgs/action/FollowJointTrajectory``.

Served at ``/<robot>/<controller.params.action_ns>`` by :class:`hilsim.services.controller.ControllerService`
through :mod:`hilsim.services.ros2_action` (its keys are the action's, as a node on rmw_zenoh has them:
``…/_action/send_goal``, ``cancel_goal``, ``get_result``, ``feedback``, ``status``). A goal's trajectory is
taken under the same rules as one on ``joint_trajectory`` (:mod:`hilsim.sim.jtc`); feedback (desired,
actual, error of the goal's joints) at ``controller.params.action_feedback_hz`` of sim time; the result:

- SUCCESSFUL once every joint of the goal is within its goal tolerance (else ``task.tolerance``) of the
  last point after its time;
- GOAL_TOLERANCE_VIOLATED if that has not happened ``goal_time_tolerance`` (else
  ``controller.params.goal_time_tolerance``) later;
- PATH_TOLERANCE_VIOLATED as soon as a joint with a path tolerance strays further from the reference (the
  arm then holds where it is);
- INVALID_JOINTS for joint names that are not the controller's (or a subset, when
  ``allow_partial_joints_goal`` is off);
- INVALID_GOAL for a trajectory it cannot follow (no points, times not increasing, outside the limits,
  multi-DOF, stamped too far ahead of sim time: the reason names ``use_sim_time``);
- OLD_HEADER_TIMESTAMP for one that ended before it arrived.

Invalid goals are accepted and aborted with that code (so the client reads why); a cancel holds the
current position; a new goal, or a trajectory on ``joint_trajectory`` or the planner's, replaces the goal's
from its own start and aborts the goal once it is no longer followed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from hilsim.core import msgs
from hilsim.core.msgs import control as cm
from hilsim.core.service import Service
from hilsim.services.ros2_action import ActionServer, goal_text
from hilsim.sim import control, jtc

FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"
REFUSAL_CODES = {jtc.JOINTS: cm.FJT_INVALID_JOINTS, jtc.ENDED: cm.FJT_OLD_HEADER_TIMESTAMP,
                 jtc.AHEAD: cm.FJT_INVALID_GOAL}


class Controller(Protocol):
    """What the action needs of its controller (:class:`hilsim.services.controller.ControllerService`)."""

    sc: Any
    params: Any
    names: list[str]
    timeline: jtc.Timeline | None
    taken: control.TrajectorySampler | None
    pos: np.ndarray
    vel: np.ndarray
    ref_pos: np.ndarray
    ref_vel: np.ndarray

    def take(self, msg: msgs.JointTrajectory, key: str, source: str) -> tuple[str, str] | None: ...

    def stop_here(self) -> None: ...

    def warn(self, text: str) -> None: ...


@dataclass
class FjtGoal:
    """The FollowJointTrajectory goal being followed."""

    goal_id: bytes
    names: list[str]
    cols: list[int]  # model index of each of the goal's joints
    sampler: control.TrajectorySampler
    target: np.ndarray  # the last point, the goal's joints
    path_tol: np.ndarray  # position, per goal joint; inf: none
    goal_tol: np.ndarray
    goal_vel_tol: np.ndarray
    deadline_ns: int  # the end plus the goal time tolerance
    next_feedback_ns: int = 0


class FollowJointTrajectory:
    """The action of one controller: its goals, their tolerances, feedback and results. Runs under the
    controller's lock (its handlers are the controller's, :meth:`step` is called from its control step)."""

    def __init__(self, ctl: Controller, svc: Service) -> None:
        """``ctl`` and ``svc``: the controller, as the action's law and as the service that serves it."""
        self.ctl = ctl
        self.server = ActionServer(svc, ctl.params.action_ns, FOLLOW_JOINT_TRAJECTORY, self.on_goal, self.on_cancel)
        self.goal: FjtGoal | None = None
        self.goals = 0

    @property
    def source(self) -> str:
        return f"{self.server.name} goal"

    def on_goal(self, goal_id: bytes, goal: cm.FollowJointTrajectoryGoal) -> bool:
        """A goal is accepted; one that cannot be followed is aborted at once with its error code, and
        leaves the motion under way alone."""
        ctl = self.ctl
        self.goals += 1
        tr = goal.trajectory
        names = list(tr.joint_names)
        why: tuple[int, str] | None = None
        if len(set(names)) != len(names) or any(n not in ctl.names for n in names) or not names:
            why = cm.FJT_INVALID_JOINTS, f"joint names {names} are not among the controller's joints {ctl.names}"
        elif goal.multi_dof_trajectory.points or goal.multi_dof_trajectory.joint_names:
            why = cm.FJT_INVALID_GOAL, "multi-DOF trajectories are not supported"
        elif not tr.points:
            why = cm.FJT_INVALID_GOAL, "the trajectory has no points"
        elif ctl.timeline is None:
            why = cm.FJT_INVALID_GOAL, "no joint_states measured yet"
        else:
            try:
                msgs.validate(tr)  # sizes, times strictly increasing, finite values
            except msgs.BadMessage as e:
                why = cm.FJT_INVALID_GOAL, str(e)
        if why is None:
            strangers = [t.name for t in [*goal.path_tolerance, *goal.goal_tolerance] if t.name not in names]
            if strangers:
                why = cm.FJT_INVALID_JOINTS, f"tolerances for {strangers}, joints the goal does not move"
        if why is None and (refused := ctl.take(tr, self.server.keys.send_goal, self.source)) is not None:
            why = REFUSAL_CODES.get(refused[0], cm.FJT_INVALID_GOAL), refused[1]
        if why is not None:
            ctl.warn(f"{self.server.name}: goal {goal_text(goal_id)} aborted: {why[1]}")
            self.server.finish(goal_id, cm.FollowJointTrajectoryResult(error_code=why[0], error_string=why[1]),
                               False)
            return True
        sampler = ctl.taken
        assert sampler is not None
        if self.goal is not None:
            self.end(False, cm.FJT_INVALID_GOAL, f"preempted by goal {goal_text(goal_id)}")
        cols = [ctl.names.index(n) for n in names]
        gtt = msgs.ns_of(goal.goal_time_tolerance) or round(ctl.params.goal_time_tolerance * 1e9)
        self.goal = FjtGoal(goal_id, names, cols, sampler, sampler.pos[-1][cols],
                            *self._tolerances(names, goal), deadline_ns=sampler.end_ns + gtt,
                            next_feedback_ns=sampler.start_ns)
        return True

    def _tolerances(self, names: list[str], goal: cm.FollowJointTrajectoryGoal) -> tuple[np.ndarray, ...]:
        """(path position, goal position, goal velocity) tolerance per goal joint. In a JointTolerance 0
        means the default (none on the path, ``task.tolerance`` at the goal, none for the velocity) and a
        negative value none."""
        path = np.full(len(names), np.inf)
        pos = np.full(len(names), float(self.ctl.sc.task.tolerance))
        vel = np.full(len(names), np.inf)

        def put(into: np.ndarray, name: str, value: float) -> None:
            if value:
                into[names.index(name)] = np.inf if value < 0 else value

        for t in goal.path_tolerance:
            put(path, t.name, t.position)
        for t in goal.goal_tolerance:
            put(pos, t.name, t.position)
            put(vel, t.name, t.velocity)
        return path, pos, vel

    def on_cancel(self, goal_id: bytes) -> bool:
        g = self.goal
        if g is None or g.goal_id != goal_id:
            return False
        self.ctl.stop_here()
        self.end(False, cm.FJT_SUCCESSFUL, "canceled")
        return True

    def end(self, success: bool, code: int, text: str) -> None:
        g, self.goal = self.goal, None
        if g is not None:
            self.server.finish(g.goal_id, cm.FollowJointTrajectoryResult(error_code=code, error_string=text), success)

    def step(self, now: int) -> None:
        """Once per control step, after the reference: tolerances, feedback, the end of the goal."""
        g = self.goal
        ctl = self.ctl
        if g is None:
            return
        assert ctl.timeline is not None
        if not ctl.timeline.holds(g.sampler):
            last = ctl.timeline.last()
            self.end(False, cm.FJT_INVALID_GOAL, f"replaced by a trajectory from {last.source if last else 'a stop'}")
            return
        if now < g.sampler.start_ns:
            return
        desired, actual = ctl.ref_pos[g.cols], ctl.pos[g.cols]
        error = desired - actual
        if now >= g.next_feedback_ns:
            g.next_feedback_ns = now + round(1e9 / ctl.params.action_feedback_hz)
            elapsed = now - g.sampler.start_ns

            def point(p: np.ndarray, v: np.ndarray) -> msgs.JointTrajectoryPoint:
                return msgs.JointTrajectoryPoint(positions=p.tolist(), velocities=v.tolist(),
                                                 time_from_start=msgs.Duration(sec=elapsed // 1_000_000_000,
                                                                               nanosec=elapsed % 1_000_000_000))

            desired_vel, actual_vel = ctl.ref_vel[g.cols], ctl.vel[g.cols]
            self.server.feedback(g.goal_id, cm.FollowJointTrajectoryFeedback(
                header=msgs.header(now), joint_names=g.names, desired=point(desired, desired_vel),
                actual=point(actual, actual_vel), error=point(error, desired_vel - actual_vel)))
        if now < g.sampler.end_ns:
            bad = np.nonzero(np.abs(error) > g.path_tol)[0]
            if bad.size:
                j = int(bad[0])
                ctl.stop_here()
                self.end(False, cm.FJT_PATH_TOLERANCE_VIOLATED,
                         f"{g.names[j]} is {abs(error[j]):.4f} from its reference (path tolerance {g.path_tol[j]:g})")
            return
        off = np.abs(actual - g.target)
        if np.all(off <= g.goal_tol) and np.all(np.abs(ctl.vel[g.cols]) <= g.goal_vel_tol):
            self.end(True, cm.FJT_SUCCESSFUL, "")
        elif now > g.deadline_ns:
            j = int(np.argmax(off - g.goal_tol))
            ctl.stop_here()
            self.end(False, cm.FJT_GOAL_TOLERANCE_VIOLATED,
                     f"{g.names[j]} is {off[j]:.4f} from the goal (tolerance {g.goal_tol[j]:g}) "
                     f"{(now - g.sampler.end_ns) * 1e-9:.3f} s after the trajectory's end")
