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
The service is this module (its setup, the control step up to the PID and the commands out, health) and
its bases, one concern each: :mod:`hilsim.services.controller_trajectories` (which trajectory is taken,
when it acts, ``controller/has_trajectory``), :mod:`hilsim.services.controller_params` (``controller.params``
and live gains); the action server is :mod:`hilsim.services.controller_action`, the control law
:mod:`hilsim.sim.control`; robots as arrays: :mod:`hilsim.services.controller_fleet`.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import numpy as np
from pydantic import ValidationError

from hilsim.core import msgs, registry
from hilsim.core.config import ConfigError, Scenario, format_error
from hilsim.core.restart import kept
from hilsim.core.service import Publisher, Service
from hilsim.services.controller_action import FollowJointTrajectory
from hilsim.services.controller_fleet import FleetControllerService
from hilsim.services.controller_params import ControllerParameters, Params
from hilsim.services.controller_trajectories import (
    HANDOFF_KEPT,
    JOINT_TRAJECTORY,
    PLANNER,
    PLANNER_TRAJECTORY,
    ControllerTrajectories,
)
from hilsim.services.ros2_action import goal_text
from hilsim.sim import control, jtc

__all__ = ["HANDOFF_KEPT", "JOINT_TRAJECTORY", "PLANNER", "PLANNER_TRAJECTORY", "ControllerService",
           "FleetControllerService", "Params"]


class ControllerService(ControllerTrajectories, ControllerParameters):
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

