"""GPS emulator: a MAVLink GPS receiver whose antenna is on the simulated rover
(``hilsim run gps-emulator --config FILE``), the project's stand-in for a real GPS in demos and
tests, its own process like the CAN drive emulator.

On the wall clock, every ``1 / rate_hz`` s (default: the simulated GPS's rate) it sends
GPS_RAW_INT with the rover's **true** position from ``truth/odom``: the antenna site of the
scenario's simulated GPS (``sensor``; its ``frame``) put where the truth says the chassis is, and
converted to latitude, longitude and altitude by that sensor's own code (its datum, UTM, X north
and Y east: :class:`hilsim.sim.sensors_mobile.Gps`), plus Gaussian error if asked
(``horizontal_std``, ``vertical_std``; none by default). The message is what a receiver sends:
fix type ``fix_type`` (3D), ``satellites``, velocity and course from the truth, ``h_acc`` /
``v_acc`` (the reported 1σ: the error's σ, at least 1 cm), DOPs 1.0, ``alt`` and ``alt_ellipsoid``
both the simulated altitude, ``time_usec`` the UNIX time. A HEARTBEAT (MAV_TYPE_GPS) goes out every
``heartbeat_period`` s. Before the first truth it sends no fix (a receiver still searching).

The link defaults to the other end of ``bridge-mavlink``'s: its ``udpin:HOST:PORT`` becomes our
``udpout:HOST:PORT`` (``0.0.0.0`` -> ``127.0.0.1``), so a scenario names the port once. What it
receives (the bridge's heartbeats) is counted; bad input is counted, never fatal.

Reads: ``<prefix>/<robot>/truth/odom`` (nav_msgs/Odometry). Writes: MAVLink on its link;
``health/gps-emulator`` (link, fixes sent, the host's heartbeat) and ``log/gps-emulator``.
"""

from __future__ import annotations

import time
import zlib
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from pymavlink.dialects.v20 import common as mavlink

from hilsim.bridges import mavlink_gps as mg
from hilsim.bridges.link import OncePer
from hilsim.bridges.mavlink_link import LinkConfig, MavLink
from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario, require_realtime
from hilsim.core.service import Service


class GpsEmulatorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    connection: str | None = Field(None, description="pymavlink connection string (default: the other end of "
                                   "bridge-mavlink's udpin)")
    baud: int = Field(115200, gt=0, description="serial devices only")
    system_id: int = Field(1, ge=1, le=255)
    component_id: int = Field(mavlink.MAV_COMP_ID_GPS, ge=0, le=255, description="220: MAV_COMP_ID_GPS")
    mavlink1: bool = Field(False, description="send MAVLink 1 frames")
    heartbeat_period: float = Field(1.0, gt=0, description="[s]")
    reconnect_interval: float = Field(1.0, gt=0, description="[s]")
    sensor: str | None = Field(None, description="the simulated GPS whose antenna and datum it uses (default: "
                               "the scenario's only sensor of type gps)")
    rate_hz: float | None = Field(None, gt=0, description="fixes per second (default: that sensor's rate)")
    horizontal_std: float = Field(0.0, ge=0, description="[m] Gaussian error of north and of east")
    vertical_std: float = Field(0.0, ge=0, description="[m] Gaussian error of the altitude")
    satellites: int = Field(12, ge=0, le=255)
    fix_type: int = Field(mavlink.GPS_FIX_TYPE_3D_FIX, ge=0, le=8, description="MAVLink GPS_FIX_TYPE sent")


def default_connection(sc: Scenario) -> str:
    """The other end of bridge-mavlink's link: its ``udpin:HOST:PORT`` as ``udpout:HOST:PORT``."""
    conn = str(sc.section("bridge-mavlink").get("connection") or "udpin:127.0.0.1:14550")
    if conn.startswith("udpin:"):
        host, _, port = conn[6:].rpartition(":")
        return f"udpout:{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{port}"
    raise ConfigError(f"gps-emulator.connection: not given, and bridge-mavlink's connection {conn!r} is not "
                      "udpin:HOST:PORT, whose other end it would take; give it")


class GpsEmulatorService(Service):
    name = "gps-emulator"
    stop_rank = 45  # after the bridge: the GPS stays on while its host stops
    Config = GpsEmulatorConfig
    cfg: GpsEmulatorConfig

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = f"{scenario.source or 'scenario'}: "
        c = self.cfg
        require_realtime(scenario, "clock.mode", f"{self.name} is a device on the wall clock")
        self.gps = mg.scenario_gps(scenario, c.sensor, where)
        self.rate_hz = c.rate_hz or self.gps.rate_hz
        self.link_cfg = LinkConfig(connection=c.connection or default_connection(scenario), baud=c.baud,
                                   system_id=c.system_id, component_id=c.component_id, mavlink1=c.mavlink1,
                                   heartbeat_period=c.heartbeat_period, reconnect_interval=c.reconnect_interval)
        self.rng = np.random.default_rng([scenario.seed & 0xFFFFFFFF, zlib.crc32(self.name.encode())])
        self.link = MavLink(self.link_cfg, self._on_message, self._on_link, self._on_bad, name=self.name)
        self.odom: msgs.Odometry | None = None
        self.sent = 0
        self.host: tuple[tuple[int, int], float] | None = None
        self.received = 0
        self._said = OncePer(5.0)

    def setup(self) -> None:
        self.subscribe(self.keys.truth("odom"), msgs.Odometry, self._on_odom)
        self.log.info("GPS on MAVLink %s: GPS_RAW_INT at %g Hz from the truth at sensors.%s's antenna (%s)",
                      self.link_cfg.describe(), self.rate_hz, self.gps.name, self.gps.p.frame)
        self.link.start()

    def _on_odom(self, m: msgs.Odometry, key: str) -> None:
        self.sim_ns = max(self.sim_ns, msgs.ns_of(m.header.stamp))
        self.odom = m

    def _on_link(self, up: bool, reason: str) -> None:
        with self.lock:
            if up:
                self.log.info("MAVLink link %s open", self.link_cfg.describe())
                self._publish_log(20, f"MAVLink link {self.link_cfg.describe()} open")
            else:
                self.fault(f"MAVLink link {self.link_cfg.describe()} down: {reason}; retrying every "
                           f"{self.link_cfg.reconnect_interval:g} s")

    def _on_bad(self, kind: str, text: str) -> None:
        with self.lock:
            self.rejected[f"mavlink:{kind}"] += 1
            if self._said.due(kind):
                self.warn(f"MAVLink input not used ({kind}): {text}")

    def _on_message(self, m: Any, t_rx: float) -> None:
        with self.lock:
            self.received += 1
            if m.get_type() == "HEARTBEAT":
                self.host = ((m.get_srcSystem(), m.get_srcComponent()), time.monotonic())

    def fix(self, odom: msgs.Odometry) -> Any:
        """The GPS_RAW_INT of the antenna for a chassis pose and velocity (truth), error added."""
        c = self.cfg
        pos, _ = self.gps.frame.world_pose(odom)
        e = self.rng.normal(0.0, 1.0, 3)  # north, east, up: three draws per fix, always
        lat, lon, alt = self.gps.geodetic(pos[0] + c.horizontal_std * e[0], pos[1] + c.horizontal_std * e[1],
                                          pos[2] + c.vertical_std * e[2])
        return mg.gps_raw_int(lat, lon, alt, unix_us=time.time_ns() // 1000,
                              vel_ned=mg.ned_velocity(odom, self.gps.frame.pos),
                              h_acc=max(c.horizontal_std, 0.01), v_acc=max(c.vertical_std, 0.01),
                              satellites=c.satellites, fix_type=c.fix_type)

    def loop(self) -> None:
        period, hb = 1.0 / self.rate_hz, self.cfg.heartbeat_period
        next_fix = next_hb = time.monotonic()
        while not self.stop_event.is_set():
            now = time.monotonic()
            with self.lock:
                self.state = "running" if self.link.up else "fault"
                if now >= next_fix and self.odom is not None and self.link.send(self.fix(self.odom)):
                    self.sent += 1
                if now >= next_hb:
                    self.link.heartbeat(mavlink.MAV_TYPE_GPS)
            if now >= next_fix:
                next_fix = max(next_fix + period, now)
            if now >= next_hb:
                next_hb = max(next_hb + hb, now)
            self.stop_event.wait(max(0.0, min(next_fix, next_hb) - time.monotonic()))

    def teardown(self) -> None:
        self.link.stop()

    def health_values(self) -> dict[str, Any]:
        ln = self.link
        host = "not heard"
        if self.host is not None:
            (s, c), t = self.host
            host = f"system {s} component {c}, heartbeat age {time.monotonic() - t:.2f} s"
        return {"link": self.link_cfg.describe(), "link_up": ln.up, "fixes_sent": self.sent,
                "truth": "ok" if self.odom is not None else "waiting for truth/odom", "host": host,
                "mavlink_rx": ln.rx, "mavlink_tx": ln.tx, **{f"mavlink_{k}": v for k, v in ln.bad.items()}}
