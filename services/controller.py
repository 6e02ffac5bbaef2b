"""Joint controller service: follows trajectories with one PID per joint.

Reads (``<prefix>/<robot>/…``):
  ``joint_states`` (sensor_msgs/JointState, measured; one control step per message),
  ``joint_trajectory`` (trajectory_msgs/JointTrajectory: a person's, a tool's or a ROS 2 node's),
  ``planner/joint_trajectory`` (the same type: the planner's, written by the planner's identity only).
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
  answered once this controller holds the planner's trajectory of that stamp (accepted, or not with
  the reason it was rejected), or after a third of ``clock.ack_timeout`` without it (not accepted). In
  lockstep the planner acknowledges its tick only then: Zenoh orders nothing between keys, so without
  it a trajectory taken late (a loaded machine) would act steps later than in another run of the seed;
  ``controller/set_parameters`` (SetParameters ``<joint>.<kp|ki|kd|i_limit|output_limit|feedforward>``
  → SetParametersResult): all-or-nothing, effective at the next control step; the gains in
  force are in its health (``gains:<joint>`` = ``kp=… ki=… kd=… i_limit=… …``).

Serves the ROS 2 action ``control_msgs/action/FollowJointTrajectory`` at
``/<robot>/<controller.params.action_ns>`` (default ``follow_joint_trajectory``, what MoveIt's
controller manager calls with ``action_ns: follow_joint_trajectory``; ``""`` serves none), as a node on
rmw_zenoh does: :mod:`hilsim.services.controller_action` (goals, tolerances, results).

Setpoint: the first measured position until a trajectory arrives. Which trajectory is taken and when
it acts are ROS 2's joint_trajectory_controller's rules, in one place (:mod:`hilsim.sim.jtc`): stamp
zero is now, a future stamp starts then, a newer trajectory replaces what was commanded from its own
start, one that ended before it arrived is refused, as is one stamped more than
``controller.params.max_start_ahead`` after sim time (wall-clock stamps: ``use_sim_time``); joint names
in any order, a subset if ``allow_partial_joints_goal``; an empty trajectory holds the measured position.
A refusal is said in the log (a rejected payload of its key), the health (``trajectories_refused``,
``last_refused``) and, for a goal, the action's result. Whose command is followed is a matter of keys,
not stamps: ``planner/joint_trajectory`` only the planner's identity may write (the router's access
control, docs/security.md), so a replay of the planner's trajectory can come only on
``joint_trajectory``, as any other person's command; the health says whose command the arm follows
(``command_from``). The planner's own is taken even if it has ended: it hands a restarted controller
the trajectory under way again, whose end is then held.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError, Scenario, format_error
from hilsim.core.keys import NOT_REACHED
from hilsim.core.restart import keep, kept
from hilsim.core.service import Publisher, Service
from hilsim.services.controller_action import FollowJointTrajectory
from hilsim.services.ros2_action import goal_text
from hilsim.sim import control, jtc

PLANNER, JOINT_TRAJECTORY = "planner", "joint_trajectory"  # who sent a trajectory (health: command_from)
PLANNER_TRAJECTORY = "planner/joint_trajectory"  # the planner's own key (hilsim.core.keys)
HANDOFF_KEPT = 64  # the start stamps of the last trajectories taken, each with why it was rejected (or None)


class Params(BaseModel):
    """``controller.params`` of the joint_trajectory controller."""

    model_config = ConfigDict(extra="forbid")
    action_ns: str = Field("follow_joint_trajectory", description="name of the FollowJointTrajectory action below "
                           "the robot's namespace (absolute if it starts with '/'); empty: no action")
    action_feedback_hz: float = Field(20.0, gt=0, description="feedback rate of the action [1/s of sim time]")
    goal_time_tolerance: float = Field(1.0, gt=0, description="how long after a goal's last point the joints "
                                       "may take to be within tolerance, when the goal gives no time [s]")
    max_start_ahead: float = Field(30.0, gt=0, description="a trajectory stamped to start later than this after "
                                   "sim time is refused (a sender not on sim time: use_sim_time) [s]")
    allow_partial_joints_goal: bool = Field(True, description="take a trajectory that names only some of the "
                                            "joints (the others keep their command), as ROS 2's JTC parameter")


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
        # the command over sim time (None until the first measurement gives the position to hold)
        self.timeline: jtc.Timeline | None = None
        self._early: list[tuple[msgs.JointTrajectory, str, str]] = []  # arrived before any measurement
        self.taken: control.TrajectorySampler | None = None  # the last trajectory take() took
        self.command_from = ""  # who sent the command followed last (health)
        self.refused = 0
        self.last_refused = ""
        # the planner's trajectories taken (start stamp -> why rejected, or None), for has_trajectory's waiters
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
        self.rules = jtc.Rules(round(self.params.max_start_ahead * 1e9), self.params.allow_partial_joints_goal)
        self.fjt: FollowJointTrajectory | None = None
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
        if self.sc.zenoh.auth is not None or self.sc.zenoh.tls is not None:
            # a run with credentials: every writer of a person's command announces itself (a ROS 2 node on
            # rmw_zenoh, hilsim's tools, the DDS bridge), so a sample from one that has not is an impostor's,
            # as on any key with an announced writer (hilsim.core.provenance); without them a test may drive it
            self.provenance.restricted.add(self.keys.topic("joint_trajectory"))
        self.subscribe(self.keys.topic(PLANNER_TRAJECTORY), msgs.JointTrajectory, self.on_planner_trajectory,
                       stream=False)
        self.queryable(
            self.keys.topic("controller/set_parameters"),
            msgs.SetParameters,
            self.on_set_parameters,
            reject=lambda reason: msgs.SetParametersResult(successful=False, reason=reason),
        )
        self.queryable(self.keys.topic("controller/has_trajectory"), msgs.Time, self.on_has_trajectory,
                       reject=lambda reason: msgs.GoalResponse(accepted=False, reason=reason))
        if self.params.action_ns.strip("/"):
            self.fjt = FollowJointTrajectory(self, self)

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
        if self.timeline is None:
            self.timeline = jtc.Timeline(self.pos.copy())  # hold where the arm is until told otherwise
            early, self._early = self._early, []
            for msg, key, source in early:
                self.take(msg, key, source)
        self.timeline.advance(stamp)
        self.ref_pos, self.ref_vel = self.timeline.sample(stamp, self._zero)
        if self.fjt is not None and self.fjt.goal is not None:
            self.fjt.step(stamp)
        err = self.ref_pos - self.pos
        self.tracking_error = float(np.abs(err).max())  # the method: np.max's Python wrapper costs more
        if self.timeline.current is not None or self.timeline.pending:
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

    # ------------------------------------------------------------------ trajectories
    def on_trajectory(self, msg: msgs.JointTrajectory, key: str) -> None:
        """``joint_trajectory``: a person's, a tool's or a ROS 2 node's command (anyone the router lets write it)."""
        self._arrived(msg, key, JOINT_TRAJECTORY)

    def on_planner_trajectory(self, msg: msgs.JointTrajectory, key: str) -> None:
        """``planner/joint_trajectory``: the planner's own, a key only the planner's identity may write."""
        self._arrived(msg, key, PLANNER)

    def _arrived(self, msg: msgs.JointTrajectory, key: str, source: str) -> None:
        if self.timeline is None:
            # the setpoint to start from is not known yet: taken, in order, before the first step
            self._early.append((msg, key, source))
            why = None
        else:
            refused = self.take(msg, key, source)
            why = refused[1] if refused is not None else None
        if source == PLANNER:  # controller/has_trajectory answers the planner about its own
            self._taken[msgs.ns_of(msg.header.stamp)] = why
            while len(self._taken) > HANDOFF_KEPT:
                self._taken.popitem(last=False)
            self._took.notify_all()

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

    def take(self, msg: msgs.JointTrajectory, key: str, source: str) -> tuple[str, str] | None:
        """Follow ``msg`` (from ``source``) under the rules of :mod:`hilsim.sim.jtc`; None, or (what, why)
        it is refused (a rejected payload of ``key``, said in the log and the health). The planner's own
        is taken even if it has ended: only it may write its key, and it hands a restarted controller
        the trajectory under way again (whose end is then held)."""
        assert self.timeline is not None
        self.taken = None
        refused = jtc.refusal(msg, self.sim_ns, self.names, self.rules, ended_ok=source == PLANNER)
        if refused is None and not msg.points:
            # ROS convention: an empty trajectory stops the motion where the arm is now.
            self.stop_here()
            self.command_from = source
            return None
        if refused is None:
            start = msgs.ns_of(msg.header.stamp) or self.sim_ns
            # from where the command will be when the new one starts (joints it does not name keep it)
            base = self.timeline.reference_at(start)
            try:
                t = control.TrajectorySampler(msg, self.names, start, base, self.joints.lower, self.joints.upper)
            except control.TrajectoryError as e:
                refused = jtc.JOINTS if "joint" in str(e) else "invalid", str(e)
            else:
                self.timeline.replace(jtc.Segment(t, source))
                self.taken = t
                self.max_tracking_error = 0.0
                return None
        self.refused += 1
        self.last_refused = f"{source}: {refused[1]}"
        self.reject(key, refused[1])
        return refused

    def stop_here(self) -> None:
        """Hold the measured position: nothing followed or pending."""
        assert self.timeline is not None
        self.timeline.stop(self.pos.copy())

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
        tl = self.timeline
        last = tl.last() if tl is not None else None
        current = tl.current if tl is not None else None
        active = last is not None and not last.sampler.done(self.sim_ns)
        progress = current.sampler.progress(self.sim_ns) if current is not None else 0.0
        return {
            "trajectory_active": "yes" if active else "no",
            "trajectory_progress": f"{progress:.3f}",
            # whose command the arm follows (planner, joint_trajectory, the action's goal; empty: its first
            # position), and whose starts later
            "command_from": current.source if current is not None else "",
            "command_pending": ",".join(s.source for s in tl.pending) if tl is not None else "",
            "trajectories_refused": self.refused,
            "last_refused": self.last_refused,
            "tracking_error": f"{self.tracking_error:.6f}",
            "max_tracking_error": f"{self.max_tracking_error:.6f}",
            "control_steps": self.steps,
            "fjt_goals": self.fjt.goals if self.fjt is not None else 0,
            "fjt_goal": goal_text(self.fjt.goal.goal_id) if self.fjt is not None and self.fjt.goal is not None else "",
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
