"""CAN bridge: the external joint server of the joints mapped to CAN drives (drive in the loop,
``hilsim run bridge-can --config FILE``).

It serves the joints whose scenario entry says ``server: bridge-can`` as the motor model does,
but talks to real drives (or the drive emulator) over any python-can bus: it takes the joints'
commands from ``joint_commands`` (the field of each joint's interface), sends them to the drives
in the drive protocol (``profile``, ODrive CAN Simple by default), reads the drives' encoder
estimates and heartbeats, and publishes the joints' measured state. Physics makes those joints
follow it; controller, planner and logger see the same keys as in pure simulation.

At start, and whenever a drive needs it, the bridge puts the drive in the control mode of its
joint's interface (position -> position control, velocity -> velocity, effort -> torque) and into
closed-loop control, holding its present position. Units: the profile's on the wire (ODrive:
turns, turns/s), rad and rad/s on Zenoh, through each joint's ``gear_ratio``, ``direction`` and
``offset`` (``bridge-can.joints``).

Faults (each published with :meth:`Service.fault` on ``log/bridge-can``, which ``hilsim up``
prints as ``fault: …``, and in health, where the service state is ``fault`` while one lasts):
a drive that misses ``heartbeat_misses`` heartbeats, reports an axis error, leaves closed-loop
control or does not enter it; a bus that fails or goes bus-off. A bus that cannot be opened at
start (within ``open_timeout``, default at once) is no fault but the end: the bridge exits
non-zero with the reason in one line, and ``hilsim up`` ends the run. What the
bridge does then: no new setpoint goes to a faulted drive; with ``on_fault: hold_all`` (the
default) its other drives are held where they are (position control at their measured
position) until every drive is healthy again; with ``hold_faulted`` they go on following their
commands. It keeps trying: it reopens the bus every ``reconnect_interval``, clears axis errors
and asks for closed-loop control every ``recover_interval``, and says when a drive has
recovered (``log/bridge-can``, level info). A recovered position drive rejoins its command at
no more than ``rejoin_velocity``. Frames with unknown ids, wrong lengths or bad content are
counted (health ``frames_unknown_id``, ``frames_bad_length``, ``frames_malformed``), never fatal.

Reads:
  ``<prefix>/<robot>/joint_commands`` (sensor_msgs/JointState; the entries of its joints only)
Writes:
  ``<prefix>/<robot>/hw/bridge-can/joint_states`` (sensor_msgs/JointState: position, velocity of
  the joints whose encoder estimates just arrived), stamped with the sim time at which the newest of
  them came off the bus (the frame's receive time, taken by the kernel where the interface gives it,
  on the simulation's clock as the commands' stamps show it: :class:`hilsim.core.simclock.SimClock`;
  before any command, 0), so a recording tells when the drive reported what. One message per
  batch of frames the bus reader drained together (``batch_window``): on a quiet bus that is one
  per estimate; when estimates arrive faster than they can be published one by one, each joint's
  newest estimate of the batch is published and the older ones are counted as coalesced (health
  ``estimates``, ``estimates_coalesced``, ``state_samples``);
  ``<prefix>/<robot>/hw/bridge-can/setpoints`` (with ``setpoints: true``; sensor_msgs/JointState: the
  setpoints of one command as they went on the bus, position and velocity feed-forward in joint
  units, stamped with the sim time they did), what ``hilsim identify`` tells the drive's own dead
  time from the way to it with;
  ``<prefix>/<robot>/health/bridge-can`` (per joint: status, fault, node, axis state and error,
  heartbeat age; frame counters) and ``<prefix>/<robot>/log/bridge-can``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import can
from pydantic import BaseModel, ConfigDict, Field

from hilsim.bridges.can_bus import BusConfig, CanLink, JointMap, UnusedFrames, finite, raise_priority, resolve_bus
from hilsim.bridges.can_profiles import DriveCommand, Estimate, FrameError, Heartbeat, make_profile
from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.service import Service
from hilsim.core.simclock import SimClock, wall_of

WAITING, STARTING, OK, FAULT = "waiting", "starting", "ok", "fault"


class BridgeConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    profile: str = Field("odrive", description="drive protocol, by name (hilsim.bridges.can_profiles)")
    dbc: Path | None = Field(None, description="the profile's DBC file, if not its own")
    bus: BusConfig = Field(default_factory=BusConfig)
    joints: dict[str, JointMap] = Field(default_factory=dict, description="joint -> node id, gear ratio, …")
    heartbeat_period: float = Field(0.1, gt=0, description="the drives' heartbeat period [s]")
    heartbeat_misses: int = Field(3, ge=1, description="missed heartbeats that make a drive faulted")
    startup_timeout: float = Field(3.0, gt=0, description="[s] a drive may take to send its first heartbeat "
                                   "after the bus comes up, and to enter closed-loop control when asked")
    recover_interval: float = Field(0.5, gt=0, description="[s] between attempts to bring a faulted drive back")
    reconnect_interval: float = Field(1.0, gt=0, description="[s] between attempts to reopen a failed bus")
    open_timeout: float = Field(0.0, ge=0, description="[s] a bus that cannot be opened at start is retried this "
                                "long, then the bridge stops with the reason (and hilsim up with it); 0: at once. "
                                "A bus that was open and fails is reopened however long that takes")
    realtime_priority: int = Field(0, ge=0, le=99, description="SCHED_FIFO priority to ask for (0: none); "
                                   "physics asks for 10")
    rejoin_velocity: float = Field(0.5, gt=0, description="[rad/s] a recovered position joint moves to its command")
    command_rate_hz: float | None = Field(None, gt=0, description="at most this many setpoints per drive and "
                                          "second (default: one per joint_commands message)")
    on_fault: Literal["hold_all", "hold_faulted"] = "hold_all"
    on_stop: Literal["idle", "hold"] = Field("idle", description="what the drives are told when the bridge stops")
    batch_window: float = Field(3e-4, ge=0, le=0.01, description="[s] the most an encoder estimate waits while "
                                "the reader drains the frames that came with it (all published together, the "
                                "newest per joint); 0: one sample per estimate")
    setpoints: bool = Field(False, description="publish hw/bridge-can/setpoints: each command's setpoints as "
                            "they went on the bus, stamped with the sim time they did (hilsim identify)")
    rx_buffer: int = Field(1 << 20, ge=0, description="[bytes] receive buffer asked for on the bus's socket "
                           "(socketcan, udp_multicast): frames wait there while the process is not scheduled "
                           "instead of being dropped; capped by net.core.rmem_max; 0: the system's default")


class BridgedJoint:
    """One joint on the bus, as the bridge knows it."""

    def __init__(self, name: str, jm: JointMap, interface: str) -> None:
        self.name, self.map, self.node, self.interface = name, jm, jm.node_id, interface
        self.status = WAITING
        self.fault = ""  # the reason of the present (or last unrecovered) fault
        self.hb: Heartbeat | None = None
        self.hb_t = 0.0
        self.since = time.monotonic()  # of the present status
        self.setup_t = -1e9
        self.pos = self.vel = 0.0
        self.est_ns = 0  # sim time the newest estimate came off the bus
        self.have_estimate = False
        self.dirty = False  # an estimate not published yet
        self.held = False
        self.rejoin = False
        self.sp = 0.0  # last position setpoint sent [joint rad]
        self.sp_t = 0.0
        self.sent_t = -1e9
        self.setpoints = 0
        self.faults = 0


class CanBridgeService(Service):
    name = "bridge-can"
    stop_rank = 40  # after the loop's services, before the drives' stand-in
    Config = BridgeConfig
    cfg: BridgeConfig

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = scenario.source or "scenario"
        c = self.cfg
        mine = scenario.served_by(self.name)
        missing = [n for n in mine if n not in c.joints]
        if missing:
            raise ConfigError(f"{where}: {self.name}.joints: no drive given for {', '.join(missing)} "
                              f"(e.g. {missing[0]}: {{node_id: 0}})")
        extra = [n for n in c.joints if n not in mine]
        if extra:
            raise ConfigError(f"{where}: {self.name}.joints.{extra[0]}: that joint's server is not {self.name}")
        nodes = [c.joints[n].node_id for n in mine]
        if len(set(nodes)) != len(nodes):
            raise ConfigError(f"{where}: {self.name}.joints: node ids repeat: {nodes}")
        self.profile = make_profile(c.profile, c.dbc)
        c.bus = resolve_bus(c.bus, self.log)  # python-can's IPv4 group where IPv6 multicast is missing
        self.joints: dict[str, BridgedJoint] = {}
        for n in mine:
            iface = scenario.joint(n).interface
            if iface not in self.profile.CONTROL_MODES:
                raise ConfigError(f"{where}: joints.{n}.interface: {iface!r} has no control mode in profile "
                                  f"{c.profile!r}")
            self.joints[n] = BridgedJoint(n, c.joints[n], iface)
        self.by_node = {j.node: j for j in self.joints.values()}
        self.hb_timeout = c.heartbeat_misses * c.heartbeat_period
        self.bus_down = ""
        self.bus_up_t = time.monotonic()
        self._unused = UnusedFrames(("unknown_id", "bad_length", "malformed"), self.rejected, self.warn)
        self.bad = self._unused.counts
        self.frames_host = 0  # host -> drive frames seen (our own, echoed by the bus, or another host's)
        self.frames_other_nodes = 0
        self.commands = 0
        self.estimates = 0  # encoder estimates of our joints taken in
        self.state_samples = 0  # joint_states samples published
        self.coalesced = 0  # estimates a newer one of the same joint replaced before publication
        self.clock = SimClock()  # sim time on this process's wall clock, from the commands' stamps
        self.link = CanLink(c.bus, self._on_frame, self._on_bus, reconnect_interval=c.reconnect_interval,
                            name=self.name, on_batch_end=self._publish_states, batch_window=c.batch_window,
                            rx_buffer=c.rx_buffer)

    # ---------------------------------------------------------------- wiring
    def setup(self) -> None:
        self.pub = self.publisher(self.keys.server_state(self.name))
        self.sp_pub = self.publisher(self.keys.server_setpoints(self.name)) if self.cfg.setpoints else None
        self.subscribe(self.keys.topic("joint_commands"), msgs.JointState, self._on_command)
        self.log.info("serving %s on CAN bus %s (profile %s)", ", ".join(
            f"{j.name} (node {j.node}, {j.interface})" for j in self.joints.values()),
            self.cfg.bus.describe(), self.cfg.profile)
        self.link.start_or_fail(self.cfg.open_timeout)  # a bus that cannot open ends the service (one line)

    def _info(self, text: str) -> None:
        """Good news (a recovery), in the process log and on ``log/bridge-can`` (level 20)."""
        self.log.info(text)
        self._publish_log(20, text)

    # ---------------------------------------------------------------- the bus
    def _on_bus(self, up: bool, reason: str) -> None:
        with self.lock:
            if up:
                was, self.bus_down = self.bus_down, ""
                self.bus_up_t = time.monotonic()
                for j in self.joints.values():  # start over; a drive that had a fault says so when it is back
                    j.hb = None
                    j.status, j.since = WAITING, time.monotonic()
                self._update_holds()  # before saying so: whoever reads the line finds the state it names
                self._info(f"CAN bus {self.cfg.bus.describe()} up" + (f" again (was: {was})" if was else ""))
            else:
                self.bus_down = reason
                for j in self.joints.values():
                    j.status, j.fault, j.since = FAULT, f"CAN bus down: {reason}", time.monotonic()
                    j.faults += 1
                self._update_holds()  # before saying so (above)
                self.fault(f"CAN bus {self.cfg.bus.describe()} down: {reason}; "
                           f"{', '.join(self.joints)} faulted, held by physics at their last measured state; "
                           f"retrying every {self.cfg.reconnect_interval:g} s")

    def _on_frame(self, frame: can.Message) -> None:
        if self.profile.direction(frame) == "to_drive":
            self.frames_host += 1  # a host's frame (ours, echoed by the bus, or another host's)
            return
        try:
            ev = self.profile.parse(frame)
        except FrameError as e:
            with self.lock:
                self._unused(e.kind, str(e))
            return
        if isinstance(ev, DriveCommand):
            self.frames_host += 1
            return
        j = self.by_node.get(ev.node)
        if j is None:
            self.frames_other_nodes += 1
            return
        with self.lock:
            if isinstance(ev, Estimate):
                self._on_estimate(j, ev, wall_of(frame.timestamp))
            else:
                self._on_heartbeat(j, ev)

    def _on_estimate(self, j: BridgedJoint, ev: Estimate, rx: float) -> None:
        m = j.map
        j.pos, j.vel = m.to_joint(ev.position), m.vel_to_joint(ev.velocity)
        j.est_ns = self.clock.sim_ns(rx)
        j.have_estimate = True
        self.estimates += 1
        if j.dirty:
            self.coalesced += 1  # the older estimate of this batch will not be published on its own
        j.dirty = True

    def _publish_states(self) -> None:
        """After each batch the bus reader drained: the newest estimate of every joint that had one."""
        with self.lock:
            fresh = [j for j in self.joints.values() if j.dirty]
            if not fresh:
                return
            for j in fresh:
                j.dirty = False
            msg = msgs.JointState(header=msgs.header(max(j.est_ns for j in fresh)), name=[j.name for j in fresh],
                                  position=[j.pos for j in fresh], velocity=[j.vel for j in fresh])
            if self.stop_event.is_set():
                return
            self.state_samples += 1  # counted with the estimates, so the counters always add up
        self.pub.put(msg)

    def _on_heartbeat(self, j: BridgedJoint, hb: Heartbeat) -> None:
        j.hb, j.hb_t = hb, time.monotonic()
        if hb.error:
            self._fault(j, f"axis error 0x{hb.error:X} (axis state {hb.state})")
        elif hb.state != self.profile.CLOSED_LOOP:
            if j.status == OK:
                self._fault(j, f"left closed-loop control (axis state {hb.state})")
            elif j.status == WAITING:
                j.status, j.since = STARTING, time.monotonic()
                self._setup(j)
        elif j.status != OK:
            self._ok(j)

    # ---------------------------------------------------------------- drive states
    def _setup(self, j: BridgedJoint) -> None:
        """Control mode of the joint's interface, hold where it is, closed-loop control."""
        hold = j.map.to_motor(j.pos) if j.have_estimate else None
        for f in self.profile.setup_frames(j.node, j.interface, hold):
            self.link.send(f)
        j.setup_t = time.monotonic()

    def _fault(self, j: BridgedJoint, reason: str) -> None:
        if j.status == FAULT and j.fault == reason:
            return
        j.status, j.fault, j.since = FAULT, reason, time.monotonic()
        j.faults += 1
        others = [o.name for o in self.joints.values() if o is not j]
        what = "no setpoints are passed to it"
        if others:
            what += "; " + ("its other joints are held" if self.cfg.on_fault == "hold_all"
                            else "its other joints go on")
        self._update_holds()  # before saying so (_on_bus)
        self.fault(f"{j.name} (node {j.node}): {reason}; {what}; trying to recover every "
                   f"{self.cfg.recover_interval:g} s")

    def _ok(self, j: BridgedJoint) -> None:
        was = j.fault
        j.status, j.fault, j.since = OK, "", time.monotonic()
        if j.interface == "position":
            j.rejoin, j.sp, j.sp_t = True, j.pos, time.monotonic()
        self._update_holds()  # before saying so (_on_bus)
        if was:
            self._info(f"{j.name} (node {j.node}) recovered ({was}): closed-loop control again; "
                       + ("rejoining its command" if j.interface == "position" else "following its command"))
        else:
            self.log.info("%s (node %d) in closed-loop control (%s)", j.name, j.node, j.interface)

    def _update_holds(self) -> None:
        """Service state, and (``on_fault: hold_all``) hold or release the healthy drives."""
        faulted = [j.name for j in self.joints.values() if j.status == FAULT]
        self.state = "fault" if faulted or self.bus_down else "running"
        if self.cfg.on_fault != "hold_all":
            return
        for j in self.joints.values():
            if j.status != OK:
                continue
            if faulted and not j.held:
                j.held = True
                self.link.send(self.profile.mode_frame(j.node, "position"))
                self.link.send(self.profile.command_frame(j.node, "position", j.map.to_motor(j.pos), 0.0, 0.0))
                self._info(f"{j.name} (node {j.node}) held at {j.pos:.4f} rad while {', '.join(faulted)} is faulted")
            elif not faulted and j.held:
                j.held = False
                if j.interface != "position":
                    self.link.send(self.profile.mode_frame(j.node, j.interface))
                else:
                    j.rejoin, j.sp, j.sp_t = True, j.pos, time.monotonic()
                self._info(f"{j.name} (node {j.node}) released: following its command again")

    # ---------------------------------------------------------------- commands
    def _on_command(self, cmd: msgs.JointState, key: str) -> None:
        now = time.monotonic()
        self.sim_ns = max(self.sim_ns, msgs.ns_of(cmd.header.stamp))
        self.clock.saw(msgs.ns_of(cmd.header.stamp), now)
        n = len(cmd.name)
        min_dt = 1.0 / self.cfg.command_rate_hz if self.cfg.command_rate_hz else 0.0
        sent: list[tuple[str, float, float]] = []  # (joint, position, velocity) of the setpoints that went out
        for k, name in enumerate(cmd.name):
            j = self.joints.get(name)
            if j is None:
                continue
            q = cmd.position[k] if len(cmd.position) == n else None
            dq = cmd.velocity[k] if len(cmd.velocity) == n else 0.0
            tau = cmd.effort[k] if len(cmd.effort) == n else 0.0
            if (j.interface == "position" and q is None) or (j.interface == "velocity" and len(cmd.velocity) != n) \
                    or (j.interface == "effort" and len(cmd.effort) != n):
                self.reject(key, f"no {j.interface} value for {name}")
                continue
            self.commands += 1
            if j.status != OK or j.held or now - j.sent_t < min_dt:
                continue
            m = j.map
            if j.interface == "position":
                assert q is not None
                if j.rejoin:  # after a recovery: approach the command at rejoin_velocity
                    step = self.cfg.rejoin_velocity * max(0.0, now - j.sp_t)
                    q_new = j.sp + max(-step, min(step, q - j.sp))
                    if q_new == q:
                        j.rejoin = False
                    else:
                        q, dq = q_new, 0.0
                j.sp, j.sp_t = q, now
                frame = self.profile.command_frame(j.node, "position", m.to_motor(q), m.vel_to_motor(dq),
                                                   m.torque_to_motor(tau))
            elif j.interface == "velocity":
                frame = self.profile.command_frame(j.node, "velocity", 0.0, m.vel_to_motor(dq), 0.0)
            else:
                frame = self.profile.command_frame(j.node, "effort", 0.0, 0.0, m.torque_to_motor(tau))
            if self.link.send(frame):
                j.sent_t = now
                j.setpoints += 1
                sent.append((name, q if q is not None else 0.0, dq))
        if sent and self.sp_pub is not None:
            self.sp_pub.put(msgs.JointState(header=msgs.header(self.clock.sim_ns(now)), name=[s[0] for s in sent],
                                            position=[s[1] for s in sent], velocity=[s[2] for s in sent]))

    # ---------------------------------------------------------------- supervision
    def _supervise(self) -> None:
        now = time.monotonic()
        c = self.cfg
        if self.bus_down:
            return
        for j in self.joints.values():
            fresh = j.hb is not None and now - j.hb_t <= self.hb_timeout
            if j.status in (OK, STARTING) and not fresh:
                self._fault(j, f"heartbeat lost (none for more than {self.hb_timeout:g} s, "
                               f"{c.heartbeat_misses} missed)")
            elif j.status == WAITING and now - self.bus_up_t > max(self.hb_timeout, c.startup_timeout):
                self._fault(j, f"no heartbeat from node {j.node} since the bus came up (is the drive powered, "
                               f"on this bus, with this node id and bitrate?)")
            elif j.status == STARTING and now - j.since > c.startup_timeout:
                state = j.hb.state if j.hb is not None else "?"
                self._fault(j, f"does not enter closed-loop control (axis state {state})")
            if j.status in (FAULT, STARTING) and fresh and now - j.setup_t >= c.recover_interval:
                assert j.hb is not None
                if j.hb.error:
                    self.link.send(self.profile.clear_errors_frame(j.node))
                self._setup(j)

    def loop(self) -> None:
        raise_priority(self.cfg.realtime_priority, self.log)
        while not self.stop_event.wait(0.02):
            self.link.check_opened()
            with self.lock:
                self._supervise()

    def teardown(self) -> None:
        with self.lock:
            for j in self.joints.values():
                if j.status != OK:
                    continue
                if self.cfg.on_stop == "idle":
                    self.link.send(self.profile.state_frame(j.node, self.profile.IDLE))
                elif finite(j.pos):
                    self.link.send(self.profile.mode_frame(j.node, "position"))
                    self.link.send(self.profile.command_frame(j.node, "position", j.map.to_motor(j.pos), 0.0, 0.0))
        self.link.stop()

    def health_values(self) -> dict[str, Any]:
        now = time.monotonic()
        out: dict[str, Any] = {
            "bus": self.cfg.bus.describe(), "bus_up": not self.bus_down and self.link.up,
            "bus_outages": self.link.outages, "frames_rx": self.link.rx, "frames_tx": self.link.tx,
            "frames_tx_failed": self.link.tx_failed, "error_frames": self.link.error_frames,
            "frames_host": self.frames_host, "frames_other_nodes": self.frames_other_nodes,
            **{f"frames_{k}": v for k, v in self.bad.items()}, "commands": self.commands,
            "estimates": self.estimates, "estimates_coalesced": self.coalesced, "state_samples": self.state_samples,
            "rx_batches": self.link.batches, "rx_buffer_bytes": self.link.rx_buffer_granted,
        }
        for j in self.joints.values():
            hb = j.hb
            age = f"{now - j.hb_t:.3f}" if hb is not None else "none"
            state = f"state {hb.state}, error 0x{hb.error:X}" if hb is not None else "no heartbeat"
            out[f"joint:{j.name}"] = (f"{j.status}{' (held)' if j.held else ''}, node {j.node}, {j.interface}, "
                                      f"{state}, heartbeat age {age} s, position {j.pos:.5f} rad, "
                                      f"setpoints {j.setpoints}, faults {j.faults}"
                                      + (f", fault: {j.fault}" if j.fault else ""))
        return out
