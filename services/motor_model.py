"""Motor model: a stand-in external joint server, run as its own process like real hardware.

It serves the joints whose scenario entry says ``server: motor-model`` exactly as a CAN or
MAVLink bridge serves its device's joints: it takes their commands from the robot's
``joint_commands`` (the field of each joint's interface), lets a first- or second-order motor
follow them on the wall clock after a transport ``delay``, and publishes what the motor's
encoder would measure. Physics makes those joints follow that state; the controller, planner
and logger see the same keys as in pure simulation.

Reads:
  ``<prefix>/<robot>/joint_commands`` (sensor_msgs/JointState; the entries of its joints only)
Writes:
  ``<prefix>/<robot>/hw/motor-model/joint_states`` (sensor_msgs/JointState: position, velocity,
  effort of its joints) at ``motor-model.rate_hz`` (wall clock), stamped with the sim time at
  which it was taken (the wall clock on the simulation's, as the commands' stamps show it:
  :class:`hilsim.core.simclock.SimClock`; before any command, 0).

Settings (scenario section ``motor-model:``): ``rate_hz``, ``order`` (1: position/velocity
lag with ``time_constant``; 2: ``natural_frequency`` and ``damping_ratio``), ``delay`` [s],
``max_velocity`` [rad/s], ``initial_position`` per joint; effort joints are a rotor of
``inertia`` and ``friction`` (viscous).
"""

from __future__ import annotations

import collections
import math
import time
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.service import Service
from hilsim.core.simclock import SimClock


class MotorModelConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    rate_hz: float = Field(500.0, gt=0, le=5000, description="state publication rate [Hz, wall clock]")
    order: Literal[1, 2] = 1
    time_constant: float = Field(0.01, gt=0, description="first order: lag of position/velocity [s]")
    natural_frequency: float = Field(60.0, gt=0, description="second order: ω_n [rad/s]")
    damping_ratio: float = Field(1.0, gt=0, description="second order: ζ")
    delay: float = Field(0.002, ge=0, le=1.0, description="command transport delay [s]")
    max_velocity: float = Field(math.inf, gt=0, description="[rad/s]")
    inertia: float = Field(0.03, gt=0, description="effort joints: rotor + load inertia [kg·m²]")
    friction: float = Field(0.05, ge=0, description="effort joints: viscous friction [N·m·s/rad]")
    initial_position: dict[str, float] = Field(default_factory=dict)


class Motor:
    """One joint's motor: state and the law that moves it towards its command."""

    def __init__(self, name: str, interface: str, cfg: MotorModelConfig, p0: float) -> None:
        self.name, self.interface, self.cfg = name, interface, cfg
        self.p, self.v, self.effort = p0, 0.0, 0.0
        self.cmd_p, self.cmd_v, self.cmd_u = p0, 0.0, 0.0

    def command(self, p: float | None, v: float | None, u: float | None) -> None:
        if p is not None:
            self.cmd_p = p
        if v is not None:
            self.cmd_v = v
        if u is not None:
            self.cmd_u = u

    def step(self, dt: float) -> None:
        c = self.cfg
        a = 0.0
        if self.interface == "effort":
            a = (self.cmd_u - c.friction * self.v) / c.inertia
            self.effort = self.cmd_u
            self.v += a * dt
        elif c.order == 1:
            if self.interface == "velocity":
                self.v += (self.cmd_v - self.v) * min(1.0, dt / c.time_constant)
            else:
                # position lag with the commanded velocity as feed-forward
                self.v = self.cmd_v + (self.cmd_p - self.p) / c.time_constant
        else:
            wn, z = c.natural_frequency, c.damping_ratio
            if self.interface == "velocity":
                a = 2 * z * wn * (self.cmd_v - self.v)
            else:
                a = wn * wn * (self.cmd_p - self.p) + 2 * z * wn * (self.cmd_v - self.v)
            self.v += a * dt
        if self.interface != "effort":
            self.effort = c.inertia * a
        self.v = max(-c.max_velocity, min(c.max_velocity, self.v))
        self.p += self.v * dt


class MotorModelService(Service):
    name = "motor-model"
    stop_rank = 40  # after the loop's services: the hardware stays up while they stop
    Config = MotorModelConfig
    cfg: MotorModelConfig

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = scenario.source or "scenario"
        mine = {n: scenario.joint(n) for n in scenario.served_by(self.name)}
        for n in self.cfg.initial_position:
            if n not in mine:
                raise ConfigError(f"{where}: {self.name}.initial_position.{n}: not a joint served by {self.name}")
        p0 = self.cfg.initial_position
        self.motors = {n: Motor(n, j.interface, self.cfg, p0.get(n, 0.0)) for n, j in mine.items()}
        self.names = list(self.motors)
        # commands in flight: (wall time due, stamp, {joint: (p, v, u)})
        self._inflight: collections.deque[tuple[float, int, dict[str, tuple[Any, Any, Any]]]] = collections.deque()
        self.stamp_ns = 0
        self.clock = SimClock()  # sim time on the wall clock, from the commands' stamps
        self.commands = 0
        self.last_cmd_wall = 0.0

    def setup(self) -> None:
        self.pub = self.publisher(self.keys.server_state(self.name))
        self.subscribe(self.keys.topic("joint_commands"), msgs.JointState, self.on_command)

    def on_command(self, cmd: msgs.JointState, key: str) -> None:
        n = len(cmd.name)
        entry: dict[str, tuple[Any, Any, Any]] = {}
        for k, jn in enumerate(cmd.name):
            if jn in self.motors:
                entry[jn] = (
                    cmd.position[k] if len(cmd.position) == n else None,
                    cmd.velocity[k] if len(cmd.velocity) == n else None,
                    cmd.effort[k] if len(cmd.effort) == n else None,
                )
        now = time.monotonic()
        self.clock.saw(msgs.ns_of(cmd.header.stamp), now)
        if entry:
            self._inflight.append((now + self.cfg.delay, msgs.ns_of(cmd.header.stamp), entry))
            self.commands += 1
            self.last_cmd_wall = time.monotonic()

    def loop(self) -> None:
        dt = 1.0 / self.cfg.rate_hz
        next_t = last = time.monotonic()
        while not self.stop_event.is_set():
            next_t += dt
            with self.lock:
                now = time.monotonic()
                # the motor moves on the wall clock: a tick this process was late for covers the time that
                # passed (at most 0.1 s), not one period, each command taken when it fell due
                t, last = last, now
                while self._inflight and self._inflight[0][0] <= now:
                    due, stamp, entry = self._inflight.popleft()
                    self._move(t, due)
                    t = max(t, due)
                    self.stamp_ns = max(self.stamp_ns, stamp)
                    for jn, (p, v, u) in entry.items():
                        self.motors[jn].command(p, v, u)
                self._move(t, now)
                self.sim_ns = self.stamp_ns
                ms = list(self.motors.values())
                self.pub.put(msgs.JointState(
                    header=msgs.header(self.clock.sim_ns(now)), name=self.names,
                    position=[m.p for m in ms], velocity=[m.v for m in ms], effort=[m.effort for m in ms],
                ))
            delay = next_t - time.monotonic()
            if delay > 0:
                self.stop_event.wait(delay)
            else:
                self.overruns += 1
                next_t = time.monotonic()  # do not try to catch up a backlog of ticks

    def _move(self, t0: float, t1: float) -> None:
        """Every motor from wall time ``t0`` to ``t1`` (at most 0.1 s), in substeps of at most 0.5 ms."""
        span = min(max(0.0, t1 - t0), 0.1)
        if span <= 0.0:
            return
        n = max(1, math.ceil(span / 0.0005))
        for m in self.motors.values():
            for _ in range(n):
                m.step(span / n)

    def health_values(self) -> dict[str, Any]:
        age = time.monotonic() - self.last_cmd_wall if self.last_cmd_wall else float("inf")
        return {
            "joints": ",".join(self.names),
            "commands": self.commands,
            "last_command_age_s": f"{age:.3f}",
            **{f"position:{m.name}": f"{m.p:.5f}" for m in self.motors.values()},
        }
