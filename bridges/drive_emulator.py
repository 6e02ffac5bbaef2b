"""Drive emulator: drives on a CAN bus that a motor-controller host commands with the drive
protocol's frames (``hilsim run drive-emulator --config FILE``).

Two modes (``drive-emulator.mode``):

- ``model`` (default): the project's stand-in drive, no simulation needed. Each drive is an
  internal second-order position loop (``natural_frequency``, ``damping_ratio``; velocity mode:
  a first-order velocity loop of bandwidth 2ζω_n; torque mode: a rotor of ``inertia`` and viscous
  ``friction``), which acts on a setpoint ``dead_time`` after its frame arrived, accelerates at
  most ``max_acceleration`` and turns at most ``max_velocity``; its encoder estimates are rounded
  to ``encoder_cpr`` counts per turn. This is what the CAN bridge talks to in demos and tests, and
  what ``hilsim identify`` is tested on (parameters the fit does not know).
- ``simulation`` (controller in the loop): the drives are simulated joints. The host's setpoints
  become those joints' commands in the simulation (the emulator publishes ``joint_commands`` for
  them, taking the controller's place), and the encoder estimates come from the simulated joint
  states.

Either way each drive answers like the real one: a heartbeat every ``heartbeat_period`` (axis
error, axis state, procedure result, trajectory done), encoder estimates every ``encoder_period``
and on request (RTR), closed-loop control only after Set_Axis_State(closed loop), setpoints
taken in closed loop only. Entering closed loop the position input is set to the present
position, as the ODrive firmware does. Frames it cannot use are counted (health), never fatal.

Reads (mode ``simulation``):
  ``<prefix>/<robot>/truth/joint_states`` (sensor_msgs/JointState; or ``joint_states``, per
  ``state_topic``): the simulated joints' position and velocity.
Writes (mode ``simulation``):
  ``<prefix>/<robot>/joint_commands`` (sensor_msgs/JointState): the emulated joints only, all
  three fields filled (position, velocity, effort; physics reads the field of each joint's
  interface), one message per setpoint frame and on every axis-state change (idle: hold the
  present position, zero velocity and effort), stamped with the latest sim time.
Both modes: ``health/drive-emulator`` (per drive: axis state, error, control mode, position) and
``log/drive-emulator``.

Settings (scenario section ``drive-emulator:``): ``mode``, ``profile``, ``bus`` and ``drives``
(joint -> node id, gear ratio, direction, offset; both default to the ``bridge-can`` section's,
so a scenario with the bridge and its emulated drive names them once), ``heartbeat_period``,
``encoder_period``, the model's parameters and ``initial_position`` (joint rad), ``state_topic``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import Any, Literal

import can
from pydantic import BaseModel, ConfigDict, Field

from hilsim.bridges.can_bus import BusConfig, CanLink, JointMap, UnusedFrames, raise_priority, resolve_bus
from hilsim.bridges.can_profiles import DriveCommand, DriveProfile, Estimate, FrameError, Heartbeat, make_profile
from hilsim.core import msgs
from hilsim.core.config import SIM, ConfigError, Scenario, require_realtime
from hilsim.core.service import Service
from hilsim.core.simclock import wall_of

# ODrive-like axis errors the emulator can report
ERROR_INVALID_STATE = 0x1
ERROR_CONTROLLER_FAILED = 0x200


class DriveEmulatorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    mode: Literal["model", "simulation"] = "model"
    profile: str | None = Field(None, description="drive protocol (default: bridge-can's, else odrive)")
    bus: BusConfig | None = Field(None, description="python-can bus (default: bridge-can's)")
    drives: dict[str, JointMap] | None = Field(None, description="joint -> drive (default: bridge-can's joints)")
    heartbeat_period: float = Field(0.1, gt=0, description="[s]")
    encoder_period: float = Field(0.01, gt=0, description="cyclic encoder estimates [s]")
    reconnect_interval: float = Field(1.0, gt=0, description="[s] between attempts to reopen a failed bus")
    open_timeout: float = Field(0.0, ge=0, description="[s] a bus that cannot be opened at start is retried this "
                                "long, then the emulator stops with the reason; 0: at once")
    realtime_priority: int = Field(0, ge=0, le=99, description="SCHED_FIFO priority to ask for (0: none); "
                                   "physics asks for 10")
    natural_frequency: float = Field(40.0, gt=0, description="model: position loop ω_n [rad/s]")
    damping_ratio: float = Field(1.0, gt=0, description="model: ζ")
    inertia: float = Field(0.01, gt=0, description="model: rotor + load at the motor [kg·m²]")
    friction: float = Field(0.01, ge=0, description="model: viscous friction at the motor [N·m·s/rad]")
    max_velocity: float = Field(math.inf, gt=0, description="model: [motor rad/s]")
    max_acceleration: float = Field(math.inf, gt=0, description="model: [motor rad/s²] (position and velocity "
                                    "modes: the current limit over the inertia)")
    dead_time: float = Field(0.0, ge=0, le=1.0, description="model: [s] from a setpoint frame's arrival to the "
                             "drive acting on it (the firmware's input filter, its control cycle)")
    encoder_cpr: int = Field(0, ge=0, description="model: encoder counts per motor turn: estimates are rounded to "
                             "them (0: exact)")
    initial_position: dict[str, float] = Field(default_factory=dict, description="model: joint rad")
    state_topic: Literal["truth/joint_states", "joint_states"] = "truth/joint_states"


class DriveModel:
    """Model mode: the motor behind one drive (motor shaft units), on the wall clock."""

    SUBSTEP = 0.0005  # [s] integrate at ≤ 0.5 ms

    def __init__(self, cfg: DriveEmulatorConfig, p0: float) -> None:
        self.cfg = cfg
        self.p, self.v, self.torque = p0, 0.0, 0.0
        self.t = time.monotonic()
        # setpoints that arrived and act after the dead time: (when [monotonic s], (p, v, torque))
        self.pending: deque[tuple[float, tuple[float, float, float]]] = deque()

    def take(self, inp: tuple[float, float, float], now: float) -> None:
        """A setpoint that arrived at ``now``: in force ``dead_time`` later."""
        self.pending.append((now + self.cfg.dead_time, inp))

    def advance(self, now: float, closed_loop: bool, mode: str, inp: tuple[float, float, float]) -> tuple[
            float, float, float]:
        """Move on to ``now`` from the last time, each pending setpoint taken exactly when it falls due;
        returns the input in force at ``now``."""
        if not closed_loop:
            self.pending.clear()
        while self.pending and self.pending[0][0] <= now:
            due, new = self.pending.popleft()
            self._integrate(max(0.0, due - self.t), closed_loop, mode, inp)
            self.t = max(self.t, due)
            inp = new
        self._integrate(max(0.0, now - self.t), closed_loop, mode, inp)
        self.t = now
        return inp

    def _integrate(self, dt: float, closed_loop: bool, mode: str, inp: tuple[float, float, float]) -> None:
        if dt <= 0.0:
            return
        c = self.cfg
        wn, z, j = c.natural_frequency, c.damping_ratio, c.inertia
        p_in, v_in, t_in = inp
        n = max(1, math.ceil(dt / self.SUBSTEP))
        h = dt / n
        for _ in range(n):
            if not closed_loop:
                a = -c.friction * self.v / j  # idle: the motor coasts
            elif mode == "position":
                a = wn * wn * (p_in - self.p) + 2 * z * wn * (v_in - self.v) + t_in / j
            elif mode == "velocity":
                a = 2 * z * wn * (v_in - self.v) + t_in / j
            else:
                a = (t_in - c.friction * self.v) / j
            if closed_loop and mode != "effort":
                a = max(-c.max_acceleration, min(c.max_acceleration, a))
            self.torque = j * a
            self.v = max(-c.max_velocity, min(c.max_velocity, self.v + a * h))
            self.p += self.v * h

    def encoder(self) -> float:
        """The position as the encoder counts it."""
        cpr = self.cfg.encoder_cpr
        if not cpr:
            return self.p
        q = 2 * math.pi / cpr
        return round(self.p / q) * q


class EmulatedDrive:
    """One drive as the host sees it: axis state and error, control mode, inputs, position.

    Faults can be injected (tests, demos): :meth:`fail` reports an axis error (the axis goes
    idle until the host clears it), ``silent`` stops heartbeats and estimates."""

    def __init__(self, joint: str, node: int, profile: DriveProfile, model: DriveModel | None) -> None:
        self.joint, self.node, self.profile, self.model = joint, node, profile, model
        self.state = profile.IDLE
        self.error = 0
        self.mode = "position"
        self.inputs = (0.0, 0.0, 0.0)  # position, velocity, torque (motor units)
        self.p = model.p if model is not None else 0.0
        self.v = 0.0
        self.silent = False
        self.sticky_error = False  # an injected error that Clear_Errors does not clear
        self.commands = 0
        self.refused = 0

    @property
    def closed_loop(self) -> bool:
        return self.state == self.profile.CLOSED_LOOP

    def fail(self, error: int, sticky: bool = False) -> None:
        self.error, self.sticky_error = error, sticky
        self.state = self.profile.IDLE

    def handle(self, cmd: DriveCommand, rx: float | None = None) -> str | None:
        """Apply a host command that arrived at ``rx`` (``time.monotonic()``; default now); returns what
        changed for the outside: ``state``, ``input``, ``mode``, ``estimate`` (an estimate is asked
        for), or None. Raises ValueError for a refused command."""
        p = self.profile
        self.commands += 1
        if cmd.kind == "request_estimate":
            return "estimate"
        if cmd.kind == "clear_errors":
            if not self.sticky_error:
                self.error = 0
            return "state"
        if cmd.kind == "state":
            want = int(cmd.a)
            if want == p.CLOSED_LOOP:
                if self.error:
                    raise ValueError(f"closed loop refused: axis error 0x{self.error:X}")
                if not self.closed_loop:
                    self.state = p.CLOSED_LOOP
                    self.inputs = (self.p, 0.0, 0.0)  # as the firmware: hold where it is
            elif want == p.IDLE:
                self.state = p.IDLE
            else:
                raise ValueError(f"axis state {want} is not emulated (idle {p.IDLE}, closed loop {p.CLOSED_LOOP})")
            return "state"
        if cmd.kind == "mode":
            iface = p.interface_of(int(cmd.a))
            if iface is None:
                raise ValueError(f"control mode {int(cmd.a)} is not emulated")
            self.mode = iface
            return "mode"
        kind = {"position": "position", "velocity": "velocity", "torque": "effort"}[cmd.kind]
        if kind != self.mode:
            raise ValueError(f"a {cmd.kind} setpoint in {self.mode} control mode")
        if not self.closed_loop:
            return None  # ignored, as by the real drive: it is idle
        inputs = (cmd.a if kind == "position" else self.p, cmd.b, cmd.c)
        if self.model is not None and self.model.cfg.dead_time > 0.0:
            # in force a dead time after it arrived (the kernel's receive time: a real drive's own clock is
            # not late when this process is)
            self.model.take(inputs, time.monotonic() if rx is None else rx)
        else:
            self.inputs = inputs
        return "input"

    def advance(self, now: float) -> None:
        if self.model is not None:
            self.inputs = self.model.advance(now, self.closed_loop, self.mode, self.inputs)
            self.p, self.v = self.model.p, self.model.v

    def heartbeat(self) -> can.Message:
        return self.profile.heartbeat_frame(Heartbeat(self.node, self.error, self.state, 0, True))

    def estimate(self) -> can.Message:
        p = self.model.encoder() if self.model is not None else self.p
        return self.profile.estimate_frame(Estimate(self.node, p, self.v))


class DriveEmulatorService(Service):
    name = "drive-emulator"
    stop_rank = 45  # after the bridge: the drive stays on the bus while its host stops
    Config = DriveEmulatorConfig
    cfg: DriveEmulatorConfig

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = scenario.source or "scenario"
        c = self.cfg
        bridge = scenario.section("bridge-can")
        try:
            self.bus_cfg = c.bus or BusConfig.model_validate(bridge.get("bus", {}))
            drives = c.drives if c.drives is not None else {
                k: JointMap.model_validate(v) for k, v in (bridge.get("joints") or {}).items()}
        except ValueError as e:
            raise ConfigError(f"{where}: {self.name}: drives/bus taken from bridge-can are not valid: {e}") from None
        self.bus_cfg = resolve_bus(self.bus_cfg, self.log)  # as the bridge does: both ends on the same group
        if not drives:
            raise ConfigError(f"{where}: {self.name}.drives: no drive to emulate (name joints with a node_id, "
                              f"or give bridge-can.joints)")
        nodes = [d.node_id for d in drives.values()]
        if len(set(nodes)) != len(nodes):
            raise ConfigError(f"{where}: {self.name}.drives: node ids repeat: {nodes}")
        for n in c.initial_position:
            if n not in drives:
                raise ConfigError(f"{where}: {self.name}.initial_position.{n}: not one of the drives")
        self.profile = make_profile(c.profile or bridge.get("profile") or "odrive")
        self.maps = drives
        self.interfaces = {j: scenario.joint(j).interface for j in drives}
        if c.mode == "simulation":
            for j in drives:
                if scenario.joint(j).server != SIM:
                    raise ConfigError(f"{where}: {self.name}.drives.{j}: in mode simulation a drive is a simulated "
                                      f"joint, but joints.{j}.server is {scenario.joint(j).server!r}")
            require_realtime(scenario, self.name, "mode simulation puts a CAN host on the wall clock")
            if "controller" in scenario.services:
                raise ConfigError(f"{where}: services: {self.name} in mode simulation takes the controller's "
                                  f"place (it publishes joint_commands); remove controller from services")
        self.drives: dict[int, EmulatedDrive] = {}
        for j, m in drives.items():
            model = None
            if c.mode == "model":
                model = DriveModel(c, m.to_motor(c.initial_position.get(j, 0.0)))
            d = EmulatedDrive(j, m.node_id, self.profile, model)
            if c.mode == "simulation":
                d.mode = self.interfaces[j]  # the simulated joint's own interface
            self.drives[m.node_id] = d
        self._unused = UnusedFrames(("unknown_id", "bad_length", "malformed", "refused"), self.rejected, self.warn)
        self.bad = self._unused.counts
        self.other_frames = 0
        self.have_state = False
        self.link = CanLink(self.bus_cfg, self._on_frame, self._on_bus, reconnect_interval=c.reconnect_interval,
                            name=self.name)

    # ---------------------------------------------------------------- wiring
    def setup(self) -> None:
        if self.cfg.mode == "simulation":
            self.cmd_pub = self.publisher(self.keys.topic("joint_commands"))
            self.subscribe(self.keys.topic(self.cfg.state_topic), msgs.JointState, self._on_state)
        self.link.start_or_fail(self.cfg.open_timeout)  # a bus that cannot open ends the service (one line)

    def _on_bus(self, up: bool, reason: str) -> None:
        with self.lock:
            if up:
                self.state = "running"
                self.log.info("CAN bus %s up", self.bus_cfg.describe())
                self._publish_log(20, f"CAN bus {self.bus_cfg.describe()} up")
            else:
                self.state = "fault"
                self.fault(f"CAN bus down: {reason}; retrying every {self.cfg.reconnect_interval:g} s")

    def _on_state(self, js: msgs.JointState, key: str) -> None:
        self.sim_ns = max(self.sim_ns, msgs.ns_of(js.header.stamp))
        for k, n in enumerate(js.name):
            m = self.maps.get(n)
            if m is None:
                continue
            d = self.drives[m.node_id]
            d.p = m.to_motor(js.position[k])
            d.v = m.vel_to_motor(js.velocity[k]) if js.velocity else 0.0
        self.have_state = True

    # ---------------------------------------------------------------- frames from the host
    def _on_frame(self, frame: can.Message) -> None:
        if self.profile.direction(frame) == "to_host":
            self.other_frames += 1  # drive -> host traffic (ours echoed, or another drive's)
            return
        try:
            ev = self.profile.parse(frame)
        except FrameError as e:
            with self.lock:
                self._unused(e.kind, str(e))
            return
        if not isinstance(ev, DriveCommand):
            self.other_frames += 1  # drive -> host traffic (ours echoed, or another drive's)
            return
        with self.lock:
            d = self.drives.get(ev.node)
            if d is None:
                self.other_frames += 1  # a drive we do not emulate
                return
            if self.cfg.mode == "model":
                self._advance()
            try:
                if ev.kind == "mode" and self.cfg.mode == "simulation" and \
                        self.profile.interface_of(int(ev.a)) != self.interfaces[d.joint]:
                    raise ValueError(f"control mode {int(ev.a)} does not match the simulated joint's "
                                     f"{self.interfaces[d.joint]} interface")
                what = d.handle(ev, wall_of(frame.timestamp))
            except ValueError as e:
                d.refused += 1
                self._unused("refused", f"{d.joint} (node {d.node}): {e}")
                return
            if what == "estimate":
                if not d.silent:
                    self.link.send(d.estimate())
            elif what in ("state", "input") and self.cfg.mode == "simulation":
                self._command(d)

    def _command(self, d: EmulatedDrive) -> None:
        """Simulation mode: the drive's input as the joint's command in the simulation."""
        m = self.maps[d.joint]
        if d.closed_loop:
            p, v, t = d.inputs
            q, dq, tau = m.to_joint(p), m.vel_to_joint(v), m.torque_to_joint(t)
            if d.mode == "effort":
                q = m.to_joint(d.p)
        else:  # idle: hold where it is (position joints), no velocity, no effort
            q, dq, tau = m.to_joint(d.p), 0.0, 0.0
        self.cmd_pub.put(msgs.JointState(header=msgs.header(self.sim_ns), name=[d.joint], position=[q],
                                         velocity=[dq], effort=[tau]))

    # ---------------------------------------------------------------- cyclic frames
    def _advance(self) -> None:
        now = time.monotonic()
        for d in self.drives.values():
            d.advance(now)

    def loop(self) -> None:
        c = self.cfg
        raise_priority(c.realtime_priority, self.log)
        next_enc = next_hb = time.monotonic()
        while not self.stop_event.is_set():
            self.link.check_opened()
            now = time.monotonic()
            with self.lock:
                if c.mode == "model":
                    self._advance()
                if self.link.up and (c.mode == "model" or self.have_state):
                    if now >= next_enc:
                        for d in self.drives.values():
                            if not d.silent:
                                self.link.send(d.estimate())
                    if now >= next_hb:
                        for d in self.drives.values():
                            if not d.silent:
                                self.link.send(d.heartbeat())
            if now >= next_enc:
                next_enc = max(next_enc + c.encoder_period, now)
            if now >= next_hb:
                next_hb = max(next_hb + c.heartbeat_period, now)
            self.stop_event.wait(max(0.0, min(next_enc, next_hb) - time.monotonic()))

    def teardown(self) -> None:
        self.link.stop()

    def health_values(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "mode": self.cfg.mode, "bus": self.bus_cfg.describe(), "bus_up": self.link.up,
            "frames_rx": self.link.rx, "frames_tx": self.link.tx, "frames_tx_failed": self.link.tx_failed,
            "frames_other": self.other_frames, **{f"frames_{k}": v for k, v in self.bad.items()},
        }
        for d in self.drives.values():
            out[f"drive:{d.joint}"] = (f"node {d.node}, state {d.state}, error 0x{d.error:X}, mode {d.mode}, "
                                       f"position {d.p:.5f} rad (motor)")
        return out
