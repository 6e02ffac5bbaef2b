"""Navigator service: rover goals (x, y, optional yaw) → occupancy grid → SE(2) plan → path following on ``cmd_vel``.

At start it rasterises the world's static geometry (the scenario's MJCF, ``world.model``) into an
occupancy grid (:mod:`hilsim.navigation.grid`) at ``navigator.resolution``; each goal is planned
with OMPL in SE(2) with Reeds–Shepp curves, the robot's footprint as circles on the grid inflated
by their radius (:mod:`hilsim.navigation.planner`), and followed by a pure-pursuit follower for a
four-wheel-steer base (:mod:`hilsim.navigation.follower`).

Where the rover is: the controller's wheel odometry (``odom``, with the IMU's yaw rate), never
the physics truth (that is for judging). ``odom`` starts at the identity when the rover stands at
its initial pose, so the navigator puts it in the world by that pose, read from the model (the
free joint's initial position and orientation): pose_world = initial ∘ pose_odom. Why odometry
alone: on the goal sequences of the rover scenarios (up to ~40 m of driving, turns in place)
the wheel-and-gyro odometry stays within a few centimetres of the truth (checked by
``tests/test_rover_nav_e2e.py`` at every goal, against truth/odom), well inside the 0.2 m the
goals are judged by; the GPS outdoors (σ = 1 m) would only make a 0.2 m goal worse, so it is not
fused. A longer mission would need it (or a laser-based localisation).

Reads (``<prefix>/<robot>/…``):
  ``odom`` (nav_msgs/Odometry, the controller's; one per control step). Every
  ``navigator.rate_hz`` step's odometry is a *decision tick*: goals start, plans are made and
  ``cmd_vel`` is computed there; in lockstep the tick is acknowledged on ``sync/navigator`` after
  the ``cmd_vel`` (and any plan) is out, so planning and following take no sim time and a run
  repeats bit for bit.
Writes:
  ``cmd_vel`` (geometry_msgs/Twist, base_link): exactly one per tick, zero when no goal is being
  followed (in lockstep the controller holds a control step until the cmd_vel of every earlier tick
  has come, so a command takes effect at the same step in every run); in realtime also a zero
  twist at once when a goal is canceled or preempted;
  ``map`` (nav_msgs/OccupancyGrid, ``world``: 100 obstacle, 50 within the footprint's reach of
  one, 0 free) at the first tick and every ``navigator.map_period`` sim seconds, so a recorder
  started late still gets it; ``plan`` (nav_msgs/Path, ``world``) when a goal is planned, an
  empty one when it ends;
  ``navigator/feedback`` (Move_Feedback: ``planning``, ``executing``, ``settling``; progress along
  the path), ``navigator/result`` (Move_Result; ``execution_error`` = [position error m, yaw
  error rad] by the odometry, ``planning_time`` wall seconds); ``task/result`` (Move_Result
  ``task``): the scenario task's outcome (``hilsim up`` ends the run on it);
  ``sync/navigator`` (lockstep acknowledgement).
Serves:
  ``navigator/goal`` (Move_Goal, ``target_kind: pose``: the base's x, y in ``world``, the yaw of
  ``pose.orientation`` when ``use_orientation``) → Move_GoalResponse; ``navigator/cancel``.
  A new goal preempts the running one; a goal outside the map or where the footprint does not
  fit is rejected with the reason. A rover more than ``navigator.replan_distance`` off its path,
  or stopped outside ``goal_tolerance``, is planned again from where it is (``max_replans``).

The scenario task (``task.targets``: ``[x, y]`` or ``[x, y, yaw]`` each) runs as goals
``task-1`` … ``task-N`` through :class:`hilsim.sim.tasks.TaskRunner`, like the arm planner's.
Planning runs in the tick's handler, under the service lock: a goal or cancel query waits for a
plan in progress (at most ``navigator.planning_time`` wall seconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel

from hilsim.core import msgs
from hilsim.core.config import ConfigError, NavigatorConfig, Scenario
from hilsim.core.geometry import heading, yaw_of
from hilsim.core.service import Service
from hilsim.navigation import grid as gridmod
from hilsim.navigation.follower import Follower, FollowerParams, wrap
from hilsim.navigation.planner import Footprint, SE2Planner, path_length
from hilsim.sim.tasks import TaskGoal, TaskRunner, is_reserved

FEEDBACK_PERIOD_NS = 500_000_000  # 2 Hz sim
SETTLE_MAX_NS = 1_000_000_000  # a goal is judged at rest, or at most 1 s (sim) after the follower ended


def rover_targets(sc: Scenario) -> list[tuple[float, float, float | None]]:
    """The scenario task's targets as (x, y, yaw or None); one-line ConfigError on a bad one."""
    out = []
    for i, t in enumerate(sc.task.targets):
        if len(t) not in (2, 3):
            raise ConfigError(f"{sc.source or 'scenario'}: task.targets[{i}]: a rover target is [x, y] or "
                              f"[x, y, yaw] (got {len(t)} numbers)")
        out.append((float(t[0]), float(t[1]), float(t[2]) if len(t) == 3 else None))
    return out


def initial_pose(model: Any) -> tuple[float, float, float]:
    """World x, y, yaw of the model's free-joint base at its initial configuration (qpos0)."""
    import mujoco

    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            a = model.jnt_qposadr[j]
            x, y = float(model.qpos0[a]), float(model.qpos0[a + 1])
            w, qx, qy, qz = (float(v) for v in model.qpos0[a + 3:a + 7])
            return x, y, heading(w, qx, qy, qz)
    raise ConfigError("world.model: the navigator needs a mobile base (a free joint); this model has none")


def quat_of(yaw: float) -> msgs.Quaternion:
    return msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def build(sc: Scenario, cfg: NavigatorConfig) -> tuple[gridmod.Grid, SE2Planner]:
    """The grid and the planner of a scenario (the service's and ``hilsim plan evaluate``'s)."""
    try:
        g = gridmod.from_model(sc.world.model, resolution=cfg.resolution, z_band=cfg.z_band, bounds=cfg.bounds)
    except ValueError as e:
        raise ConfigError(f"{sc.source or 'scenario'}: navigator: {e}") from None
    fp = Footprint.covering(cfg.footprint.length, cfg.footprint.width, cfg.footprint.circles)
    try:
        planner = SE2Planner(g, fp, turning_radius=cfg.turning_radius, clearance=cfg.clearance, planner=cfg.planner,
                             planner_range=cfg.planner_range)
    except ValueError as e:
        raise ConfigError(f"{sc.source or 'scenario'}: navigator.planner: {e}") from None
    return g, planner


@dataclass
class NavGoal:
    goal_id: str
    x: float
    y: float
    yaw: float | None
    task: bool = False
    state: str = "queued"  # queued | planning | executing | settling | done
    follower: Follower | None = None
    deadline_ns: int = 0
    planning_time: float = 0.0
    invalid: tuple[int, str] | None = None  # a task target that cannot be used: reported in turn
    last_feedback_ns: int = -FEEDBACK_PERIOD_NS
    settle_since: int = 0
    replans: int = 0


class NavigatorService(Service):
    name: ClassVar[str] = "navigator"
    stop_rank: ClassVar[int] = 15  # stops after physics, before the controller it drives
    Config: ClassVar[type[BaseModel]] = NavigatorConfig

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        try:
            rate = NavigatorConfig.model_validate(sc.section("navigator")).rate_hz
        except ValueError:  # a bad section is the constructor's one-line error
            rate = NavigatorConfig().rate_hz
        return round(1.0 / (rate * sc.clock.dt))

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        cfg: NavigatorConfig = self.cfg
        where = scenario.source or "scenario"
        ratio = scenario.controller.rate_hz / cfg.rate_hz
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ConfigError(f"{where}: navigator.rate_hz ({cfg.rate_hz:g}) must divide controller.rate_hz "
                              f"({scenario.controller.rate_hz:g}): it decides on the odometry of its own steps")
        self.period = round(1.0 / (cfg.rate_hz * scenario.clock.dt))
        targets = rover_targets(scenario)
        self.grid, self.planner = build(scenario, cfg)
        import mujoco

        self.origin = initial_pose(mujoco.MjModel.from_xml_path(str(scenario.world.model)))
        self.fparams = FollowerParams(**cfg.follower.model_dump())
        self.pose: tuple[float, float, float] | None = None  # world x, y, yaw from the odometry
        self.speed = (0.0, 0.0)  # |v|, |wz| from the odometry
        self.active: NavGoal | None = None
        self.pending: list[NavGoal] = []
        self.task_runner = TaskRunner([np.array([x, y, math.nan if yaw is None else yaw]) for x, y, yaw in targets],
                                      self._submit_task_goal, self._report_task, planner=cfg.planner)
        self.goal_counter = 0
        self.plans = 0
        self.goals_rejected = 0
        self.last_planning_time = 0.0
        self.last_map_ns: int | None = None
        self._map_msg: msgs.OccupancyGrid | None = None
        self.tick_cmd = msgs.Twist()

    # ------------------------------------------------------------------ setup
    def setup(self) -> None:
        k = self.keys
        self.pub_cmd = self.publisher(k.topic("cmd_vel"))
        self.pub_map = self.publisher(k.topic("map"))
        self.pub_plan = self.publisher(k.topic("plan"))
        self.pub_feedback = self.publisher(k.topic("navigator/feedback"))
        self.pub_result = self.publisher(k.topic("navigator/result"))
        self.pub_task_result = self.publisher(k.topic("task/result"))
        self.subscribe(k.topic("odom"), msgs.Odometry, self.on_odom)
        self.queryable(k.topic("navigator/goal"), msgs.MoveGoal, self.on_goal, reject=self._reject)
        self.queryable(k.topic("navigator/cancel"), msgs.CancelRequest, self.on_cancel, reject=self._reject)

    def health_values(self) -> dict[str, Any]:
        x, y, th = self.pose or (math.nan, math.nan, math.nan)
        return {
            "goal": self.active.goal_id if self.active else "",
            "goal_state": self.active.state if self.active else "idle",
            "pose": f"{x:.3f},{y:.3f},{th:.3f}",
            "plans": self.plans,
            "goals_rejected": self.goals_rejected,
            "last_planning_time_s": round(self.last_planning_time, 4),
            "map_cells": f"{self.grid.width}x{self.grid.height}",
        }

    # ------------------------------------------------------------------ goals
    def _reject(self, reason: str, goal_id: str = "") -> msgs.GoalResponse:
        self.goals_rejected += 1
        return msgs.GoalResponse(goal_id=goal_id, accepted=False, reason=reason)

    def check_goal(self, x: float, y: float, yaw: float | None) -> tuple[int, str] | None:
        """(error code, reason) if the rover cannot stand at the goal; a goal without a yaw
        needs some yaw at which the footprint fits."""
        yaws = [yaw] if yaw is not None else [i * math.pi / 8 for i in range(16)]
        why = None
        for th in yaws:
            why = self.planner.why_invalid(x, y, th)
            if why is None:
                return None
        assert why is not None
        code = msgs.GOAL_OUT_OF_LIMITS if "outside the map" in why else msgs.GOAL_IN_COLLISION
        return code, f"{'GOAL_OUT_OF_LIMITS' if code == msgs.GOAL_OUT_OF_LIMITS else 'GOAL_IN_COLLISION'}: {why}"

    def on_goal(self, g: msgs.MoveGoal) -> msgs.GoalResponse:
        self.goal_counter += 1
        gid = g.goal_id or f"goal-{self.goal_counter}"
        if is_reserved(gid):
            return self._reject(f"INVALID_GOAL: goal id {gid!r} is reserved for the scenario task", gid)
        if g.target_kind != "pose":
            return self._reject(f"INVALID_GOAL: the rover takes target_kind 'pose' (x, y, optional yaw), "
                                f"not {g.target_kind!r}", gid)
        yaw = None
        if g.use_orientation:
            o = g.pose.orientation
            norm = math.sqrt(o.w**2 + o.x**2 + o.y**2 + o.z**2)
            if abs(norm - 1.0) > 1e-3:
                return self._reject(f"INVALID_GOAL: orientation quaternion is not unit (norm {norm:.4f})", gid)
            yaw = yaw_of(o)
        if (bad := self.check_goal(g.pose.position.x, g.pose.position.y, yaw)) is not None:
            return self._reject(bad[1], gid)
        self._preempt(f"preempted by goal {gid}")
        self.pending.append(NavGoal(gid, g.pose.position.x, g.pose.position.y, yaw))
        return msgs.GoalResponse(goal_id=gid, accepted=True, reason="accepted")

    def on_cancel(self, req: msgs.CancelRequest) -> msgs.GoalResponse:
        goals = ([self.active] if self.active else []) + self.pending
        for goal in goals:
            if goal.goal_id == req.goal_id or (req.goal_id == "" and goal is goals[0]):
                self._finish(goal, False, msgs.CANCELED, "canceled by request")
                return msgs.GoalResponse(goal_id=goal.goal_id, accepted=True, reason="canceled")
        return msgs.GoalResponse(goal_id=req.goal_id, accepted=False, reason=f"no active goal {req.goal_id!r}")

    def _preempt(self, why: str) -> None:
        for goal in [*self.pending, *([self.active] if self.active else [])]:
            self._finish(goal, False, msgs.CANCELED, why)

    def _submit_task_goal(self, tg: TaskGoal) -> None:
        x, y, yaw = (float(v) for v in tg.target)
        goal = NavGoal(tg.goal_id, x, y, None if math.isnan(yaw) else yaw, task=True)
        goal.invalid = self.check_goal(goal.x, goal.y, goal.yaw)  # reported in turn, as a failed step
        self.pending.append(goal)

    def _report_task(self, result: msgs.MoveResult) -> None:
        self.pub_result.put(result)
        self.pub_task_result.put(result)
        self.log.info("task finished: %s", result.message)

    # ------------------------------------------------------------------ results
    def _error(self, goal: NavGoal) -> list[float]:
        if self.pose is None:
            return []
        x, y, th = self.pose
        return [math.hypot(goal.x - x, goal.y - y), abs(wrap(goal.yaw - th)) if goal.yaw is not None else 0.0]

    def _finish(self, goal: NavGoal, success: bool, code: int, message: str) -> None:
        was_moving = goal.state in ("executing", "settling")
        goal.state = "done"
        if goal in self.pending:
            self.pending.remove(goal)
        if self.active is goal:
            self.active = None
            self.tick_cmd = msgs.Twist()  # this tick's command, if in one: stand still
            if was_moving and not self.lockstep:
                self.pub_cmd.put(msgs.Twist())  # stop now, not after the controller's cmd_timeout
            self.pub_plan.put(msgs.Path(header=msgs.header(self.sim_ns, "world")))
        err = self._error(goal)
        self.pub_result.put(msgs.MoveResult(
            header=msgs.header(self.sim_ns), goal_id=goal.goal_id, success=success, error_code=code,
            message=message, planning_time=goal.planning_time, execution_error=err, planner=self.cfg.planner,
        ))
        if success:
            self.log.info("%s: %s (error %s)", goal.goal_id, message, ", ".join(f"{e:.3f}" for e in err))
        if goal.task:
            self.task_runner.on_goal_result(success, self.sim_ns, err)

    def _feedback(self, goal: NavGoal, progress: float, now_ns: int) -> None:
        goal.last_feedback_ns = now_ns
        self.pub_feedback.put(msgs.MoveFeedback(header=msgs.header(now_ns), goal_id=goal.goal_id,
                                                state=goal.state, progress=progress))

    # ------------------------------------------------------------------ inputs
    def on_odom(self, o: msgs.Odometry, _key: str) -> None:
        t = msgs.ns_of(o.header.stamp)
        x0, y0, th0 = self.origin
        p = o.pose.pose.position
        c, s = math.cos(th0), math.sin(th0)
        self.pose = (x0 + c * p.x - s * p.y, y0 + s * p.x + c * p.y, wrap(th0 + yaw_of(o.pose.pose.orientation)))
        tw = o.twist.twist
        self.speed = (math.hypot(tw.linear.x, tw.linear.y), abs(tw.angular.z))
        if (t // self.sc.dt_ns) % self.period == 0:
            self.on_tick(t)

    def on_tick(self, t: int) -> None:
        """A decision step: map, goals, plan, follow; then the lockstep acknowledgement."""
        self.sim_ns = max(self.sim_ns, t)
        self.tick_cmd = msgs.Twist()  # stand still unless a goal is being followed
        try:
            if self.last_map_ns is None or t - self.last_map_ns >= round(self.cfg.map_period * 1e9):
                self._publish_map(t)
            self.task_runner.on_tick()
            if self.active is None and self.pending:
                self._start(self.pending.pop(0), t)
            if self.active is not None:
                self._follow(self.active, t)
        finally:
            # exactly one cmd_vel per tick, goal or not: in lockstep the controller waits for it
            # (services/rover_controller.py), so it takes effect at the same step in every run
            self.pub_cmd.put(self.tick_cmd)
            if self.lockstep:
                self.ack(t)

    def _publish_map(self, t: int) -> None:
        if self._map_msg is None:
            levels = np.where(self.grid.occ, gridmod.OCCUPIED, np.where(self.grid.inflated, 50, gridmod.FREE))
            self._map_msg = self.grid.to_msg(t)
            self._map_msg.data = levels.astype(np.int8).ravel().tolist()
        self._map_msg.header = msgs.header(t, "world")
        self.pub_map.put(self._map_msg)
        self.last_map_ns = t

    def _start(self, goal: NavGoal, t: int) -> None:
        if goal.invalid is not None:
            self._finish(goal, False, *goal.invalid)
            return
        assert self.pose is not None
        self.active = goal
        goal.state = "planning"
        self._feedback(goal, 0.0, t)
        self._plan(goal, t)

    def _plan(self, goal: NavGoal, t: int) -> None:
        """Plan from the estimated pose to the goal and follow the plan (a goal's start, or a replan)."""
        assert self.pose is not None
        x, y, th = self.pose
        # no yaw asked for: arrive heading along the straight line from here (any valid yaw will do)
        gyaw = goal.yaw
        if gyaw is None:
            gyaw = math.atan2(goal.y - y, goal.x - x) if math.hypot(goal.y - y, goal.x - x) > 1e-6 else th
            for k in range(16):
                cand = wrap(gyaw + (k + 1) // 2 * (math.pi / 8) * (1 if k % 2 else -1))
                if self.planner.is_valid(goal.x, goal.y, cand):
                    gyaw = cand
                    break
        res = self.planner.plan((x, y, th), (goal.x, goal.y, gyaw), max_iterations=self.cfg.iterations,
                                time_limit=self.cfg.planning_time, seed=self.sc.seed, attempts=self.cfg.attempts)
        self.plans += 1
        goal.planning_time = self.last_planning_time = res.planning_time
        if res.wall_cap_hit:
            self.warn(f"{goal.goal_id}: planning hit the wall-clock cap ({self.cfg.planning_time:g} s): "
                      "not deterministic")
        if res.path is None:
            code = msgs.TIMED_OUT if res.iterations else msgs.PLANNING_FAILED
            self._finish(goal, False, code, f"planning failed: {res.message}")
            return
        self.pub_plan.put(msgs.Path(header=msgs.header(t, "world"), poses=[
            msgs.PoseStamped(header=msgs.header(t, "world"),
                             pose=msgs.Pose(position=msgs.Point(x=float(px), y=float(py)), orientation=quat_of(pth)))
            for px, py, pth in res.path]))
        goal.follower = Follower(res.path, self.fparams, final_yaw=goal.yaw)
        length = path_length(res.path)
        if not goal.replans:  # a replan keeps the goal's deadline
            goal.deadline_ns = t + round((length / self.fparams.max_speed * 2 + self.cfg.goal_timeout) * 1e9)
        goal.state = "executing"
        self.log.info("%s: planned %.2f m (%d poses) in %.3f s, %d iterations", goal.goal_id, length,
                      len(res.path), res.planning_time, res.iterations)

    def _follow(self, goal: NavGoal, t: int) -> None:
        assert goal.follower is not None and self.pose is not None
        f = goal.follower
        if goal.state == "executing":
            vx, vy, wz = f.step(*self.pose)
            if f.off_path > self.cfg.replan_distance and goal.replans < self.cfg.max_replans:
                self._replan(goal, t, f"{f.off_path:.2f} m off its path")
                return
            if f.done:
                goal.state = "settling"
                goal.settle_since = t
            else:
                self.tick_cmd = msgs.Twist(linear=msgs.Vector3(x=vx, y=vy), angular=msgs.Vector3(z=wz))
        # at rest by the odometry, or after SETTLE_MAX whatever a biased gyro says
        if goal.state == "settling" and ((self.speed[0] < 0.01 and self.speed[1] < 0.02)
                                         or t - goal.settle_since >= SETTLE_MAX_NS):
            err = self._error(goal)
            if err[0] <= self.cfg.goal_tolerance and (goal.yaw is None or err[1] <= 2 * self.fparams.yaw_tolerance):
                self._finish(goal, True, msgs.SUCCESS, "goal reached")
            elif goal.replans < self.cfg.max_replans:
                self._replan(goal, t, f"stopped {err[0]:.3f} m / {err[1]:.3f} rad from the goal")
            else:
                self._finish(goal, False, msgs.CONTROL_FAILED,
                             f"stopped {err[0]:.3f} m / {err[1]:.3f} rad from the goal")
            return
        if t >= goal.deadline_ns:
            self._finish(goal, False, msgs.TIMED_OUT, "goal not reached in time")
            return
        if t - goal.last_feedback_ns >= FEEDBACK_PERIOD_NS:
            self._feedback(goal, f.progress, t)

    def _replan(self, goal: NavGoal, t: int, why: str) -> None:
        """The rover strayed from its path, or stopped short of the goal: stand still this tick and
        plan again from where it is (at most ``navigator.max_replans`` times per goal)."""
        goal.replans += 1
        self.tick_cmd = msgs.Twist()
        self.warn(f"{goal.goal_id}: {why}; replanning ({goal.replans}/{self.cfg.max_replans})")
        goal.state = "planning"
        self._plan(goal, t)
