"""Planner service: move goals → collision-free path (OMPL / improved RRT*) → ruckig trajectory → execution.

Reads:
- ``joint_states_throttle`` (sensor_msgs/JointState, 6 joints): the sensors' ``joint_states`` of
  every ``planner.rate_hz`` step only, not all 1 kHz of them: sim time, the start state of a plan
  and execution monitoring (in sim time, at ``planner.rate_hz``). Each is a *decision tick*: goals
  start there, and in lockstep mode the tick is acknowledged only once the trajectory is out
  (planning takes no sim time). Deciding on the joint state itself, not on the clock, means a
  plan always starts from the state of its own step: reproducible bit for bit. Physics waits for
  a tick's acknowledgement only ``lockstep_lag`` steps later (the trajectory acts later still).

  With ``fleet.arrays`` (robots > 1) :class:`FleetPlannerFeed` hands it its robot's slice of
  ``fleet/joint_states_throttle`` instead (the same message, its ticks and acknowledgements unchanged).

Writes:
- ``planner/joint_trajectory`` (trajectory_msgs/JointTrajectory) for the joint trajectory controller
  (a key only the planner's identity may write, so the controller knows its trajectories from a
  person's on ``joint_trajectory``), stamped to start ``START_DELAY`` after the tick it was planned
  on; never dropped on a congested link
  (a sample given once: hilsim.core.keys), and in realtime sent again, up to ``HANDOVER_TRIES`` times
  in all, while the controller answers ``controller/has_trajectory`` that it did not reach it;
- ``planner/path`` (the geometric path, for the logger), ``planner/feedback`` (state ``planning`` /
  ``executing`` / ``settling``, progress, 10 Hz sim), ``planner/result`` (MoveResult);
- ``task/result`` (MoveResult ``task``): the outcome of the scenario task;
- ``sync/planner`` (lockstep acknowledgement) through the base class: a tick that sent a trajectory
  is acknowledged only once the controller answered ``controller/has_trajectory`` for it (the
  controller's docstring says why; no wait when no controller serves that query).

Serves ``planner/goal`` (MoveGoal → GoalResponse, accepted or rejected with the reason) and
``planner/cancel`` (CancelRequest → GoalResponse). A new goal preempts the active one.

Serves the same goals as the ROS 2 action ``hilsim_msgs/action/Move`` at ``/<robot>/move``
(:mod:`hilsim.services.ros2_action`): a goal (a MoveGoal; its ``goal_id`` string, if empty, becomes the
action goal's UUID) goes through :meth:`PlannerService.on_goal`, a cancel through the same cancel as
``planner/cancel``; the action's feedback is the MoveFeedback and its result the MoveResult published
on ``planner/feedback`` / ``planner/result``. A goal ``on_goal`` refuses is accepted and aborted at
once with its error code (INVALID_GOAL, NO_IK_SOLUTION, GOAL_OUT_OF_LIMITS …), as move_group
reports a bad request in its result. The result's status is SUCCEEDED for a successful MoveResult,
CANCELED when a cancel request ended it, ABORTED otherwise (a failure, or preempted by another goal).

The scenario task (``task.targets``) is a :class:`hilsim.sim.tasks.TaskRunner` hosted here: goals
``task-1`` … ``task-N`` in order, each starting on the tick after the previous result, then a
MoveResult ``task`` saying how many targets were reached, on ``planner/result`` and on
``task/result`` (``hilsim up`` ends the run on the latter).

Threads: Zenoh callbacks run under ``self.lock`` and only queue work; one worker thread plans
(with its own MuJoCo model) so goal and cancel queries are answered while it plans.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from hilsim.core import msgs
from hilsim.core.config import Scenario
from hilsim.core.keys import NOT_REACHED
from hilsim.core.restart import keep, kept
from hilsim.core.service import Service
from hilsim.planning import quiet_ompl_at_exit
from hilsim.planning.collision import ArmModel
from hilsim.planning.ik import IKError, solve_ik
from hilsim.planning.library import PlannerConfigError, PlannerLibrary, PlanOutcome, Problem, UnknownPlanner
from hilsim.planning.trajectory import (
    TimedTrajectory,
    TrajectoryError,
    path_msg,
    stop_on_segment,
    time_parameterize,
    to_msg,
)
from hilsim.services.ros2_action import ActionServer, goal_text
from hilsim.sim.tasks import TaskGoal, TaskRunner, is_reserved

START_DELAY_NS = 20_000_000  # trajectory starts 20 ms (sim) after the tick it was planned on
# realtime: a trajectory that did not reach the controller is sent this many times in all
HANDOVER_TRIES = 3
FEEDBACK_PERIOD_NS = 100_000_000  # 10 Hz sim
MOVE_ACTION = "move"  # /<robot>/move
MOVE_ACTION_TYPE = "hilsim_msgs/action/Move"


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


class PlannerService(Service):
    name = "planner"
    stop_rank = 10

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        return sc.planner_decimation  # it decides, and acknowledges, on its own ticks only

    @classmethod
    def array_driver(cls, sc: Scenario) -> type[Service] | None:
        """robots as arrays (fleet.arrays): every robot's planner fed from the one fleet joint_states."""
        return FleetPlannerFeed

    @classmethod
    def lockstep_lag(cls, sc: Scenario) -> int:
        # What the planner decides at tick t acts from t + START_DELAY_NS on (the trajectory's
        # stamp), so physics need not stop at t for it: it simulates on while the planner's round
        # trip is under way and waits at t + lag at the latest (measured: the planner's wait was
        # half the time of a composed step; docs/performance.md). Half the start delay at most,
        # so the trajectory, sent before the acknowledgement, still has half of it to reach the
        # controller; one decision period at most, so at most one tick is owed at a time.
        return max(0, min(sc.planner_decimation, START_DELAY_NS // (2 * sc.dt_ns)))

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        self.library = PlannerLibrary.load(scenario.planner.library)
        self.iterations = scenario.planner.iterations or self.library.iterations
        self.default_planner = scenario.planner.planner
        self.criterion = scenario.planner.criterion  # what planner: auto chooses for
        # an unknown default is a configuration error at start
        default = self.library.create(self.default_planner, criterion=self.criterion)
        # one model for the query handlers (validation, IK), one for the planning worker
        self.arm = ArmModel(scenario.world.model, scenario.planner.clearance)
        self.plan_arm = ArmModel(scenario.world.model, scenario.planner.clearance, self.arm.joint_names)
        self.auto_fallbacks = 0  # planner: auto plans that went to its fallback (an arm it does not know, too slow)
        self.choice_over_bound = 0  # planner: auto decisions over their CPU bound
        self.choice_p99_ms: float | None = None  # planner: auto's decisions at start, 99th percentile [ms CPU]
        # planner: auto, named anywhere (the default, a goal): its model and its world's features are loaded and
        # its decision measured now, not at the first goal
        for name, spec in self.library.specs.items():
            if spec.get("kind") == "auto":
                try:  # the default's error ended the start above; another's is said, and refuses its goals
                    auto = default if name == self.default_planner else self.library.create(name,
                                                                                            criterion=self.criterion)
                except PlannerConfigError as e:
                    self.log.warning("planner %s: %s", name, e)
                    continue
                auto.prepare(self.plan_arm)  # type: ignore[attr-defined]
                self.choice_p99_ms = auto.warm_p99_ms(self.plan_arm)  # type: ignore[attr-defined]
                if name == self.default_planner and auto.unfit(self.plan_arm):  # type: ignore[attr-defined]
                    self.log.warning("%s", auto.fallback_text(self.plan_arm))  # type: ignore[attr-defined]
        self.n = self.arm.n
        self.vmax, self.amax, self.jmax = self.library.joint_limits(self.n, self.arm.velocity_limits(),
                                                                    self.arm.joint_names)
        self.q: np.ndarray | None = None  # latest measured joint positions (model order)
        self.last_target: np.ndarray | None = None  # target of the last goal reached
        self.active: Goal | None = None
        self.pending: list[Goal] = []
        self.task_runner = TaskRunner(scenario.task.targets, self._submit_task_goal, self._report_task,
                                      planner=self.default_planner)
        # restarted (hilsim.core.restart): the task goes on at the target the dead planner was on
        task = kept(scenario, self.name).get("task")
        if isinstance(task, dict) and 0 <= task.get("index", -1) < len(self.task_runner.targets):
            self.task_runner.next_index, self.task_runner.reached = task["index"], task.get("reached", 0)
            self.log.info("restarted: the task resumes at target %d (%d reached before)",
                          task["index"] + 1, self.task_runner.reached)
        self.goal_counter = 0
        self.plans = 0
        self.goals_rejected = 0
        self.last_planning_time = 0.0
        self.handovers = 0  # trajectories the controller confirmed it holds
        self.resent = 0  # realtime: trajectories sent again, the controller not holding them
        self.handover_wait_max = 0.0  # [s of wall time] the longest wait for that
        self._jobs: queue.Queue[tuple[Goal, int, np.ndarray] | None] = queue.Queue()
        self._planning = False  # a job is queued or being planned
        self._deferred: deque[tuple[int, np.ndarray]] = deque()  # lockstep ticks that came meanwhile
        self._worker: threading.Thread | None = None
        self.move: ActionServer | None = None
        self.action_goals: dict[str, bytes] = {}  # hilsim goal id -> action goal id, while the goal runs

    # ------------------------------------------------------------------ setup
    def setup(self) -> None:
        k = self.keys
        self.pub_traj = self.publisher(k.topic("planner/joint_trajectory"))
        self.pub_path = self.publisher(k.topic("planner/path"))
        self.pub_feedback = self.publisher(k.topic("planner/feedback"))
        self.pub_result = self.publisher(k.topic("planner/result"))
        self.pub_task_result = self.publisher(k.topic("task/result"))
        # its decision ticks: an error there would stop every goal and the task, so it ends the service
        # (joint_states_throttle: the sensors' joint_states of those steps only, not all 1 kHz of them;
        # robots as arrays: FleetPlannerFeed hands it its robot's slice of fleet/joint_states_throttle)
        if not self.fleet_driven:
            self.subscribe(k.topic("joint_states_throttle"), msgs.JointState, self.on_joint_states,
                           n_joints=self.n, fatal=True)
        self._controller_seen = False
        self._declared.append(self.session.liveliness().declare_subscriber(
            k.alive("controller"), self._on_controller, history=True))
        self.queryable(k.topic("planner/goal"), msgs.MoveGoal, self.on_goal, n_joints=self.n, reject=self._reject)
        self.queryable(k.topic("planner/cancel"), msgs.CancelRequest, self.on_cancel, reject=self._reject)
        self.move = ActionServer(self, MOVE_ACTION, MOVE_ACTION_TYPE, self.on_move_goal, self.on_move_cancel)
        self._worker = threading.Thread(target=self._work, daemon=True, name="planner-worker")
        self._worker.start()

    def teardown(self) -> None:
        self._jobs.put(None)
        if self._worker is not None:
            self._worker.join(timeout=30)

    def run(self) -> int:
        rc = super().run()
        if threading.current_thread() is threading.main_thread():  # the service's own process
            quiet_ompl_at_exit()
        return rc

    def health_values(self) -> dict[str, Any]:
        return {
            "goal": self.active.goal_id if self.active else "",
            "goal_state": self.active.state if self.active else "idle",
            "plans": self.plans,
            "goals_rejected": self.goals_rejected,
            "last_planning_time_s": round(self.last_planning_time, 4),
            "handovers": self.handovers,
            "trajectories_resent": self.resent,
            "handover_wait_max_s": round(self.handover_wait_max, 4),
            "auto_fallbacks": self.auto_fallbacks,
            "choice_over_bound": self.choice_over_bound,
            "choice_p99_ms": None if self.choice_p99_ms is None else round(self.choice_p99_ms, 2),
        }

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

    # ------------------------------------------------------------------ the same, as a ROS 2 action
    def on_move_goal(self, action_id: bytes, g: msgs.MoveGoal) -> bool:
        """An action goal: accepted, then run as :meth:`on_goal` runs a goal of ``planner/goal``, or
        aborted at once with the code of the reason it refuses it."""
        assert self.move is not None
        g.goal_id = g.goal_id or goal_text(action_id)
        try:
            msgs.validate(g, n_joints=self.n)  # what decoding checks of a goal on planner/goal
            resp = self.on_goal(g) if g.goal_id not in self.action_goals else self._reject(
                f"INVALID_GOAL: goal id {g.goal_id!r} is running already", g.goal_id)
        except msgs.BadMessage as e:
            resp = self._reject(f"INVALID_GOAL: {e}", g.goal_id)
        if not resp.accepted:
            code = getattr(msgs, resp.reason.split(":", 1)[0], msgs.INVALID_GOAL)
            self.move.finish(action_id, msgs.MoveResult(header=msgs.header(self.sim_ns), goal_id=g.goal_id,
                                                        error_code=code, message=resp.reason), False)
            return True
        self.action_goals[resp.goal_id] = action_id
        return True

    def on_move_cancel(self, action_id: bytes) -> bool:
        gid = next((k for k, v in self.action_goals.items() if v == action_id), None)
        return gid is not None and self.on_cancel(msgs.CancelRequest(goal_id=gid)).accepted

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
        # state 'planning': the worker sees goal.canceled and reports

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

    # ------------------------------------------------------------------ the scenario task (hilsim.sim.tasks)
    def _on_controller(self, sample: Any) -> None:
        """A controller (re)appeared: a restarted one knows no trajectory, so the one being
        executed is sent again (its start stamp unchanged: it picks up where the arm should be),
        at once and after ``clock.start_delay``: a sample sent before the peers' own links to the
        new process exist can be lost (see physics' start of the run)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        with self.lock:
            first, self._controller_seen = not self._controller_seen, True
        if first:
            return  # the run's own controller, before any goal: nothing to send again (nor any timer)
        self._resend_trajectory()
        t = threading.Timer(self.sc.clock.start_delay, self._resend_trajectory)
        t.daemon = True
        t.start()

    def _resend_trajectory(self) -> None:
        with self.lock:
            if self.stop_event.is_set():
                return
            goal = self.active
            if goal is not None and goal.state in ("executing", "settling") and goal.traj_msg.points:
                self.log.info("a controller appeared: %s's trajectory sent again", goal.goal_id)
                self.pub_traj.put(goal.traj_msg)

    def _submit_task_goal(self, tg: TaskGoal) -> None:
        keep(self.sc, self.name, {"task": {"index": self.task_runner.next_index - 1,
                                           "reached": self.task_runner.reached}})
        goal = Goal(tg.goal_id, tg.target, self.default_planner, self.sc.planner.planning_time, True, task=True)
        goal.invalid = self.check_target(tg.target)  # reported in turn, as a failed step
        self.pending.append(goal)

    def _report_task(self, result: msgs.MoveResult) -> None:
        self.pub_result.put(result)
        self.pub_task_result.put(result)
        self.log.info("task finished: %s", result.message)

    def _feedback(self, goal: Goal, progress: float, now_ns: int) -> None:
        goal.last_feedback_ns = now_ns
        fb = msgs.MoveFeedback(header=msgs.header(now_ns), goal_id=goal.goal_id, state=goal.state, progress=progress,
                               planner=goal.used or goal.planner, choice=goal.choice)
        self.pub_feedback.put(fb)
        action_id = self.action_goals.get(goal.goal_id)
        if action_id is not None and self.move is not None:
            self.move.feedback(action_id, fb)

    # ------------------------------------------------------------------ inputs
    def on_joint_states(self, js: msgs.JointState, _key: str) -> None:
        if not js.position:
            return
        pos = dict(zip(js.name, js.position, strict=True))
        try:
            self.q = np.array([pos[n] for n in self.arm.joint_names])
        except KeyError as e:
            self.warn(f"joint_states lacks joint {e}")
            return
        t = msgs.ns_of(js.header.stamp)
        self._monitor(t)
        if self.sc.planner_tick(t):
            self.on_tick(t)

    def _monitor(self, now: int) -> None:
        """Execution monitoring, in sim time of the joint state (deterministic in lockstep)."""
        goal = self.active
        if goal is None or goal.state not in ("executing", "settling") or self.q is None:
            return
        if now < goal.start_ns:
            return
        progress = min(1.0, (now - goal.start_ns) / max(goal.duration_ns, 1))
        if now >= goal.start_ns + goal.duration_ns:
            if goal.state == "executing":
                goal.state = "settling"
                self._feedback(goal, 1.0, now)
            if float(np.max(np.abs(self.q - goal.target))) <= self.sc.task.tolerance:
                if goal.settle_since is None:
                    goal.settle_since = now
                if now - goal.settle_since >= round(self.sc.task.settle_time * 1e9):
                    self._finish(goal, True, msgs.SUCCESS, "target reached")
                    return
            else:
                goal.settle_since = None
        if now >= goal.deadline_ns:
            err = np.abs(self.q - goal.target)
            self._finish(
                goal, False, msgs.CONTROL_FAILED,
                f"target not held within {self.sc.task.tolerance} rad: max joint error {float(np.max(err)):.4f} rad",
            )
            return
        if now - goal.last_feedback_ns >= FEEDBACK_PERIOD_NS:
            self._feedback(goal, progress, now)

    def on_tick(self, t: int) -> None:
        """A decision step (see the module docstring)."""
        # self.q is replaced by every joint state, never changed in place: this tick keeps its own
        assert self.q is not None
        if self.lockstep and self._planning:
            # Physics runs up to lockstep_lag steps past a tick being planned, so a later tick can
            # come before that plan is out: it waits, with its own step's state, and is decided
            # (and acknowledged) after it, in order, exactly as if physics had stopped at the first
            self._deferred.append((t, self.q))
            return
        self._decide(t, self.q)

    def _decide(self, t: int, q: np.ndarray) -> None:
        self.sim_ns = max(self.sim_ns, t)
        self.task_runner.on_tick()
        if self.active is None and self.pending:
            goal = self.pending.pop(0)
            if goal.invalid is not None:
                self._finish(goal, False, *goal.invalid)
            else:
                self.active = goal
                goal.state = "planning"
                self._feedback(goal, 0.0, t)
                self._planning = True
                self._jobs.put((goal, t, q))  # planned from q, the state of this tick's step
                return  # the worker acknowledges t once the trajectory is out
        if self.lockstep:
            self.ack(t)

    # ------------------------------------------------------------------ planning worker
    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            goal, t, q = job
            sent: int | None = None
            try:
                sent = self._plan(goal, t, q)
            except Exception as e:  # a planner bug must fail the goal, not the service
                with self.lock:
                    self.fault(f"planning {goal.goal_id} failed: {type(e).__name__}: {e}", exc=e)
                    if goal.state == "planning":
                        self._finish(goal, False, msgs.PLANNING_FAILED, f"{type(e).__name__}: {e}")
            finally:
                if sent is not None:
                    self._handed_over(goal, sent)
                with self.lock:
                    if self.lockstep:
                        self.ack(t)
                    self._planning = False
                    # the ticks that came while planning, in order (one may start the next plan)
                    while self._deferred and not self._planning:
                        self._decide(*self._deferred.popleft())

    def _handed_over(self, goal: Goal, start_ns: int) -> None:
        """Wait until the controller holds the trajectory starting at ``start_ns`` (its
        ``controller/has_trajectory``). Lockstep: the tick is acknowledged only then. Zenoh keeps no
        order between keys: a trajectory the controller took after the joint states of its start step
        would act later than in another run of the seed. Realtime: one that never reached it (lost on
        the way) is sent again, up to ``HANDOVER_TRIES`` times in all, or the arm would not move for the
        rest of the goal's time. No answer (no controller yet, or a control law without the query):
        nothing to wait for; no answer in time: a warning (lockstep: and the tick is acknowledged)."""
        if not self._controller_seen:
            return
        session = self.zenoh_session
        if session is None:
            return  # an in-process bus (benchmarks): delivery is in publication order
        tries = 1 if self.lockstep else HANDOVER_TRIES
        for attempt in range(1, tries + 1):
            got = self._ask_controller(session, start_ns)
            if got is None or got.accepted:
                return  # no controller answers this query, or it holds the trajectory
            with self.lock:
                again = (attempt < tries and got.reason.startswith(NOT_REACHED) and self.active is goal
                         and goal.state in ("executing", "settling"))
                # lockstep: this run may not repeat bit for bit; a refusal: the controller says why too
                self.warn(f"{goal.goal_id}: the controller does not hold the trajectory: {got.reason}"
                          + ("; sent again" if again else ""))
                if not again:
                    return
                self.resent += 1
                self.pub_traj.put(goal.traj_msg)

    def _ask_controller(self, session: zenoh.Session, start_ns: int) -> msgs.GoalResponse | None:
        """The controller's ``controller/has_trajectory`` answer for ``start_ns``; None if none came."""
        w0 = time.perf_counter()
        key, ask = self.keys.topic("controller/has_trajectory"), msgs.encode(msgs.stamp(start_ns))
        got: msgs.GoalResponse | None = None
        # Half of physics' patience (the controller's own wait is a third): a controller that stopped
        # answering (SIGSTOP, hung) is then named silent by physics, not this planner waiting for it
        for reply in session.get(key, payload=ask, timeout=self.sc.clock.ack_timeout / 2):
            try:
                got = (msgs.decode(msgs.GoalResponse, reply.ok.payload.to_bytes()) if reply.ok is not None
                       else msgs.GoalResponse(reason=reply.err.payload.to_string()))
            except msgs.BadMessage as e:
                got = msgs.GoalResponse(reason=f"bad answer: {e}")
            with self.lock:
                self.handover_wait_max = max(self.handover_wait_max, time.perf_counter() - w0)
                self.handovers += got.accepted
        return got

    def _plan(self, goal: Goal, t: int, q: np.ndarray) -> int | None:
        """Plan ``goal`` from ``q`` at tick ``t``; the start stamp of the trajectory sent, if one was."""
        start = np.clip(q, self.arm.lower, self.arm.upper)
        measured = start
        with self.lock:
            anchor = self.last_target
        if (
            anchor is not None
            and float(np.max(np.abs(start - anchor))) <= 2 * self.sc.task.tolerance
            and not self.plan_arm.is_valid(start)
        ):
            # Measured noise / tracking error put the start a hair inside the clearance of the
            # last target (which was validated): plan from that target; the first waypoint stays
            # the measured state, a step of at most 2 tolerances.
            start = anchor
        planner = self.library.create(goal.planner, criterion=self.criterion)
        if hasattr(planner, "prepare"):  # auto (prepared at start; once per collision model)
            planner.prepare(self.plan_arm)
            planner.enforce_bound = not self.lockstep  # lockstep: sim time waits; a choice by load breaks determinism
        if self.lockstep:
            budget: dict[str, Any] = {
                "max_iterations": self.iterations,
                "time_limit": goal.planning_time * self.library.wall_cap_factor,
            }
        else:
            # realtime plans for planning_time; with planner.iterations set they stop at that count
            # first, so a busy machine plans as well as a quiet one, only later
            budget = {"max_iterations": self.sc.planner.iterations, "time_limit": goal.planning_time}
        seed = self.sc.seed + self.plans
        pb = Problem(self.plan_arm, start, goal.target, seed=seed, resolution=self.library.resolution,
                     cancelled=lambda: goal.canceled, report=lambda used, why: self._chosen(goal, used, why, t),
                     **budget)
        w0 = time.perf_counter()
        if np.max(np.abs(goal.target - start)) < 1e-6:
            out = PlanOutcome(np.array([start, goal.target]), "already there")
        elif (why := self.plan_arm.why_invalid(start)) is not None:
            out = PlanOutcome(None, f"start state invalid: {why[1]}")
        else:
            out = planner.solve(pb)
        self.plans += 1
        traj = None
        if out.path is not None and start is not measured:
            out.path = np.vstack([measured, out.path])
        if out.path is not None:
            try:
                traj = time_parameterize(out.path, self.vmax, self.amax, self.jmax, dt=0.01)
            except TrajectoryError as e:
                out.path, out.message = None, str(e)
        wall = time.perf_counter() - w0
        with self.lock:
            self.last_planning_time = wall
            goal.planning_wall = wall
            goal.used = str(out.extra.get("planner", goal.planner))
            goal.choice = str(out.extra.get("choice", ""))
            if out.extra.get("auto_fallback"):
                self.auto_fallbacks += 1
            if out.extra.get("over_bound"):
                self.choice_over_bound += 1
            if out.wall_cap_hit:
                self.warn(f"{goal.goal_id}: planning hit the wall-clock cap ({pb.time_limit:g} s): not deterministic")
            if goal.canceled or goal.state != "planning":
                if goal.state == "planning":
                    self._finish(goal, False, msgs.CANCELED, "canceled while planning")
                return
            if out.path is None or traj is None:
                # the planner ran its budget out without a solution: TIMED_OUT; anything else: PLANNING_FAILED
                code = msgs.TIMED_OUT if out.path is None and out.iterations > 0 else msgs.PLANNING_FAILED
                self._finish(goal, False, code, f"planning failed: {out.message}")
                return
            start_ns = t + START_DELAY_NS if self.lockstep else self.sim_ns + START_DELAY_NS
            goal.traj = traj
            goal.traj_msg = to_msg(traj, self.arm.joint_names, start_ns)
            self.pub_path.put(path_msg(out.path, self.arm.joint_names, t))
            if not goal.execute:
                self._finish(goal, True, msgs.SUCCESS, f"planned ({len(out.path)} waypoints), not executed")
                return
            self.pub_traj.put(goal.traj_msg)
            goal.start_ns = start_ns
            goal.duration_ns = round(traj.duration * 1e9)
            timeout = max(self.sc.task.target_timeout, traj.duration + self.sc.task.settle_time + 1.0)
            goal.deadline_ns = start_ns + round(timeout * 1e9)
            goal.state = "executing"
            self._feedback(goal, 0.0, t)
            self.log.info(
                "%s: %s planned %d waypoints in %.3f s (%d iterations), trajectory %.2f s%s",
                goal.goal_id, goal.used, len(out.path), wall, out.iterations, traj.duration,
                f"; {goal.choice} (decided in {1e3 * out.extra.get('decision_s', 0.0):.1f} ms CPU)"
                if goal.choice else "",
            )
        return start_ns

    def _chosen(self, goal: Goal, used: str, why: str, t: int) -> None:
        """planner: auto has chosen (before it plans): the goal's feedback says which planner and why."""
        with self.lock:
            goal.used, goal.choice = used, why
            if goal.state == "planning" and not goal.canceled:
                self._feedback(goal, 0.0, t)



class FleetPlannerFeed(Service):
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): every robot's planner fed from one sample.

    Reads ``<prefix>/<robot>/fleet/joint_states_throttle`` (every robot's encoders of the planners'
    decision steps, joints ``arm<k>/<joint>``) and
    hands each robot's :class:`PlannerService` its slice, the very JointState (names, values, stamp) the
    robot's own ``joint_states`` carries, in robot order; writes nothing of its own. The planners keep
    everything else, their lockstep role included (each acknowledges its ticks on its own ``sync/planner``):
    one sample to decode per step instead of one per robot.
    """

    name = "planner"
    stop_rank = 11  # started before the planners it feeds, stopped after them
    acks_for_robots = False

    def __init__(self, scenario: Scenario, members: list[PlannerService]) -> None:
        super().__init__(scenario)
        self.members = members
        self.n = members[0].n
        self.names: list[str] | None = None
        self.robot_joints: list[list[str]] = []

    def setup(self) -> None:
        self.subscribe(self.keys.fleet("joint_states_throttle"), msgs.JointState, self.on_joint_states)

    def on_joint_states(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        self.sim_ns = stamp
        n, k_n = self.n, len(self.members)
        if self.names is None:
            self.names = list(msg.name)
            self.robot_joints = [[j.split("/", 1)[-1] for j in self.names[k * n:(k + 1) * n]] for k in range(k_n)]
        if list(msg.name) != self.names or len(msg.name) != n * k_n or len(msg.position) != len(msg.name):
            self.reject(key, f"fleet JointState of {len(msg.name)} joints is not {k_n} robots of {n} joints")
            return
        for k, m in enumerate(self.members):
            c = slice(k * n, (k + 1) * n)
            js = msgs.JointState(header=msg.header, name=self.robot_joints[k], position=msg.position[c],
                                 velocity=msg.velocity[c] if msg.velocity else [],
                                 effort=msg.effort[c] if msg.effort else [])
            with m.lock:
                if m.stop_event.is_set():
                    continue
                try:
                    m.on_joint_states(js, key)
                except Exception as e:  # its decision ticks, as its own subscription is: fatal to it
                    m.fail(f"error handling {key}: {type(e).__name__}: {e}", exc=e)
                    continue
            m.counts_in[key] += 1

    def health_values(self) -> dict[str, Any]:
        return {"robots": len(self.members), "arrays": "yes"}
