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

The service is this module (its setup, health, the scenario task, the joint states and execution
monitoring) and its bases, one concern each: :mod:`hilsim.services.planner_goals` (the goal record, its
checks, the goal and cancel queries, feedback and results), :mod:`hilsim.services.planner_action` (the
ROS 2 action), :mod:`hilsim.services.planner_handover` (the trajectory handed over to the controller),
:mod:`hilsim.services.planner_worker` (decision ticks and the planning worker); robots as arrays:
:mod:`hilsim.services.planner_fleet`.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import Scenario
from hilsim.core.restart import keep, kept
from hilsim.core.service import Service
from hilsim.planning import quiet_ompl_at_exit
from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlannerConfigError, PlannerLibrary
from hilsim.services.planner_action import MOVE_ACTION, MOVE_ACTION_TYPE, PlannerAction
from hilsim.services.planner_fleet import FleetPlannerFeed
from hilsim.services.planner_goals import FEEDBACK_PERIOD_NS, Goal
from hilsim.services.planner_handover import HANDOVER_TRIES
from hilsim.services.planner_worker import START_DELAY_NS, PlannerWorker
from hilsim.services.ros2_action import ActionServer
from hilsim.sim.tasks import TaskGoal, TaskRunner

# the names other modules import from here, wherever they are defined
__all__ = ["FEEDBACK_PERIOD_NS", "HANDOVER_TRIES", "MOVE_ACTION", "MOVE_ACTION_TYPE", "START_DELAY_NS",
           "FleetPlannerFeed", "Goal", "PlannerService"]


class PlannerService(PlannerWorker, PlannerAction):
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

    # ------------------------------------------------------------------ the scenario task (hilsim.sim.tasks)
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
