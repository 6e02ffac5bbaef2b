"""MAVLink bridge: a real GPS (or an autopilot that has one) stands in for the simulated GPS, and
the simulation feeds a real autopilot (``hilsim run bridge-mavlink --config FILE``).

One MAVLink link (:mod:`hilsim.bridges.mavlink_link`: ``udpin:``, ``udpout:``, ``tcp:`` or a
serial device with its baud rate; MAVLink 1 and 2 read alike) and three jobs, each switched on in
the scenario's ``bridge-mavlink:`` section:

**GPS in the loop** (``gps.enabled``). GPS_RAW_INT (or GPS2_RAW, or an autopilot's fused
GLOBAL_POSITION_INT: ``gps.messages``, in order of preference, each used while the ones before it
are silent) becomes sensor_msgs/NavSatFix on ``gps/fix``, the key and type of the simulated GPS,
which the same HIL file switches off (``sensors.<gps>.enabled: false``; the bridge refuses to
start while it is on), so nothing downstream changes. Conversion: :mod:`hilsim.bridges.mavlink_gps`
(degE7 -> degrees, mm -> m, accuracies or DOPs -> covariance with its type, fix type ->
NavSatStatus); the fix is stamped with the latest sim time (``<prefix>/clock``) and framed like
the simulated GPS (its ``frame``). Messages from the first system/component that sends each type
are used (``gps.source_system`` / ``source_component`` pick one); another source of the same
type is counted and ignored.

**Link health.** No GPS message for ``gps.timeout`` s (``gps.startup_timeout`` before the first,
counted from the simulation's first step)
-> a NO_FIX fix is published at once (at the last position, covariance unknown) and every
``gps.timeout`` s while it lasts, and a fault is raised; when messages return it says so once. A fix
farther from the last good one than ``gps.jump_gate`` plus what ``gps.max_speed`` explains in the
time between them is a jump: a fault is raised, and the fix is published flagged as NO_FIX (its
position kept, so a recording shows it), as are the fixes after it, until the track comes back
within the gate (said once) or ``gps.jump_confirm`` consecutive fixes agree on the new position,
which is then accepted (said once). Frames with a bad CRC, bytes that are not MAVLink and message
ids outside the common dialect are counted (health ``mavlink_bad_crc``, ``mavlink_bad_data``,
``mavlink_unknown_id``; a warning at most every 5 s per kind), never fatal.

**The simulation feeds an autopilot** (``to_autopilot``). The simulated GPS (``gps/fix``) as
HIL_GPS (PX4) or GPS_INPUT (ArduPilot, ``GPS1_TYPE = 14``), its velocity from the physics truth
(the simulated GPS models position only), at most ``gps_rate_hz``; the simulated IMU (``imu``) as
HIL_SENSOR at most ``imu_rate_hz``, with a magnetometer (``mag_field`` rotated into the body by the
IMU's orientation) and a barometer (ISA pressure at the true altitude). Axes and units:
:mod:`hilsim.bridges.mavlink_gps`. Time stamps (``time_usec``) are sim time.

**Heartbeats.** The bridge sends HEARTBEAT (an onboard controller) every ``heartbeat_period`` s
and tracks the autopilot's: the first HEARTBEAT from a system whose ``autopilot`` field is not
MAV_AUTOPILOT_INVALID (or from ``autopilot.system`` / ``component``) makes it present (said once);
none for ``autopilot.timeout`` s makes it lost (a fault when the bridge feeds it, else a warning)
and its return is said once. Health shows ``autopilot`` and every other MAVLink peer heard.

Reads: ``<prefix>/clock``; with ``to_autopilot``: ``gps/fix``, ``imu``, ``truth/odom``.
Writes: ``gps/fix`` (sensor_msgs/NavSatFix, with ``gps.enabled``); ``health/bridge-mavlink``
(link, GPS, autopilot, counters) and ``log/bridge-mavlink`` (faults and recoveries).
"""

from __future__ import annotations

import time
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pymavlink.dialects.v20 import common as mavlink

from hilsim.bridges import mavlink_gps as mg
from hilsim.bridges.link import OncePer
from hilsim.bridges.mavlink_link import LinkConfig, MavLink
from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario, require_realtime
from hilsim.core.service import Service
from hilsim.sim.sensing import sensor_class


class GpsInConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    enabled: bool = Field(True, description="publish the MAVLink GPS on gps/fix (GPS in the loop)")
    messages: list[Literal["GPS_RAW_INT", "GPS2_RAW", "GLOBAL_POSITION_INT"]] = Field(
        default_factory=lambda: ["GPS_RAW_INT"], min_length=1,
        description="messages a position is taken from, in order of preference")
    source_system: int | None = Field(None, ge=1, le=255, description="use GPS messages of this system only")
    source_component: int | None = Field(None, ge=0, le=255, description="… and of this component only")
    sensor: str | None = Field(None, description="the simulated GPS it stands in for (default: the scenario's "
                               "only sensor of type gps); its frame names the fixes")
    altitude: Literal["auto", "msl", "ellipsoid"] = Field("auto", description="which altitude goes to "
                                                          "NavSatFix.altitude (auto: ellipsoid when given)")
    uere: float = Field(4.0, gt=0, description="[m] σ per unit of DOP when the GPS gives DOPs but no accuracy")
    timeout: float = Field(1.0, gt=0, description="[s] without a GPS message: NO_FIX and a fault")
    startup_timeout: float = Field(10.0, gt=0, description="[s] the first GPS message may take (from the "
                                   "simulation's first step; from the bridge's start without one)")
    jump_gate: float = Field(20.0, gt=0, description="[m] a fix farther than this (plus max_speed × dt) from the "
                             "last good one is a jump")
    max_speed: float = Field(10.0, ge=0, description="[m/s] the fastest the antenna can move")
    jump_confirm: int = Field(3, ge=1, description="consecutive agreeing fixes that accept a jumped position")

    @field_validator("messages")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("a message is listed twice")
        return v


class AutopilotConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    system: int | None = Field(None, ge=1, le=255, description="the autopilot's system id (default: any "
                               "HEARTBEAT whose autopilot field is not MAV_AUTOPILOT_INVALID)")
    component: int | None = Field(None, ge=0, le=255, description="… and component id")
    timeout: float = Field(3.0, gt=0, description="[s] without its HEARTBEAT: lost")


class ToAutopilotConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    gps: Literal["none", "hil_gps", "gps_input"] = Field("none", description="the simulated GPS as HIL_GPS "
                                                         "(PX4) or GPS_INPUT (ArduPilot)")
    gps_rate_hz: float = Field(10.0, gt=0, description="at most this many GPS messages per second")
    imu: Literal["none", "hil_sensor"] = Field("none", description="the simulated IMU as HIL_SENSOR")
    imu_rate_hz: float = Field(100.0, gt=0, description="at most this many HIL_SENSOR per second")
    satellites: int = Field(12, ge=0, le=255, description="satellites_visible reported")
    speed_accuracy: float = Field(0.1, ge=0, description="GPS_INPUT speed accuracy [m/s]")
    dop: float = Field(1.0, gt=0, description="GPS_INPUT hdop and vdop reported")
    mag_field: tuple[float, float, float] = Field((0.27, -0.01, 0.34), description="the Earth's field "
                                                  "[gauss], north, east, down")
    temperature: float = Field(20.0, description="[°C] in HIL_SENSOR")

    @property
    def enabled(self) -> bool:
        return self.gps != "none" or self.imu != "none"


class MavlinkBridgeConfig(LinkConfig):
    gps: GpsInConfig = Field(default_factory=GpsInConfig)
    autopilot: AutopilotConfig = Field(default_factory=AutopilotConfig)
    to_autopilot: ToAutopilotConfig = Field(default_factory=ToAutopilotConfig)


class MavlinkBridgeService(Service):
    name = "bridge-mavlink"
    stop_rank = 40  # after the loop's services, before the GPS's stand-in
    Config = MavlinkBridgeConfig
    cfg: MavlinkBridgeConfig
    WARN_EVERY = 5.0  # s: the same kind of bad input is said at most this often

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = f"{scenario.source or 'scenario'}: "
        c = self.cfg
        require_realtime(scenario, "clock.mode", f"{self.name} talks to a device on the wall clock")
        if not c.gps.enabled and not c.to_autopilot.enabled:
            raise ConfigError(f"{where}{self.name}: nothing to do: enable gps (GPS in the loop) or to_autopilot "
                              f"(gps: hil_gps|gps_input, imu: hil_sensor)")
        if c.gps.enabled and c.to_autopilot.gps != "none":
            raise ConfigError(f"{where}{self.name}.to_autopilot.gps: with gps.enabled the bridge writes gps/fix "
                              f"itself and would send its own fixes back; use one of them")
        if c.gps.enabled:
            for n, s in scenario.sensors.items():
                if s.enabled and _output_topic(s.type) == "gps/fix":
                    raise ConfigError(f"{where}sensors.{n}.enabled: the simulated GPS still writes gps/fix, which "
                                      f"{self.name} writes in its place; set sensors.{n}.enabled: false")
        self.gps_sensor: Any = None
        if c.to_autopilot.enabled or any(_output_topic(s.type) == "gps/fix" for s in scenario.sensors.values()):
            self.gps_sensor = mg.scenario_gps(scenario, c.gps.sensor, where)
        elif c.gps.sensor is not None:
            raise ConfigError(f"{where}{self.name}.gps.sensor: no sensor {c.gps.sensor!r} of type gps")
        self.frame = self.gps_sensor.p.frame if self.gps_sensor is not None else "gps"
        self.link = MavLink(c, self._on_message, self._on_link, self._on_bad, name=self.name)
        self.t0 = time.monotonic()  # since when the first GPS message is awaited
        self.clock_seen = False
        self._said = OncePer(self.WARN_EVERY)
        self.ignored = 0
        # GPS in
        self.gps_src: dict[str, tuple[int, int]] = {}  # message type -> the source locked onto
        self.gps_seen: dict[str, float] = {}  # message type -> when it last came
        self.gps_active = ""
        self.other_sources = 0
        self.standby = 0  # messages of a less preferred type, while a better one comes
        self.last_gps = -1.0  # monotonic time of the last GPS message used (-1: none yet)
        self.last_msg: Any = None
        self.lost = False
        self.lost_since = 0.0
        self.no_fix_t = -1e9
        self.last_fix: msgs.NavSatFix | None = None
        self.ref: tuple[float, float, float] | None = None  # last good (lat, lon, monotonic t)
        self.jump: dict[str, Any] | None = None  # the jump episode under way
        self.receiver_fix = True  # the receiver's own fix type is a fix
        self.n = {"fixes": 0, "no_fix_lost": 0, "no_fix_receiver": 0, "jumps": 0, "jump_flagged": 0,
                  "jumps_accepted": 0, "messages_used": 0}
        # autopilot
        self.ap: tuple[int, int] | None = None
        self.ap_hb: Any = None
        self.ap_t = 0.0
        self.ap_lost = False
        self.peers: dict[tuple[int, int], tuple[str, float]] = {}
        self.hb_next = 0.0
        # to the autopilot
        self.odom: msgs.Odometry | None = None
        self.out_last: dict[str, int] = {}
        self.sent: dict[str, int] = {"HIL_GPS": 0, "GPS_INPUT": 0, "HIL_SENSOR": 0}

    # ---------------------------------------------------------------- wiring
    def setup(self) -> None:
        c = self.cfg
        self.subscribe(self.keys.clock, msgs.Clock, self._on_clock)
        if c.gps.enabled:
            self.pub_fix = self.publisher(self.keys.topic("gps/fix"))
        o = c.to_autopilot
        if o.enabled:
            self.subscribe(self.keys.truth("odom"), msgs.Odometry, self._on_odom)
        if o.gps != "none":
            self.subscribe(self.keys.topic("gps/fix"), msgs.NavSatFix, self._on_sim_fix)
        if o.imu != "none":
            self.subscribe(self.keys.topic("imu"), msgs.Imu, self._on_sim_imu)
        jobs = []
        if c.gps.enabled:
            jobs.append(f"GPS in the loop ({', '.join(c.gps.messages)} -> gps/fix)")
        if o.enabled:
            jobs.append("feeding an autopilot (" + ", ".join(
                x for x in (o.gps.upper() if o.gps != "none" else "", "HIL_SENSOR" if o.imu != "none" else "") if x)
                + ")")
        self.log.info("MAVLink link %s: %s", c.describe(), "; ".join(jobs))
        self.link.start()

    def _on_clock(self, m: msgs.Clock, key: str) -> None:
        if not self.clock_seen:  # the simulation starts: the first GPS message is due from now
            self.clock_seen, self.t0 = True, time.monotonic()
        self.sim_ns = max(self.sim_ns, msgs.ns_of(m.clock))

    def _info(self, text: str) -> None:
        """Good news (a recovery), in the process log and on ``log/bridge-mavlink`` (level 20)."""
        self.log.info(text)
        self._publish_log(20, text)

    def _say_once_per(self, kind: str, text: str, warn: bool = True) -> None:
        if self._said.due(kind):
            if warn:
                self.warn(text)
            else:
                self.log.info(text)

    # ---------------------------------------------------------------- the link
    def _on_link(self, up: bool, reason: str) -> None:
        with self.lock:
            self._update_state()  # before saying so: whoever reads the line finds the state it names
            if up:
                self._info(f"MAVLink link {self.cfg.describe()} open")
            else:
                self.fault(f"MAVLink link {self.cfg.describe()} down: {reason}; retrying every "
                           f"{self.cfg.reconnect_interval:g} s")

    def _on_bad(self, kind: str, text: str) -> None:
        with self.lock:
            self.rejected[f"mavlink:{kind}"] += 1
            self._say_once_per(kind, f"MAVLink input not used ({kind}, {self.link.bad[kind]} so far): {text}")

    def _on_message(self, m: Any, t_rx: float) -> None:
        with self.lock:
            if self.stop_event.is_set():
                return
            t = m.get_type()
            src = (m.get_srcSystem(), m.get_srcComponent())
            if t == "HEARTBEAT":
                self._on_heartbeat(m, src)
            elif self.cfg.gps.enabled and t in self.cfg.gps.messages:
                self._on_gps(m, t, src)
            else:
                self.ignored += 1

    # ---------------------------------------------------------------- GPS in
    def _on_gps(self, m: Any, t: str, src: tuple[int, int]) -> None:
        g = self.cfg.gps
        if (g.source_system is not None and src[0] != g.source_system) or \
                (g.source_component is not None and src[1] != g.source_component):
            self.other_sources += 1
            return
        locked = self.gps_src.get(t)
        if locked is None:
            locked = self.gps_src[t] = src
            self._info(f"GPS: {t} from system {src[0]} component {src[1]}")
        if locked != src:
            self.other_sources += 1
            self._say_once_per(f"source:{t}:{src}", f"{t} also comes from system {src[0]} component {src[1]} "
                               f"(using system {locked[0]} component {locked[1]}); ignored: set "
                               f"{self.name}.gps.source_system / source_component to choose")
            return
        now = time.monotonic()
        self.gps_seen[t] = now
        active = next(x for x in g.messages if now - self.gps_seen.get(x, -1e9) <= g.timeout)
        if active != t:
            self.standby += 1
            return
        if active != self.gps_active:
            if self.gps_active:
                self._info(f"GPS position now from {active} (was {self.gps_active})")
            self.gps_active = active
        self.n["messages_used"] += 1
        fix = mg.fix_of(m, stamp_ns=self.sim_ns, frame=self.frame, altitude=g.altitude, uere=g.uere)
        if self.lost:
            self.lost = False
            self._update_state()  # before saying so (_on_link)
            self._info(f"GPS messages back after {now - self.lost_since:.1f} s without ({t} from system {src[0]} "
                       f"component {src[1]}): publishing fixes again")
        self.last_gps, self.last_msg = now, m
        has_fix = fix.status.status >= mg.STATUS_FIX
        if has_fix != self.receiver_fix:
            self.receiver_fix = has_fix
            if has_fix:
                self._info(f"the GPS has a fix again ({mg.FIX_NAMES.get(getattr(m, 'fix_type', 3), '?')})")
            else:
                ft = getattr(m, "fix_type", None)
                self.warn(f"the GPS reports no fix ({mg.FIX_NAMES.get(ft, ft) if ft is not None else 'no position'}): "
                          f"published as NO_FIX")
        if has_fix:
            self._gate(fix, now)
        else:
            self.n["no_fix_receiver"] += 1
        self._publish(fix)
        self._update_state()

    def _gate(self, fix: msgs.NavSatFix, now: float) -> None:
        """The jump gate: pass the fix, or flag it as NO_FIX (see the module doc)."""
        g = self.cfg.gps
        here = (fix.latitude, fix.longitude, now)
        if self.ref is None:
            self.ref = here
            return
        d = mg.distance(self.ref[0], self.ref[1], fix.latitude, fix.longitude)
        allowed = g.jump_gate + g.max_speed * (now - self.ref[2])
        if d <= allowed:
            if self.jump is not None:
                flagged, self.jump = self.jump["flagged"], None
                self._update_state()  # before saying so (_on_link)
                self._info(f"GPS position back within the gate ({d:.1f} m from the last good fix) after a jump; "
                           f"{flagged} fixes were flagged NO_FIX")
            self.ref = here
            return
        j = self.jump
        if j is None:
            self.n["jumps"] += 1
            j = self.jump = {"cand": here, "agree": 1, "flagged": 0}
            self._update_state()  # before saying so (_on_link)
            self.fault(f"GPS position jump: {d:.1f} m from the last good fix in {now - self.ref[2]:.2f} s "
                       f"(gate {allowed:.1f} m); published as NO_FIX until the track returns or "
                       f"{g.jump_confirm} consecutive fixes agree on the new position")
        else:
            c = j["cand"]
            near = mg.distance(c[0], c[1], fix.latitude, fix.longitude) <= g.jump_gate + g.max_speed * (now - c[2])
            j["agree"] = j["agree"] + 1 if near else 1
            j["cand"] = here
        if j["agree"] >= g.jump_confirm:
            self.n["jumps_accepted"] += 1
            self.jump = None
            self.ref = here
            self._update_state()  # before saying so (_on_link)
            self._info(f"GPS position jump accepted: {j['agree']} consecutive fixes agree on the new position "
                       f"({d:.1f} m from the old one); {j['flagged']} fixes were flagged NO_FIX")
            return
        j["flagged"] += 1
        self.n["jump_flagged"] += 1
        fix.status.status = mg.STATUS_NO_FIX

    def _publish(self, fix: msgs.NavSatFix) -> None:
        if self.stop_event.is_set():
            return
        self.pub_fix.put(fix)
        if fix.status.status >= mg.STATUS_FIX:
            self.n["fixes"] += 1
            self.last_fix = fix

    def _publish_no_fix(self) -> None:
        last = self.last_fix
        self.n["no_fix_lost"] += 1
        self.no_fix_t = time.monotonic()
        self._publish(msgs.NavSatFix(
            header=msgs.header(self.sim_ns, self.frame),
            status=msgs.NavSatStatus(status=mg.STATUS_NO_FIX, service=mg.SERVICE_GPS),
            latitude=last.latitude if last else 0.0, longitude=last.longitude if last else 0.0,
            altitude=last.altitude if last else 0.0, position_covariance=[0.0] * 9,
            position_covariance_type=mg.COV_UNKNOWN))

    # ---------------------------------------------------------------- heartbeats
    def _on_heartbeat(self, m: Any, src: tuple[int, int]) -> None:
        now = time.monotonic()
        a = self.cfg.autopilot
        # an autopilot says so in its HEARTBEAT; ids given in the config narrow it down (both given: that one)
        is_ap = (a.system is None or src[0] == a.system) and (a.component is None or src[1] == a.component) and \
            (m.autopilot != mavlink.MAV_AUTOPILOT_INVALID or (a.system is not None and a.component is not None))
        if is_ap and (self.ap is None or self.ap == src):
            first = self.ap is None
            self.ap, self.ap_hb, self.ap_t = src, m, now
            if first:
                self._info(f"autopilot present: system {src[0]} component {src[1]} ({_describe_hb(m)})")
            elif self.ap_lost:
                self.ap_lost = False
                self._update_state()  # before saying so (_on_link)
                self._info(f"autopilot present again: system {src[0]} component {src[1]} ({_describe_hb(m)})")
            return
        if src not in self.peers:
            self.log.info("MAVLink peer: system %d component %d (%s)", src[0], src[1], _describe_hb(m))
        self.peers[src] = (_describe_hb(m), now)

    # ---------------------------------------------------------------- to the autopilot
    def _on_odom(self, m: msgs.Odometry, key: str) -> None:
        self.odom = m

    def _due(self, kind: str, stamp: int, rate_hz: float) -> bool:
        last = self.out_last.get(kind)
        if last is not None and stamp - last < 0.95e9 / rate_hz:
            return False
        self.out_last[kind] = stamp
        return True

    def _on_sim_fix(self, fix: msgs.NavSatFix, key: str) -> None:
        o = self.cfg.to_autopilot
        stamp = msgs.ns_of(fix.header.stamp)
        self.sim_ns = max(self.sim_ns, stamp)
        if self.odom is None or not self._due("gps", stamp, o.gps_rate_hz):
            return
        vel = mg.ned_velocity(self.odom, self.gps_sensor.frame.pos)
        if o.gps == "hil_gps":
            msg = mg.hil_gps(fix, vel, satellites=o.satellites)
        else:
            msg = mg.gps_input(fix, vel, satellites=o.satellites, unix_s=time.time(),
                               speed_accuracy=o.speed_accuracy, dop=o.dop)
        if self.link.send(msg):
            self.sent[msg.get_type()] += 1

    def _on_sim_imu(self, imu: msgs.Imu, key: str) -> None:
        o = self.cfg.to_autopilot
        stamp = msgs.ns_of(imu.header.stamp)
        self.sim_ns = max(self.sim_ns, stamp)
        if self.odom is None or not self._due("imu", stamp, o.imu_rate_hz):
            return  # no truth yet: no altitude for the barometer
        if self.link.send(mg.hil_sensor(imu, altitude=self._altitude(), field_ned=o.mag_field,
                                        temperature=o.temperature)):
            self.sent["HIL_SENSOR"] += 1

    def _altitude(self) -> float:
        """True altitude [m] of the chassis: the datum's plus the truth's z (datum 0 without a GPS)."""
        assert self.odom is not None
        return (self.gps_sensor.datum[2] if self.gps_sensor is not None else 0.0) + self.odom.pose.pose.position.z

    # ---------------------------------------------------------------- supervision
    def _supervise(self) -> None:
        now = time.monotonic()
        c = self.cfg
        if now >= self.hb_next:
            self.hb_next = now + c.heartbeat_period
            self.link.heartbeat(mavlink.MAV_TYPE_ONBOARD_CONTROLLER)
        g = c.gps
        # before the simulation starts nothing awaits a fix (and the emulated GPS has no truth to send):
        # the first message is due startup_timeout after it starts, however long the other services took
        if g.enabled and (self.clock_seen or self.last_gps >= 0):
            since = self.last_gps if self.last_gps >= 0 else self.t0
            limit = g.timeout if self.last_gps >= 0 else g.startup_timeout
            if not self.lost and now - since > limit:
                self.lost, self.lost_since = True, since
                self._update_state()  # before saying so (_on_link)
                what = (f"no GPS message ({', '.join(g.messages)}) for {now - since:.1f} s (timeout {limit:g} s)"
                        if self.last_gps >= 0 else f"no GPS message ({', '.join(g.messages)}) within "
                        f"{limit:g} s of the simulation starting (is the GPS sending to {c.describe()}?)")
                self.fault(f"{what}: NO_FIX published on gps/fix every {g.timeout:g} s until it returns")
                self._publish_no_fix()
                self._update_state()
            elif self.lost and now - self.no_fix_t >= g.timeout:
                self._publish_no_fix()
        if self.ap is not None and not self.ap_lost and now - self.ap_t > c.autopilot.timeout:
            self.ap_lost = True
            self._update_state()  # before saying so (_on_link)
            text = (f"autopilot lost: no HEARTBEAT from system {self.ap[0]} component {self.ap[1]} for "
                    f"{now - self.ap_t:.1f} s (timeout {c.autopilot.timeout:g} s)")
            if c.to_autopilot.enabled:
                self.fault(text + "; still sending to it")
            else:
                self.warn(text)
        self._update_state()

    def _update_state(self) -> None:
        bad = not self.link.up or self.lost or self.jump is not None or \
            (self.cfg.to_autopilot.enabled and self.ap_lost)
        self.state = "fault" if bad else "running"

    def loop(self) -> None:
        while not self.stop_event.wait(0.02):
            with self.lock:
                self._supervise()

    def teardown(self) -> None:
        self.link.stop()

    def health_values(self) -> dict[str, Any]:
        now = time.monotonic()
        ln = self.link
        out: dict[str, Any] = {
            "link": self.cfg.describe(), "link_up": ln.up, "link_outages": ln.outages,
            "mavlink_rx": ln.rx, "mavlink_tx": ln.tx, "mavlink_tx_failed": ln.tx_failed,
            **{f"mavlink_{k}": v for k, v in ln.bad.items()}, "messages_ignored": self.ignored,
        }
        if self.cfg.gps.enabled:
            if self.lost:
                gps = f"lost (no GPS message for {now - self.lost_since:.1f} s)"
            elif self.last_msg is None:
                gps = "waiting for the first GPS message"
            else:
                m = self.last_msg
                ft = mg.FIX_NAMES.get(m.fix_type, str(m.fix_type)) if hasattr(m, "fix_type") else "fused"
                sats = f", {m.satellites_visible} satellites" if hasattr(m, "satellites_visible") else ""
                src = self.gps_src.get(self.gps_active, (0, 0))
                gps = (f"{'jump (fixes flagged NO_FIX)' if self.jump else 'ok'}, {self.gps_active} from system "
                       f"{src[0]} component {src[1]}, {ft}{sats}, age {now - self.last_gps:.2f} s")
            out["gps"] = gps
            out.update({f"gps_{k}": v for k, v in self.n.items()})
            out["gps_other_sources"] = self.other_sources
            out["gps_standby"] = self.standby
        if self.ap is None:
            out["autopilot"] = "not seen"
        else:
            out["autopilot"] = (f"{'lost' if self.ap_lost else 'present'}: system {self.ap[0]} component "
                                f"{self.ap[1]}, {_describe_hb(self.ap_hb)}, heartbeat age {now - self.ap_t:.2f} s")
        for (s, c), (what, t) in sorted(self.peers.items()):
            out[f"peer:{s}/{c}"] = f"{what}, heartbeat age {now - t:.2f} s"
        if self.cfg.to_autopilot.enabled:
            out.update({f"sent:{k}": v for k, v in self.sent.items()})
        return out


def _output_topic(type_name: str) -> str:
    try:
        return sensor_class(type_name).output_topic
    except ConfigError:
        return ""


def _describe_hb(m: Any) -> str:
    def name(enum: str, v: int) -> str:
        e = mavlink.enums.get(enum, {}).get(v)
        return e.name.removeprefix(enum + "_") if e is not None else str(v)

    return f"{name('MAV_TYPE', m.type)}, autopilot {name('MAV_AUTOPILOT', m.autopilot)}"
