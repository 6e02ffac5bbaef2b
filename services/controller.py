"""Joint controller service: follows trajectories with one PID per joint.

Reads (``<prefix>/<robot>/…``):
  ``joint_states`` (sensor_msgs/JointState, measured; one control step per message),
  ``joint_trajectory`` (trajectory_msgs/JointTrajectory).
Writes:
  ``joint_commands`` (sensor_msgs/JointState) stamped like the joint_states it answers, every
  joint in every message, so each joint's server (physics or an external one) reads the field of
  its interface (``joints.<name>.interface``): ``effort`` = the PID output (effort joints; 0 for
  the others), ``position`` = the reference, ``velocity`` = the reference velocity (position
  joints: feed-forward) or, for velocity joints, the velocity command
  ``v_ref + controller.velocity_gain·(p_ref − p)``. ``position`` and ``velocity`` are filled when
  any joint has a position or velocity interface (else they are empty: nobody reads them). In
  lockstep mode this message is the controller's acknowledgement of the step (no ``sync`` message);
  ``controller/reference`` (sensor_msgs/JointState: reference position and velocity), same stamp.
  With ``fleet.arrays`` (robots > 1, :class:`FleetControllerService`) the fleet driver hands the
  controller its measurement and runs its PID; both messages are then built only while subscribed.
Serves:
  ``controller/has_trajectory`` (builtin_interfaces/Time, a trajectory's start stamp → GoalResponse):
  answered once this controller holds the ``joint_trajectory`` of that stamp (accepted, or not with
  the reason it was rejected), or after a third of ``clock.ack_timeout`` without it (not accepted). In
  lockstep the planner acknowledges its tick only then: Zenoh orders nothing between keys, so without
  it a trajectory taken late (a loaded machine) would act steps later than in another run of the seed;
  ``controller/set_parameters`` (SetParameters ``<joint>.<kp|ki|kd|i_limit|output_limit|feedforward>``
  → SetParametersResult): all-or-nothing, effective at the next control step; the gains in
  force are in its health (``gains:<joint>`` = ``kp=… ki=… kd=… i_limit=… …``).

Serves the ROS 2 action ``control_msgs/action/FollowJointTrajectory`` at
``/<robot>/<controller.params.action_ns>`` (default ``follow_joint_trajectory``, what MoveIt's
controller manager calls with ``action_ns: follow_joint_trajectory``; ``""`` serves none), as a node on
rmw_zenoh does (:mod:`hilsim.services.ros2_action`). A goal's trajectory is followed exactly as a
``joint_trajectory`` message; feedback (desired, actual, error of the goal's joints) at
``controller.params.action_feedback_hz`` of sim time; the result is SUCCESSFUL once every joint of the
goal is within its goal tolerance (else ``task.tolerance``) of the last point after its time,
GOAL_TOLERANCE_VIOLATED if that has not happened ``goal_time_tolerance`` (else
``controller.params.goal_time_tolerance``) later, PATH_TOLERANCE_VIOLATED as soon as a joint with a
path tolerance strays further from the reference (the arm then holds where it is), INVALID_JOINTS for
joint names that are not the controller's, INVALID_GOAL for a trajectory it cannot follow (no points,
times not increasing, outside the limits, multi-DOF), OLD_HEADER_TIMESTAMP for one that has ended before
it arrived. Invalid goals are accepted and aborted with that code (so the client reads why); a cancel
holds the current position; a new goal, or a trajectory on ``joint_trajectory``, aborts the goal
being followed.

Setpoint: the first measured position until a trajectory arrives; a trajectory replaces the
current one at its start time (``header.stamp``; zero = on receipt) and its last point is held
after its end; an empty trajectory means hold the current measured position. A stamped trajectory on
``joint_trajectory`` that starts before the one being followed is rejected as out of date (a replay,
e.g. of the planner's own: docs/security.md).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError, Scenario, format_error
from hilsim.core.keys import NOT_REACHED
from hilsim.core.msgs import control as cm
from hilsim.core.restart import keep, kept
from hilsim.core.service import Publisher, Service
from hilsim.services.ros2_action import ActionServer, goal_text
from hilsim.sim import control

FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"
HANDOFF_KEPT = 64  # the start stamps of the last trajectories taken, each with why it was rejected (or None)


class Params(BaseModel):
    """``controller.params`` of the joint_trajectory controller."""

    model_config = ConfigDict(extra="forbid")
    action_ns: str = Field("follow_joint_trajectory", description="name of the FollowJointTrajectory action below "
                           "the robot's namespace (absolute if it starts with '/'); empty: no action")
    action_feedback_hz: float = Field(20.0, gt=0, description="feedback rate of the action [1/s of sim time]")
    goal_time_tolerance: float = Field(1.0, gt=0, description="how long after a goal's last point the joints "
                                       "may take to be within tolerance, when the goal gives no time [s]")


@dataclass
class _FjtGoal:
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


class ControllerService(Service):
    """The ``joint_trajectory`` control law (``controller.type``); other types are other
    :class:`~hilsim.core.service.Service` subclasses named ``controller``, found in the registry."""

    name = "controller"
    stop_rank = 20
    ack_via = "joint_commands"

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        return sc.control_decimation

    @classmethod
    def resolve(cls, sc: Scenario) -> type[Service]:
        law = registry.load("controllers", sc.controller.type)
        if not (isinstance(law, type) and issubclass(law, Service)) or law.name != cls.name:
            # the launcher and physics know it as "controller": any other name would never be seen
            raise ConfigError(f"{sc.source}: controller.type: {sc.controller.type!r} must be a hilsim Service "
                              f"class named {cls.name!r} (got {law!r})")
        return law

    @classmethod
    def array_driver(cls, sc: Scenario) -> type[Service] | None:
        """The fleet driver running every robot's PID as arrays (fleet.arrays); this law only, not a
        subclass (another law's step is its own)."""
        return FleetControllerService if cls is ControllerService else None

    def ack_publisher(self) -> Publisher | None:
        return self.cmd_pub

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = str(scenario.source) if scenario.source else ""
        self.joints = control.joint_table(scenario.world.model)
        self.names = list(self.joints.names)
        self.n = self.joints.n
        self.interfaces = [scenario.joint(n).interface for n in self.names]
        self.effort_joint = [i == "effort" for i in self.interfaces]
        self.velocity_joint = np.array([i == "velocity" for i in self.interfaces])
        self.any_velocity = bool(self.velocity_joint.any())
        self.setpoints = any(i != "effort" for i in self.interfaces)  # position/velocity in joint_commands
        self.velocity_gain = scenario.controller.velocity_gain
        gains = control.gains_for(scenario.controller.gains, self.names, where)
        self.pids = [
            control.Pid(g, float(self.joints.effort_lower[i]), float(self.joints.effort_upper[i]))
            for i, g in enumerate(gains)
        ]
        # Fixed control period: the encoders publish at controller.rate_hz (checked by the sensors).
        self.dt = 1.0 / scenario.controller.rate_hz
        self.hold_timeout_ns = round(scenario.controller.hold_timeout * 1e9)
        self._order: list[int] | None = None  # measured -> model order, when the names differ
        self._order_names: list[str] = list(self.names)
        self.hold: np.ndarray | None = None  # setpoint without a trajectory
        self.traj: control.TrajectorySampler | None = None  # being followed
        self.next_traj: control.TrajectorySampler | None = None  # accepted, starts later
        self._pending: tuple[msgs.JointTrajectory, str] | None = None  # arrived before any measurement
        # the trajectories taken (start stamp -> why rejected, or None), for has_trajectory's waiters
        self._taken: OrderedDict[int, str | None] = OrderedDict()
        self._took = threading.Condition(self.lock)
        self.pos = np.zeros(self.n)
        self.vel = np.zeros(self.n)
        self.ref_pos = np.zeros(self.n)
        self.ref_vel = np.zeros(self.n)
        self._zero = np.zeros(self.n)
        self.last_ns: int | None = None
        self.tracking_error = 0.0
        self.max_tracking_error = 0.0
        self.gaps = 0
        self.steps = 0
        self.gains_version = 0
        try:
            self.params = Params.model_validate(scenario.controller.params)
        except ValidationError as e:
            raise ConfigError(format_error(where or "scenario", e, prefix="controller.params")) from None
        self.fjt: ActionServer | None = None
        self.fjt_goal: _FjtGoal | None = None
        self.fjt_goals = 0
        # live gain changes, kept for a restarted controller (hilsim.core.restart): scenario + these
        self.live_gains: dict[str, float] = dict(kept(scenario, self.name).get("gains", {}))
        if self.live_gains:
            control.set_parameters(self.pids, self.names,
                                   [msgs.Parameter(name=k, value=v) for k, v in self.live_gains.items()])
            self.log.info("restarted: live gains taken over: %s",
                          ", ".join(f"{k}={v:g}" for k, v in sorted(self.live_gains.items())))

    # ------------------------------------------------------------------ wiring
    def setup(self) -> None:
        self.cmd_pub = self.publisher(self.keys.topic("joint_commands"))
        self.ref_pub = self.publisher(self.keys.topic("controller/reference"))
        if not self.fleet_driven:  # robots as arrays: the fleet driver hands each robot its measurement
            self.subscribe(self.keys.topic("joint_states"), msgs.JointState, self.on_joint_states, n_joints=self.n)
        # No n_joints here: a trajectory may name a subset of the joints.
        # a trajectory is given once: late (a loaded machine) it is still the task's (stream=False)
        self.subscribe(self.keys.topic("joint_trajectory"), msgs.JointTrajectory, self.on_trajectory, stream=False)
        self.queryable(
            self.keys.topic("controller/set_parameters"),
            msgs.SetParameters,
            self.on_set_parameters,
            reject=lambda reason: msgs.SetParametersResult(successful=False, reason=reason),
        )
        self.queryable(self.keys.topic("controller/has_trajectory"), msgs.Time, self.on_has_trajectory,
                       reject=lambda reason: msgs.GoalResponse(accepted=False, reason=reason))
        if self.params.action_ns.strip("/"):
            self.fjt = ActionServer(self, self.params.action_ns, FOLLOW_JOINT_TRAJECTORY,
                                    self.on_fjt_goal, self.on_fjt_cancel)

    # ------------------------------------------------------------------ control step
    def _measure(self, msg: msgs.JointState, key: str, stamp: int) -> bool:
        """Copy the measurement into self.pos/self.vel in model order; False if unusable."""
        if not msg.position:
            return self.reject(key, "JointState without positions")
        if msg.name != self._order_names:
            if sorted(msg.name) != sorted(self.names):
                return self.reject(key, f"JointState names {list(msg.name)} are not the joints {self.names}")
            self._order_names = list(msg.name)
            self._order = None if self._order_names == self.names else [self._order_names.index(n) for n in self.names]
        pos = np.asarray(msg.position, float)
        if self._order is not None:
            pos = pos[self._order]
        if msg.velocity:
            vel = np.asarray(msg.velocity, float)
            if self._order is not None:
                vel = vel[self._order]
        elif self.last_ns is not None and stamp > self.last_ns:
            # No velocity reported (e.g. a position-only drive): backward difference.
            vel = (pos - self.pos) / ((stamp - self.last_ns) * 1e-9)
        else:
            vel = self._zero
        self.pos, self.vel = pos, vel
        return True

    def on_joint_states(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        if not self._measure(msg, key, stamp):
            return
        self.prepare(stamp)
        u = [
            pid.update(rp, rv, p, v, self.dt) if eff else 0.0
            for pid, eff, rp, rv, p, v in zip(
                self.pids, self.effort_joint, self.ref_pos.tolist(), self.ref_vel.tolist(), self.pos.tolist(),
                self.vel.tolist(), strict=True,
            )
        ]
        self.emit(stamp, u)

    def measure_row(self, pos: np.ndarray, vel: np.ndarray | None, stamp: int) -> None:
        """This robot's measurement from a fleet sample (model order, as :meth:`_measure` leaves it)."""
        if vel is None:  # no velocity reported: backward difference, as _measure does
            vel = (pos - self.pos) / ((stamp - self.last_ns) * 1e-9) if self.last_ns is not None and \
                stamp > self.last_ns else self._zero
        self.pos, self.vel = pos, vel

    def prepare(self, stamp: int) -> None:
        """One control step up to the PID, with self.pos/self.vel measured at ``stamp``: the reference
        (self.ref_pos, self.ref_vel), the action goal, the tracking error. The fleet driver
        (robots as arrays) calls it for each robot and runs every robot's PID at once."""
        if self.last_ns is not None and stamp - self.last_ns > self.hold_timeout_ns:
            self.gaps += 1
            self.warn(f"no joint_states for {(stamp - self.last_ns) * 1e-9:.3f} s of sim time")
        self.last_ns = stamp
        self.sim_ns = stamp
        if self.hold is None:
            self.hold = self.pos.copy()  # hold where the arm is until told otherwise
            if self._pending is not None:
                self._accept(*self._pending)
                self._pending = None
        self._reference(stamp)
        if self.fjt_goal is not None:
            self._follow_goal(stamp)
        err = self.ref_pos - self.pos
        self.tracking_error = float(np.abs(err).max())  # the method: np.max's Python wrapper costs more
        if self.traj is not None or self.next_traj is not None:
            self.max_tracking_error = max(self.max_tracking_error, self.tracking_error)

    def velocity_command(self) -> np.ndarray:
        """joint_commands' velocity: the reference, or for velocity joints ``v_ref + velocity_gain·(p_ref − p)``
        (a velocity drive needs the position error closed here, as ros2_control's JTC does)."""
        if not self.any_velocity:
            return self.ref_vel
        v_cmd = self.ref_vel + self.velocity_gain * (self.ref_pos - self.pos)
        return np.where(self.velocity_joint, v_cmd, self.ref_vel)

    def emit(self, stamp: int, u: list[float] | None) -> None:
        """Publish the step's joint_commands (efforts ``u``; None: the fleet driver sent them in its fleet
        command and nobody subscribes this robot's) and controller/reference (built only if subscribed)."""
        self.steps += 1
        ref_wanted = self.ref_pub.wanted(covered=self.fleet_driven)  # robots as arrays: in the fleet's too
        if u is None and not ref_wanted:  # the fleet's usual step: nothing of this robot's is read
            self.cmd_pub.skip()
            self.ref_pub.skip()
            return
        header = msgs.header(stamp)
        position, velocity = self.ref_pos.tolist(), self.ref_vel.tolist()
        if u is None:
            self.cmd_pub.skip()
        elif self.setpoints:
            vel = self.velocity_command().tolist() if self.any_velocity else velocity
            self.cmd_pub.put(msgs.JointState(header=header, name=self.names, position=position, velocity=vel, effort=u))
        else:  # every joint takes effort: the setpoints would only cost encoding and decoding
            self.cmd_pub.put(msgs.JointState(header=header, name=self.names, effort=u))
        if ref_wanted:
            self.ref_pub.put(msgs.JointState(header=header, name=self.names, position=position, velocity=velocity))
        else:
            self.ref_pub.skip()

    def _reference(self, stamp: int) -> None:
        if self.next_traj is not None and stamp >= self.next_traj.start_ns:
            self.traj, self.next_traj = self.next_traj, None
        if self.traj is not None:
            self.ref_pos, self.ref_vel = self.traj.sample(stamp)
        else:
            assert self.hold is not None
            self.ref_pos, self.ref_vel = self.hold, self._zero

    # ------------------------------------------------------------------ trajectories
    def on_trajectory(self, msg: msgs.JointTrajectory, key: str) -> None:
        if self.hold is None:
            self._pending = (msg, key)  # the setpoint to start from is not known yet: taken before any step
            why = None
        else:
            why = self._out_of_date(msg)
            if why is not None:
                self.reject(key, why)
            else:
                why = self._accept(msg, key)
        self._taken[msgs.ns_of(msg.header.stamp)] = why
        while len(self._taken) > HANDOFF_KEPT:
            self._taken.popitem(last=False)
        self._took.notify_all()

    def _out_of_date(self, msg: msgs.JointTrajectory) -> str | None:
        """Why a stamped trajectory comes too late to be followed, else None: one that starts before the
        trajectory being followed (a newer one replaced it). Such a sample is a replay, most likely of the
        planner's own (its writer's id and all: docs/security.md); followed, it would send the arm back
        to an old target. One that ended before it arrived is still taken when nothing newer is followed:
        the planner hands its trajectory again to a restarted controller, which then holds its end.
        Stamp zero means "now": never late."""
        stamp = msgs.ns_of(msg.header.stamp)
        if not stamp or not msg.points:
            return None
        current = self.next_traj or self.traj
        if current is not None and stamp < current.start_ns:
            return (f"the trajectory starts at {stamp * 1e-9:.3f} s, before the one being followed "
                    f"({current.start_ns * 1e-9:.3f} s): out of date (a replay?)")
        return None

    def on_has_trajectory(self, start: msgs.Time) -> msgs.GoalResponse:
        """``controller/has_trajectory`` (see the module docstring); runs under self.lock, which the wait
        gives up, so the trajectory's own subscriber thread can take it meanwhile."""
        ns = msgs.ns_of(start)
        # well within physics' patience, so a trajectory lost on the way is a warning, not a stalled run
        wait = self.sc.clock.ack_timeout / 3
        end = time.monotonic() + wait
        while ns not in self._taken and not self.stop_event.is_set() and (left := end - time.monotonic()) > 0:
            self._took.wait(min(left, 0.2))
        if ns not in self._taken:
            return msgs.GoalResponse(accepted=False, reason=f"{NOT_REACHED} starting at {ns * 1e-9:.3f} s "
                                     f"reached the controller within {wait:g} s")
        why = self._taken[ns]
        return msgs.GoalResponse(accepted=why is None, reason=why or "")

    def _accept(self, msg: msgs.JointTrajectory, key: str) -> str | None:
        """Follow ``msg`` from its start; None, or why it cannot be followed (a rejected payload of ``key``)."""
        if not msg.points:
            # ROS convention: an empty trajectory stops the motion where the arm is now.
            self.traj = self.next_traj = None
            self.hold = self.pos.copy()
            return None
        start = msgs.ns_of(msg.header.stamp) or self.sim_ns
        # Continue from where the current reference will be when the new one starts.
        base = self.traj.sample(start)[0] if self.traj is not None else self.hold
        try:
            t = control.TrajectorySampler(msg, self.names, start, base, self.joints.lower, self.joints.upper)
        except control.TrajectoryError as e:
            self.reject(key, str(e))
            return str(e)
        self.next_traj = t
        self.max_tracking_error = 0.0
        if self.traj is None:
            # Before its start, hold the current setpoint; afterwards the last point (see _reference).
            self.hold = np.array(base, float)
        return None

    # ------------------------------------------------------------------ FollowJointTrajectory (ROS 2 action)
    def on_fjt_goal(self, goal_id: bytes, goal: cm.FollowJointTrajectoryGoal) -> bool:
        """A goal is accepted; one that cannot be followed is aborted at once with its error code, and
        leaves the motion under way alone."""
        assert self.fjt is not None
        self.fjt_goals += 1
        tr = goal.trajectory
        names = list(tr.joint_names)
        why: tuple[int, str] | None = None
        if len(set(names)) != len(names) or any(n not in self.names for n in names) or not names:
            why = cm.FJT_INVALID_JOINTS, f"joint names {names} are not among the controller's joints {self.names}"
        elif goal.multi_dof_trajectory.points or goal.multi_dof_trajectory.joint_names:
            why = cm.FJT_INVALID_GOAL, "multi-DOF trajectories are not supported"
        elif not tr.points:
            why = cm.FJT_INVALID_GOAL, "the trajectory has no points"
        elif self.hold is None:
            why = cm.FJT_INVALID_GOAL, "no joint_states measured yet"
        else:
            try:
                msgs.validate(tr)  # sizes, times strictly increasing, finite values
            except msgs.BadMessage as e:
                why = cm.FJT_INVALID_GOAL, str(e)
        if why is None:
            stamp = msgs.ns_of(tr.header.stamp)
            if stamp and stamp + msgs.ns_of(tr.points[-1].time_from_start) < self.sim_ns:
                why = cm.FJT_OLD_HEADER_TIMESTAMP, "the trajectory ended before it arrived"
        if why is None:
            strangers = [t.name for t in [*goal.path_tolerance, *goal.goal_tolerance] if t.name not in names]
            if strangers:
                why = cm.FJT_INVALID_JOINTS, f"tolerances for {strangers}, joints the goal does not move"
        if why is None and (reason := self._accept(tr, self.fjt.keys.send_goal)) is not None:
            why = cm.FJT_INVALID_GOAL, reason
        if why is not None:
            self.warn(f"{self.fjt.name}: goal {goal_text(goal_id)} aborted: {why[1]}")
            self.fjt.finish(goal_id, cm.FollowJointTrajectoryResult(error_code=why[0], error_string=why[1]), False)
            return True
        sampler = self.next_traj
        assert sampler is not None
        if self.fjt_goal is not None:
            self._end_goal(False, cm.FJT_INVALID_GOAL, f"preempted by goal {goal_text(goal_id)}")
        cols = [self.names.index(n) for n in names]
        gtt = msgs.ns_of(goal.goal_time_tolerance) or round(self.params.goal_time_tolerance * 1e9)
        self.fjt_goal = _FjtGoal(goal_id, names, cols, sampler, sampler.pos[-1][cols],
                                 *self._tolerances(names, goal), deadline_ns=sampler.end_ns + gtt,
                                 next_feedback_ns=sampler.start_ns)
        return True

    def _tolerances(self, names: list[str], goal: cm.FollowJointTrajectoryGoal) -> tuple[np.ndarray, ...]:
        """(path position, goal position, goal velocity) tolerance per goal joint. In a JointTolerance 0
        means the default (none on the path, ``task.tolerance`` at the goal, none for the velocity) and a
        negative value none."""
        path = np.full(len(names), np.inf)
        pos = np.full(len(names), float(self.sc.task.tolerance))
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

    def on_fjt_cancel(self, goal_id: bytes) -> bool:
        g = self.fjt_goal
        if g is None or g.goal_id != goal_id:
            return False
        self._accept(msgs.JointTrajectory(), "")  # hold where the arm is now
        self._end_goal(False, cm.FJT_SUCCESSFUL, "canceled")
        return True

    def _end_goal(self, success: bool, code: int, text: str) -> None:
        g, self.fjt_goal = self.fjt_goal, None
        if g is not None and self.fjt is not None:
            self.fjt.finish(g.goal_id, cm.FollowJointTrajectoryResult(error_code=code, error_string=text), success)

    def _follow_goal(self, now: int) -> None:
        """Once per control step, after the reference: tolerances, feedback, the end of the goal."""
        g = self.fjt_goal
        assert g is not None and self.fjt is not None
        if g.sampler is not self.traj and g.sampler is not self.next_traj:
            self._end_goal(False, cm.FJT_INVALID_GOAL, "replaced by a trajectory on joint_trajectory")
            return
        if now < g.sampler.start_ns:
            return
        desired, actual = self.ref_pos[g.cols], self.pos[g.cols]
        error = desired - actual
        if now >= g.next_feedback_ns:
            g.next_feedback_ns = now + round(1e9 / self.params.action_feedback_hz)
            elapsed = now - g.sampler.start_ns

            def point(p: np.ndarray, v: np.ndarray) -> msgs.JointTrajectoryPoint:
                return msgs.JointTrajectoryPoint(positions=p.tolist(), velocities=v.tolist(),
                                                 time_from_start=msgs.Duration(sec=elapsed // 1_000_000_000,
                                                                               nanosec=elapsed % 1_000_000_000))

            desired_vel, actual_vel = self.ref_vel[g.cols], self.vel[g.cols]
            self.fjt.feedback(g.goal_id, cm.FollowJointTrajectoryFeedback(
                header=msgs.header(now), joint_names=g.names, desired=point(desired, desired_vel),
                actual=point(actual, actual_vel), error=point(error, desired_vel - actual_vel)))
        if now < g.sampler.end_ns:
            bad = np.nonzero(np.abs(error) > g.path_tol)[0]
            if bad.size:
                j = int(bad[0])
                self._accept(msgs.JointTrajectory(), "")  # hold where the arm is
                self._end_goal(False, cm.FJT_PATH_TOLERANCE_VIOLATED,
                               f"{g.names[j]} is {abs(error[j]):.4f} from its reference (path tolerance "
                               f"{g.path_tol[j]:g})")
            return
        off = np.abs(actual - g.target)
        if np.all(off <= g.goal_tol) and np.all(np.abs(self.vel[g.cols]) <= g.goal_vel_tol):
            self._end_goal(True, cm.FJT_SUCCESSFUL, "")
        elif now > g.deadline_ns:
            j = int(np.argmax(off - g.goal_tol))
            self._accept(msgs.JointTrajectory(), "")
            self._end_goal(False, cm.FJT_GOAL_TOLERANCE_VIOLATED,
                           f"{g.names[j]} is {off[j]:.4f} from the goal (tolerance {g.goal_tol[j]:g}) "
                           f"{(now - g.sampler.end_ns) * 1e-9:.3f} s after the trajectory's end")

    # ------------------------------------------------------------------ live gains
    def on_set_parameters(self, req: msgs.SetParameters) -> msgs.SetParametersResult:
        why = control.set_parameters(self.pids, self.names, req.parameters)
        if why is not None:
            return msgs.SetParametersResult(successful=False, reason=why)
        if req.parameters:
            self.log.info("gains changed: %s", ", ".join(f"{p.name}={p.value:g}" for p in req.parameters))
            self.live_gains.update({p.name: p.value for p in req.parameters})
            self.gains_version += 1  # the fleet driver (robots as arrays) takes them at its next step
            keep(self.sc, self.name, {"gains": self.live_gains})
        return msgs.SetParametersResult(successful=True, reason=f"{len(req.parameters)} parameter(s) set")

    # ------------------------------------------------------------------ reporting
    def health_values(self) -> dict[str, Any]:
        t = self.next_traj or self.traj
        active = t is not None and not t.done(self.sim_ns)
        progress = self.traj.progress(self.sim_ns) if self.traj is not None else 0.0
        return {
            "trajectory_active": "yes" if active else "no",
            "trajectory_progress": f"{progress:.3f}",
            "tracking_error": f"{self.tracking_error:.6f}",
            "max_tracking_error": f"{self.max_tracking_error:.6f}",
            "control_steps": self.steps,
            "fjt_goals": self.fjt_goals,
            "fjt_goal": goal_text(self.fjt_goal.goal_id) if self.fjt_goal is not None else "",
            "joint_states_gaps": self.gaps,
            "interfaces": ",".join(sorted(set(self.interfaces))),
            # the gains in force (scenario + live changes), so a client (the panel) reads what it set
            **{f"gains:{n}": " ".join(f"{f}={getattr(pid, f):g}" for f in control.GAIN_FIELDS
                                      if getattr(pid, f) is not None)
               for n, pid in zip(self.names, self.pids, strict=True)},
        }


class FleetControllerService(Service):
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): every robot's PID in one step.

    Reads ``<prefix>/<robot>/fleet/joint_states`` (every robot's encoders, joints ``arm<k>/<joint>``).
    Writes ``<prefix>/<robot>/fleet/joint_commands`` (every robot's command, same layout and stamp: what
    physics applies and, in lockstep, the acknowledgement of the step for every robot),
    ``<prefix>/<robot>/fleet/controller/reference`` (every robot's reference position and velocity, same
    layout; built only while subscribed: the recorder records it robot by robot) and, from the
    same values, each robot's ``joint_commands`` and ``controller/reference`` through that robot's own
    publishers whenever anyone subscribes them. Each robot's reference, action goal and live gains
    stay with its :class:`ControllerService` (:meth:`ControllerService.prepare`); the PID law is
    :meth:`hilsim.sim.control.Pid.update` written elementwise over (robot, joint) arrays, the same
    operations in the same order, so its efforts equal the per-robot path's bit for bit.
    """

    name = "controller"
    stop_rank = 21  # started before the robots' controllers it drives, stopped after them
    acks_for_robots = True  # in lockstep its fleet sample is every robot's acknowledgement
    ack_via = "joint_commands"
    lockstep_period = ControllerService.lockstep_period

    def __init__(self, scenario: Scenario, members: list[ControllerService]) -> None:
        super().__init__(scenario)
        self.members = members
        m0 = members[0]
        if any(m.sc.control_decimation != m0.sc.control_decimation or m.names != m0.names for m in members):
            raise ConfigError(f"{scenario.source}: fleet.arrays: every robot's controller needs the same rate_hz")
        self.n_robots, self.n = len(members), m0.n
        self.names = [f"{m.sc.robot}/{j}" for m in members for j in m.names]
        self.dt = m0.dt
        self.effort = np.array([m.effort_joint for m in members], bool)
        self.setpoints = any(m.setpoints for m in members)
        self.integral = np.zeros((self.n_robots, self.n))
        self._versions: list[int] = []
        self._gains()

    def setup(self) -> None:
        self.cmd_pub = self.publisher(self.keys.fleet("joint_commands"))
        self.ref_pub = self.publisher(self.keys.fleet("controller/reference"))
        self.subscribe(self.keys.fleet("joint_states"), msgs.JointState, self.on_joint_states)

    def ack_publisher(self) -> Publisher | None:
        return self.cmd_pub

    def _gains(self) -> None:
        """The gains in force, as arrays (robot, joint), from each robot's PIDs (which live gain changes
        set); the integral clamped as :meth:`hilsim.sim.control.Pid.set` clamps it at a change."""
        def of(field: str) -> np.ndarray:
            return np.array([[getattr(p, field) for p in m.pids] for m in self.members], float)

        self.kp, self.ki, self.kd, self.ff = of("kp"), of("ki"), of("kd"), of("feedforward")
        self.lo, self.hi, i_limit = of("lo"), of("hi"), of("i_limit")
        self.integrating = self.ki > 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            self.bound = np.where(self.integrating, i_limit / np.where(self.integrating, self.ki, 1.0), np.inf)
        self.integral = np.where(self.integrating, np.minimum(np.maximum(self.integral, -self.bound), self.bound), 0.0)
        self._versions = [m.gains_version for m in self.members]

    def pid(self, ref_pos: np.ndarray, ref_vel: np.ndarray, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """:meth:`hilsim.sim.control.Pid.update` of every (robot, joint) at once; non-effort joints 0."""
        e = ref_pos - pos
        u_rest = self.kp * e + self.kd * (ref_vel - vel) + self.ff * ref_vel
        old = self.integral
        new = np.minimum(np.maximum(old + e * self.dt, -self.bound), self.bound)
        u_new = u_rest + self.ki * new
        # conditional integration: saturated and the error pushes further -> keep the old integral
        keep = ((u_new > self.hi) & (e > 0.0)) | ((u_new < self.lo) & (e < 0.0))
        u_int = np.where(keep, u_rest + self.ki * old, u_new)
        # a joint without effort interface never runs its PID (the per-robot path skips it): no integral
        self.integral = np.where(self.integrating & self.effort & ~keep, new, old)
        u = np.where(self.integrating, u_int, u_rest)
        return np.where(self.effort, np.minimum(np.maximum(u, self.lo), self.hi), 0.0)

    def on_joint_states(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        self.sim_ns = stamp
        if list(msg.name) != self.names or len(msg.position) != len(self.names):
            self.reject(key, f"fleet JointState of {len(msg.name)} joints is not the fleet's {len(self.names)} "
                             f"({self.names[0]} …) with positions")
            return
        shape = (self.n_robots, self.n)
        pos = np.asarray(msg.position, float).reshape(shape)
        vel = np.asarray(msg.velocity, float).reshape(shape) if msg.velocity else None
        for k, m in enumerate(self.members):
            with m.lock:  # its trajectory, goal and gain handlers run in other threads
                if m.stop_event.is_set():
                    return
                m.measure_row(pos[k], None if vel is None else vel[k], stamp)
                m.prepare(stamp)
        if [m.gains_version for m in self.members] != self._versions:
            self._gains()
        ref_pos = np.array([m.ref_pos for m in self.members])
        ref_vel = np.array([m.ref_vel for m in self.members])
        mvel = np.array([m.vel for m in self.members])
        u = self.pid(ref_pos, ref_vel, np.array([m.pos for m in self.members]), mvel)
        header = msgs.header(stamp)
        effort = u.ravel().tolist()
        if self.setpoints:
            vcmd = np.array([m.velocity_command() for m in self.members])
            cmd = msgs.JointState(header=header, name=self.names, position=ref_pos.ravel().tolist(),
                                  velocity=vcmd.ravel().tolist(), effort=effort)
        else:
            cmd = msgs.JointState(header=header, name=self.names, effort=effort)
        self.cmd_pub.put(cmd)  # physics' step (and, in lockstep, every robot's acknowledgement)
        if self.ref_pub.wanted():  # every robot's reference in one sample: the recorder's, robot by robot
            self.ref_pub.put(msgs.JointState(header=header, name=self.names, position=ref_pos.ravel().tolist(),
                                             velocity=ref_vel.ravel().tolist()))
        else:
            self.ref_pub.skip()
        n = self.n
        for k, m in enumerate(self.members):
            with m.lock:
                # lever 1: a robot's own joint_commands are built only for a subscriber of them
                m.emit(stamp, effort[k * n:(k + 1) * n] if m.cmd_pub.wanted(covered=True) else None)

    def health_values(self) -> dict[str, Any]:
        return {"robots": self.n_robots, "arrays": "yes"}
