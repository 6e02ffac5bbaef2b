"""The planner's decisions: its ticks, and the worker thread that plans and sends the trajectory.

A part of :class:`hilsim.services.planner.PlannerService` (one of its bases, not a service of its own).
Each decision tick (a ``joint_states_throttle`` sample of a ``planner.rate_hz`` step) starts the next
queued goal: the worker (one thread, its own MuJoCo model, so goal and cancel queries are answered while
it plans) plans it from that step's state (OMPL / improved RRT* / planner: auto, a seed of its own per
plan), time-parameterises the path (ruckig) and sends the trajectory stamped ``START_DELAY_NS`` after the
tick; in lockstep the tick is acknowledged once the trajectory is out and handed over
(:mod:`hilsim.services.planner_handover`), and ticks that came while it planned are decided after it, in
order.

Writes ``planner/joint_trajectory``, ``planner/path``, ``planner/feedback``, ``planner/result`` and
``sync/planner`` (the lockstep acknowledgement, through the base class).
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.threads import name_os_thread
from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlanOutcome, Problem
from hilsim.planning.trajectory import TrajectoryError, path_msg, time_parameterize, to_msg
from hilsim.services.planner_goals import Goal
from hilsim.services.planner_handover import PlannerHandover

START_DELAY_NS = 20_000_000  # trajectory starts 20 ms (sim) after the tick it was planned on


class PlannerWorker(PlannerHandover):
    """The planner's decision ticks and its planning worker."""

    plan_arm: ArmModel  # the worker's own model
    iterations: int
    plans: int
    last_planning_time: float
    auto_fallbacks: int
    choice_over_bound: int
    pub_path: Any
    _jobs: queue.Queue[tuple[Goal, int, np.ndarray] | None]
    _planning: bool  # a job is queued or being planned
    _deferred: deque[tuple[int, np.ndarray]]  # lockstep ticks that came meanwhile
    _worker: threading.Thread | None

    # ------------------------------------------------------------------ decision ticks
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
        name_os_thread(b"planner-worker")  # as the OS sees it: hilsim up leaves it out of SCHED_FIFO
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
