"""The joint controllers' fleet driver (``fleet.arrays``): every robot's PID in one step, as arrays.

Run in place of each robot's own subscription when robots are arrays (:mod:`hilsim.core.fleet`; the
controller's ``array_driver``). Reads ``<prefix>/<robot>/fleet/joint_states``; writes
``<prefix>/<robot>/fleet/joint_commands``, ``<prefix>/<robot>/fleet/controller/reference`` and, through
each robot's controller, its ``joint_commands`` and ``controller/reference`` (see the class).
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.service import Publisher, Service
from hilsim.sim import control


class FleetMember(Protocol):
    """What the driver uses of a robot's :class:`hilsim.services.controller.ControllerService`."""

    sc: Scenario
    lock: Any
    stop_event: threading.Event
    names: list[str]
    n: int
    dt: float
    effort_joint: list[bool]
    setpoints: bool
    pids: list[control.Pid]
    gains_version: int
    pos: np.ndarray
    vel: np.ndarray
    ref_pos: np.ndarray
    ref_vel: np.ndarray
    cmd_pub: Publisher

    def measure_row(self, pos: np.ndarray, vel: np.ndarray | None, stamp: int) -> None: ...

    def prepare(self, stamp: int) -> None: ...

    def velocity_command(self) -> np.ndarray: ...

    def emit(self, stamp: int, u: list[float] | None) -> None: ...


class FleetControllerService(Service):
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): every robot's PID in one step.

    Reads ``<prefix>/<robot>/fleet/joint_states`` (every robot's encoders, joints ``arm<k>/<joint>``).
    Writes ``<prefix>/<robot>/fleet/joint_commands`` (every robot's command, same layout and stamp: what
    physics applies and, in lockstep, the acknowledgement of the step for every robot),
    ``<prefix>/<robot>/fleet/controller/reference`` (every robot's reference position and velocity, same
    layout; built only while subscribed: the recorder records it robot by robot) and, from the
    same values, each robot's ``joint_commands`` and ``controller/reference`` through that robot's own
    publishers whenever anyone subscribes them. Each robot's reference, action goal and live gains
    stay with its :class:`hilsim.services.controller.ControllerService` (its ``prepare``); the PID law is
    :meth:`hilsim.sim.control.Pid.update` written elementwise over (robot, joint) arrays, the same
    operations in the same order, so its efforts equal the per-robot path's bit for bit.
    """

    name = "controller"
    stop_rank = 21  # started before the robots' controllers it drives, stopped after them
    acks_for_robots = True  # in lockstep its fleet sample is every robot's acknowledgement
    ack_via = "joint_commands"

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        return sc.control_decimation  # the robots' controllers' (ControllerService.lockstep_period)

    def __init__(self, scenario: Scenario, members: list[FleetMember]) -> None:
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
