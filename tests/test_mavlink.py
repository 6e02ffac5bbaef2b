"""MAVLink hardware in the loop, in one process: the conversions (GPS_RAW_INT, GPS2_RAW and
GLOBAL_POSITION_INT -> NavSatFix, exactly, MAVLink 1 and 2; fix types; covariances; the FRD axes
of HIL_SENSOR and the NED velocities of HIL_GPS against the thesis' X-north/Y-east world), the
config errors, and the bridge and the GPS emulator as services in threads (real Zenoh, real UDP
on loopback, the test as the GPS or the autopilot): link loss and recovery, the jump gate, bad
CRCs, stray bytes and unknown ids, a second source, HIL_GPS / GPS_INPUT / HIL_SENSOR decoded by a
pymavlink receiver, heartbeats and the autopilot's presence, a serial device (a pty), a TCP link
that closes and a device that is not there."""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from pymavlink.dialects.v10 import common as mavlink1
from pymavlink.dialects.v20 import common as mavlink
from util import wait_until

from hilsim.bridges import mavlink_gps as mg
from hilsim.bridges.gps_emulator import GpsEmulatorService
from hilsim.bridges.mavlink_bridge import MavlinkBridgeService
from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
OUTDOOR = REPO / "config" / "rover-outdoor.yaml"
HIL = REPO / "config" / "hil" / "mavlink.yaml"
AUTOPILOT = REPO / "config" / "hil" / "mavlink-autopilot.yaml"
KEYS = Keys("hilsim", "rover")
LAT0, LON0 = 411778800, -85977900  # the outdoor world's datum, degE7


def udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def gps_raw(k: int = 0, **kw: Any) -> Any:
    """A GPS_RAW_INT of a known track: 37 degE7 north and 53 east per step, 3D fix, h_acc 0.8 m."""
    f = {"time_usec": 1_700_000_000_000_000 + k * 200_000, "fix_type": 3, "lat": LAT0 + 37 * k,
         "lon": LON0 + 53 * k, "alt": 90_123 + 7 * k, "eph": 120, "epv": 180, "vel": 50, "cog": 4500,
         "satellites_visible": 11, "alt_ellipsoid": 141_456 + 7 * k, "h_acc": 800, "v_acc": 1500}
    f.update(kw)
    return mavlink.MAVLink_gps_raw_int_message(**f)


def packed(msg: Any, src: tuple[int, int], v1: bool = False, seq: int = 0) -> bytes:
    """The frame of ``msg``: MAVLink 2, or as a MAVLink 1 device sends it (the v1.0 dialect: no
    extension fields, which pymavlink's MAVLink 2 encoder would still append to a v1 frame)."""
    if not v1:
        tx = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        tx.seq = seq
        return bytes(msg.pack(tx))
    cls = mavlink1.mavlink_map[msg.get_msgId()]
    tx1 = mavlink1.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    tx1.seq = seq
    return bytes(cls(*(getattr(msg, f) for f in cls.fieldnames)).pack(tx1))


def parsed(msg: Any, v1: bool = False, src: tuple[int, int] = (1, 220)) -> Any:
    """``msg`` as a receiver gets it: packed (MAVLink 1 or 2) and parsed back."""
    rx = mavlink.MAVLink(None)
    out = rx.parse_buffer(packed(msg, src, v1))
    assert out is not None and len(out) == 1, out
    return out[0]


# ------------------------------------------------------------------ conversions
@pytest.mark.parametrize("v1", [False, True], ids=["mavlink2", "mavlink1"])
def test_gps_raw_int_becomes_the_navsatfix_exactly(v1: bool) -> None:
    m = parsed(gps_raw(5), v1=v1)
    f = mg.fix_of(m, stamp_ns=1_234_000_000, frame="gps", altitude="auto", uere=4.0)
    assert f.latitude * 1e7 == pytest.approx(LAT0 + 185, abs=1e-6)
    assert f.longitude * 1e7 == pytest.approx(LON0 + 265, abs=1e-6)
    assert (f.status.status, f.status.service) == (mg.STATUS_FIX, mg.SERVICE_GPS)
    assert f.header.frame_id == "gps" and msgs.ns_of(f.header.stamp) == 1_234_000_000
    if not v1:  # MAVLink 2 carries the extensions: ellipsoid height and the accuracies
        assert f.altitude == pytest.approx(141.491, abs=1e-9)
        assert f.position_covariance_type == mg.COV_DIAGONAL_KNOWN
        assert f.position_covariance == pytest.approx([0.64, 0, 0, 0, 0.64, 0, 0, 0, 2.25])
    else:  # MAVLink 1 does not: altitude above MSL, covariance from the DOPs × uere
        assert f.altitude == pytest.approx(90.158, abs=1e-9)
        assert f.position_covariance_type == mg.COV_APPROXIMATED
        assert f.position_covariance == pytest.approx([4.8**2, 0, 0, 0, 4.8**2, 0, 0, 0, 7.2**2])


def test_gps2_raw_and_global_position_int_and_the_altitude_choice() -> None:
    g2 = parsed(mavlink.MAVLink_gps2_raw_message(0, 6, LAT0, LON0, 50_000, 65535, 65535, 0, 0, 20, 3, 100,
                                                 alt_ellipsoid=101_000, h_acc=14, v_acc=21))
    f = mg.fix_of(g2, stamp_ns=0, frame="gps")
    assert f.status.status == mg.STATUS_GBAS_FIX and f.altitude == 101.0  # RTK fixed; ellipsoid (auto)
    assert f.position_covariance[0] == pytest.approx(0.014**2) and f.position_covariance_type == 2
    assert mg.fix_of(g2, stamp_ns=0, frame="gps", altitude="msl").altitude == 50.0
    gp = parsed(mavlink.MAVLink_global_position_int_message(1000, LAT0 - 1, LON0 + 1, 93_004, 3_004, 10, 0, 0, 0))
    f = mg.fix_of(gp, stamp_ns=0, frame="gps")
    assert f.latitude * 1e7 == pytest.approx(LAT0 - 1, abs=1e-6) and f.altitude == pytest.approx(93.004)
    assert f.status.status == mg.STATUS_FIX and f.position_covariance_type == mg.COV_UNKNOWN
    nowhere = parsed(mavlink.MAVLink_global_position_int_message(1000, 0, 0, 0, 0, 0, 0, 0, 0))
    assert mg.fix_of(nowhere, stamp_ns=0, frame="gps").status.status == mg.STATUS_NO_FIX
    unknown = parsed(gps_raw(eph=65535, epv=65535, h_acc=0, v_acc=0))
    assert mg.fix_of(unknown, stamp_ns=0, frame="gps").position_covariance_type == mg.COV_UNKNOWN


@pytest.mark.parametrize(("fix_type", "status"), [(0, -1), (1, -1), (2, 0), (3, 0), (4, 1), (5, 2), (6, 2),
                                                   (7, 0), (8, 0), (42, -1)])
def test_fix_types_map_to_navsat_status(fix_type: int, status: int) -> None:
    assert mg.navsat_status(fix_type) == status


def _imu(q: tuple[float, float, float, float], acc: tuple[float, ...], gyr: tuple[float, ...]) -> msgs.Imu:
    return msgs.Imu(header=msgs.header(3_000_000_000, "imu"),
                    orientation=msgs.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]),
                    linear_acceleration=msgs.Vector3(x=acc[0], y=acc[1], z=acc[2]),
                    angular_velocity=msgs.Vector3(x=gyr[0], y=gyr[1], z=gyr[2]))


def test_outputs_use_frd_and_ned_consistent_with_the_x_north_y_east_world() -> None:
    """Level and facing +X (north): FRD = NED, at rest zacc = -g, the field is as given. Turned
    90° about +Z (facing +Y, east): forward sees the east component, right the south one; a
    positive MuJoCo yaw rate (north -> east) is a positive FRD yaw rate; 1 m/s forward is 1 m/s east."""
    field = (0.27, -0.01, 0.34)
    s = mg.hil_sensor(_imu((1, 0, 0, 0), (0.1, 0.2, 9.81), (0.01, 0.02, 0.3)), altitude=90.0, field_ned=field,
                      temperature=21.0)
    assert (s.xacc, s.yacc, s.zacc) == pytest.approx((0.1, 0.2, -9.81))
    assert (s.xgyro, s.ygyro, s.zgyro) == pytest.approx((-0.01, -0.02, 0.3))
    assert (s.xmag, s.ymag, s.zmag) == pytest.approx(field)
    assert s.abs_pressure == pytest.approx(1002.5, abs=0.1) and s.pressure_alt == 90.0 and s.time_usec == 3_000_000
    assert s.fields_updated == mg.HIL_SENSOR_FIELDS
    c = math.sqrt(0.5)
    s = mg.hil_sensor(_imu((c, 0, 0, c), (0, 0, 9.81), (0, 0, 0)), altitude=0.0, field_ned=field, temperature=21.0)
    assert (s.xmag, s.ymag, s.zmag) == pytest.approx((-0.01, -0.27, 0.34))
    odom = msgs.Odometry()
    odom.pose.pose.orientation = msgs.Quaternion(w=c, x=0.0, y=0.0, z=c)
    odom.twist.twist.linear.x = 1.0
    vn, ve, vd = mg.ned_velocity(odom)
    assert (vn, ve, vd) == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
    fix = msgs.NavSatFix(header=msgs.header(2_000_000_000, "gps"), latitude=41.1778812345, longitude=-8.5977912345,
                         altitude=91.2346, position_covariance=[1, 0, 0, 0, 1, 0, 0, 0, 4], position_covariance_type=2)
    h = mg.hil_gps(fix, (vn, ve, vd), satellites=9)
    assert (h.lat, h.lon, h.alt, h.eph, h.epv) == (411778812, -85977912, 91235, 100, 200)
    assert (h.vn, h.ve, h.vd, h.vel, h.cog, h.fix_type, h.time_usec) == (0, 100, 0, 100, 9000, 3, 2_000_000)
    g = mg.gps_input(fix, (vn, ve, vd), satellites=9, unix_s=1_700_000_000.0, speed_accuracy=0.1)
    assert (g.horiz_accuracy, g.vert_accuracy, g.alt, g.lat) == (1.0, 2.0, 91.2346, 411778812)
    assert g.ve == pytest.approx(1.0)
    # 2023-11-14 22:13:20 UTC, a Tuesday: GPS time (UTC + 18 s) is 2 days 22:13:38 into week 2288
    assert (g.time_week, g.time_week_ms) == (2288, 252_818_000)


def test_bad_configurations_are_one_line() -> None:
    with pytest.raises(ConfigError, match=r"needs clock.mode: realtime"):
        MavlinkBridgeService(load_scenario(OUTDOOR, {"clock.mode": "lockstep"}, overlays=[HIL]))
    with pytest.raises(ConfigError, match=r"sensors\.gps\.enabled: the simulated GPS still writes gps/fix"):
        MavlinkBridgeService(load_scenario(OUTDOOR, {"sensors.gps.enabled": True}, overlays=[HIL]))
    with pytest.raises(ConfigError, match=r"would send its own fixes back"):
        MavlinkBridgeService(load_scenario(OUTDOOR, {"bridge-mavlink.to_autopilot.gps": "hil_gps"}, overlays=[HIL]))
    with pytest.raises(ConfigError, match=r"nothing to do"):
        MavlinkBridgeService(load_scenario(OUTDOOR, {"bridge-mavlink.gps.enabled": False}, overlays=[HIL]))
    with pytest.raises(ConfigError, match=r"bridge-mavlink\.gps\.jump_gate: Input should be greater than 0"):
        MavlinkBridgeService(load_scenario(OUTDOOR, {"bridge-mavlink.gps.jump_gate": -1}, overlays=[HIL]))
    with pytest.raises(ConfigError, match=r"is not udpin:HOST:PORT"):
        GpsEmulatorService(load_scenario(OUTDOOR, {"bridge-mavlink.connection": "/dev/ttyUSB0"}, overlays=[HIL]))
    indoor = load_scenario("rover", {"clock.mode": "realtime", "bridge-mavlink.to_autopilot.gps": "hil_gps",
                                     "bridge-mavlink.gps.enabled": False})
    with pytest.raises(ConfigError, match=r"no sensor of type gps"):
        MavlinkBridgeService(indoor)


# ------------------------------------------------------------------ the test's MAVLink device
class Peer:
    """A MAVLink device of the test on UDP loopback (a GPS, an autopilot): it sends to ``port`` and
    records what comes back to its own socket, parsed."""

    def __init__(self, port: int, system: int = 1, component: int = 220, listen: bool = False) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port if listen else 0))
        self.sock.settimeout(0.05)
        self.dest = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(self, srcSystem=system, srcComponent=component)
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self.lock = threading.Lock()
        self.got: list[tuple[float, Any]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def write(self, buf: bytes) -> None:
        self.sock.sendto(buf, self.dest)

    def send(self, msg: Any, v1: bool = False) -> None:
        if v1:
            self.write(packed(msg, (self.mav.srcSystem, self.mav.srcComponent), v1=True, seq=self.mav.seq))
            self.mav.seq = (self.mav.seq + 1) % 256
        else:
            self.mav.send(msg)

    def _read(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            for m in self.rx.parse_buffer(data) or []:
                with self.lock:
                    self.got.append((time.monotonic(), m))

    def of_type(self, t: str) -> list[Any]:
        with self.lock:
            return [m for _, m in self.got if m.get_type() == t]

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


class Watch:
    """The test's Zenoh view of the bridge: gps/fix, its log, its latest health."""

    def __init__(self, router: str) -> None:
        self.session = transport.open_session(ZenohConfig(connect=[router]))
        self.lock = threading.Lock()
        self.fixes: list[msgs.NavSatFix] = []
        self.logs: list[tuple[int, str]] = []
        self.health: dict[str, str] = {}
        s = self.session
        self.subs = [s.declare_subscriber(KEYS.topic("gps/fix"), self._fix),
                     s.declare_subscriber(KEYS.log("bridge-mavlink"), self._log),
                     s.declare_subscriber(KEYS.health("bridge-mavlink"), self._health)]

    def _fix(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.fixes.append(msgs.decode(msgs.NavSatFix, sample.payload.to_bytes()))

    def _log(self, sample: zenoh.Sample) -> None:
        m = msgs.decode(msgs.Log, sample.payload.to_bytes())
        with self.lock:
            self.logs.append((m.level, m.msg))

    def _health(self, sample: zenoh.Sample) -> None:
        h = msgs.decode(msgs.DiagnosticArray, sample.payload.to_bytes())
        with self.lock:
            self.health = {kv.key: kv.value for kv in h.status[0].values}

    def said(self, text: str, level: int | None = None) -> int:
        with self.lock:
            return sum(1 for lv, m in self.logs if text in m and (level is None or lv == level))

    def n_fixes(self) -> int:
        with self.lock:
            return len(self.fixes)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


@pytest.fixture
def bridge(router: str, run_service: Callable[[Any], Any]) -> Iterator[Callable[..., tuple[Any, int, Watch]]]:
    """``bridge(overrides, overlay=HIL)``: the bridge running in a thread, listening on a UDP port of
    its own; returns (service, port, watch). Short timeouts, so each case takes a second or two."""
    ctx: list[Any] = []
    watches: list[Watch] = []

    def start(extra: dict[str, Any] | None = None, overlay: Path = HIL) -> tuple[Any, int, Watch]:
        port = udp_port()
        o = {"zenoh.connect": [router], "bridge-mavlink.connection": f"udpin:127.0.0.1:{port}",
             "bridge-mavlink.gps.timeout": 0.4, "bridge-mavlink.gps.startup_timeout": 5.0,
             "bridge-mavlink.heartbeat_period": 0.1, "bridge-mavlink.autopilot.timeout": 1.0}
        o.update(extra or {})
        sc = load_scenario(OUTDOOR, o, overlays=[overlay])
        watch = Watch(router)
        watches.append(watch)
        svc = MavlinkBridgeService(sc)
        c = run_service(svc)
        c.__enter__()
        ctx.append(c)
        # (30 s: a loaded CI machine took over 5 s to open a session and try the link; met at once otherwise)
        assert wait_until(lambda: watch.said("MAVLink link") > 0 or svc.link.up, 30)
        time.sleep(0.3)  # the test's subscribers see the bridge's publishers
        return svc, port, watch

    yield start
    for c in reversed(ctx):
        c.__exit__(None, None, None)
    for w in watches:
        w.close()


# ------------------------------------------------------------------ GPS in the loop
def test_a_silent_gps_is_no_fix_and_a_fault_and_its_return_is_said_once(bridge: Any) -> None:
    svc, port, w = bridge()
    gps = Peer(port)
    try:
        for k in range(5):
            gps.send(gps_raw(k))
            time.sleep(0.05)
        assert wait_until(lambda: w.n_fixes() >= 5, 3)
        t0 = time.monotonic()
        # silent: one fault, NO_FIX at once and every timeout (0.4 s) after
        assert wait_until(lambda: w.n_fixes() >= 7, 3)
        with w.lock:
            lost = [f for f in w.fixes[5:]]
        assert len(lost) <= (time.monotonic() - t0) / 0.4 + 1, len(lost)
        assert all(f.status.status == mg.STATUS_NO_FIX for f in lost), lost
        assert all(f.position_covariance_type == mg.COV_UNKNOWN for f in lost)
        assert lost[0].latitude == pytest.approx((LAT0 + 4 * 37) / 1e7, abs=1e-12)  # where it was last
        assert w.said("no GPS message (GPS_RAW_INT) for", 40) == 1 and svc.state == "fault"
        for k in range(5, 10):  # back
            gps.send(gps_raw(k))
            time.sleep(0.05)
        assert wait_until(lambda: w.said("GPS messages back after") == 1, 3)
        time.sleep(0.2)
        with w.lock:
            back = w.fixes[-5:]
        assert [round(f.latitude * 1e7) for f in back] == [LAT0 + 37 * k for k in range(5, 10)]
        assert all(f.status.status == mg.STATUS_FIX for f in back)
        assert w.said("GPS messages back after") == 1 and w.said("no GPS message", 40) == 1
        assert svc.state == "running" and svc.n["fixes"] == 10
    finally:
        gps.close()


def test_the_first_fix_is_due_from_the_simulations_start_however_late_that_is(bridge: Any) -> None:
    """On a busy machine the other services can take longer to start than gps.startup_timeout: before the
    simulation's first step nothing awaits a fix (the emulated GPS has no truth to send yet), and a GPS
    that then stays silent is still a fault, startup_timeout after that step."""
    svc, _, w = bridge({"bridge-mavlink.gps.startup_timeout": 0.5})
    time.sleep(1.2)  # more than twice the timeout, no clock: the simulation has not started
    assert w.said("no GPS message", 40) == 0 and svc.state != "fault", svc.state
    pub = w.session.declare_publisher(KEYS.clock)
    try:
        t0 = time.monotonic()
        pub.put(msgs.encode(msgs.Clock(clock=msgs.stamp(1_000_000))))
        assert wait_until(lambda: w.said("no GPS message (GPS_RAW_INT) within 0.5 s of the simulation starting",
                                         40) == 1, 5)
        assert time.monotonic() - t0 >= 0.45 and svc.state == "fault"
    finally:
        pub.undeclare()


def test_a_jump_is_flagged_no_fix_and_ends_when_the_track_returns_or_is_confirmed(bridge: Any) -> None:
    """Gate 20 m + 5 m/s: a one-fix outlier 500 m away is flagged and the track then resumes
    (said once); a lasting jump is flagged until 3 fixes agree, then accepted (said once)."""
    svc, port, w = bridge({"bridge-mavlink.gps.timeout": 5.0})
    gps = Peer(port)
    far = 500 * 90  # ≈ 500 m of latitude in degE7 (1e-7 deg ≈ 1.11 cm)
    try:
        for k in range(3):
            gps.send(gps_raw(k))
            time.sleep(0.05)
        gps.send(gps_raw(3, lat=LAT0 + far))  # outlier
        time.sleep(0.05)
        for k in range(4, 6):
            gps.send(gps_raw(k))
            time.sleep(0.05)
        assert wait_until(lambda: w.n_fixes() >= 6, 3)
        assert wait_until(lambda: w.said("back within the gate") == 1, 2)
        with w.lock:
            st = [f.status.status for f in w.fixes[:6]]
            flagged = w.fixes[3]
        assert st == [0, 0, 0, -1, 0, 0]
        assert round(flagged.latitude * 1e7) == LAT0 + far  # flagged, not hidden: its position is kept
        assert w.said("GPS position jump:", 40) == 1 and svc.n["jumps"] == 1
        for k in range(6, 10):  # a lasting jump: flagged, flagged, then accepted
            gps.send(gps_raw(k, lat=LAT0 + far + 37 * k))
            time.sleep(0.05)
        assert wait_until(lambda: w.said("GPS position jump accepted") == 1, 3)
        time.sleep(0.2)
        with w.lock:
            st = [f.status.status for f in w.fixes[6:10]]
        assert st == [-1, -1, 0, 0], st
        assert w.said("GPS position jump:", 40) == 2 and svc.n["jumps_accepted"] == 1 and svc.state == "running"
    finally:
        gps.close()


def test_bad_crc_stray_bytes_unknown_ids_and_a_second_source_are_counted_not_fatal(bridge: Any) -> None:
    svc, port, w = bridge({"bridge-mavlink.gps.timeout": 5.0})
    gps = Peer(port)
    other = Peer(port, system=7, component=220)
    try:
        gps.send(gps_raw(0))
        good = bytearray(gps_raw(1).pack(gps.mav))
        good[-1] ^= 0xFF  # CRC broken
        gps.write(bytes(good))
        gps.write(b"\x01\x02garbage\x03")
        unknown = bytearray(b"\xfd\x04\x00\x00\x07\x01\xdc\x39\x30\x00" + b"\x01\x02\x03\x04" + b"\x00\x00")
        gps.write(bytes(unknown))  # msgid 12345 (0x3039): not in the common dialect
        other.send(gps_raw(2, lat=LAT0 + 999))  # another GPS of the same type: ignored
        gps.send(gps_raw(3), v1=True)  # MAVLink 1 is fine
        gps.send(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))  # known, of no use here
        assert wait_until(lambda: w.n_fixes() >= 2 and svc.link.bad["unknown_id"] >= 1, 3)
        time.sleep(0.3)
        with w.lock:
            lats = [round(f.latitude * 1e7) for f in w.fixes]
        assert lats == [LAT0, LAT0 + 3 * 37]
        bad = svc.link.bad
        assert (bad["bad_crc"], bad["unknown_id"]) == (1, 1) and bad["bad_data"] >= 1, bad
        assert svc.other_sources == 1 and svc.ignored == 1 and svc.state == "running" and svc.errors == 0
        assert w.said("also comes from system 7 component 220") == 1
        assert wait_until(lambda: w.health.get("mavlink_bad_crc") == "1", 3), w.health
        assert w.health["mavlink_unknown_id"] == "1" and w.health["gps_messages_used"] == "2"
        assert "GPS_RAW_INT from system 1 component 220, 3D_FIX, 11 satellites" in w.health["gps"], w.health
    finally:
        gps.close()
        other.close()


def test_gps2_raw_stands_in_while_gps_raw_int_is_silent(bridge: Any) -> None:
    svc, port, w = bridge({"bridge-mavlink.gps.messages": ["GPS_RAW_INT", "GPS2_RAW"]})
    gps = Peer(port)
    try:
        g2 = mavlink.MAVLink_gps2_raw_message(0, 3, LAT0 + 5, LON0, 90_000, 100, 100, 0, 0, 9, 0, 0)
        gps.send(gps_raw(0))
        gps.send(g2)  # GPS_RAW_INT is there: standby
        time.sleep(0.6)  # GPS_RAW_INT silent for more than the timeout
        gps.send(g2)
        assert wait_until(lambda: w.said("GPS position now from GPS2_RAW (was GPS_RAW_INT)") == 1, 3)

        def used() -> list[int]:
            with w.lock:
                return [round(f.latitude * 1e7) for f in w.fixes if f.status.status == 0]

        assert wait_until(lambda: len(used()) >= 2, 10), (used(), w.logs)
        assert used() == [LAT0, LAT0 + 5] and svc.standby == 1
    finally:
        gps.close()


def test_a_gps_on_a_serial_device(bridge: Any) -> None:
    """The connection is a serial device (a pty here) at a baud rate: fixes come through it."""
    master, slave = os.openpty()
    try:
        svc, _, w = bridge({"bridge-mavlink.connection": os.ttyname(slave), "bridge-mavlink.baud": 57600})
        tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=220)
        for k in range(3):
            os.write(master, gps_raw(k).pack(tx))
            time.sleep(0.05)
        assert wait_until(lambda: w.n_fixes() >= 3, 3)
        with w.lock:
            assert [round(f.latitude * 1e7) for f in w.fixes] == [LAT0, LAT0 + 37, LAT0 + 74]
        assert svc.cfg.describe() == f"{os.ttyname(slave)} at 57600 baud"
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.serial  # wall-clock timing: failed two tests at a time
def test_a_tcp_link_that_closes_is_a_fault_and_is_reopened(bridge: Any) -> None:
    """``tcp:`` to a server of the test: fixes come; the server closes the connection (a fault: closed,
    or reset when our heartbeats were still unread), the
    bridge connects again by itself (said), and fixes come again."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(10)
    port = server.getsockname()[1]
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=220)
    try:
        svc, _, w = bridge({"bridge-mavlink.connection": f"tcp:127.0.0.1:{port}",
                            "bridge-mavlink.reconnect_interval": 0.2, "bridge-mavlink.gps.timeout": 5.0})
        conn, _ = server.accept()
        conn.sendall(gps_raw(0).pack(tx) + gps_raw(1).pack(tx))
        assert wait_until(lambda: w.n_fixes() >= 2, 3)
        conn.close()
        assert wait_until(lambda: w.said(f"MAVLink link tcp:127.0.0.1:{port} down: ", 40) == 1, 3)  # closed or reset
        assert svc.state == "fault"
        conn, _ = server.accept()  # the bridge is back
        assert wait_until(lambda: w.said("open") >= 2, 3)
        conn.sendall(gps_raw(2).pack(tx))
        assert wait_until(lambda: w.n_fixes() >= 3, 3)
        conn.close()
        with w.lock:
            assert [round(f.latitude * 1e7) for f in w.fixes] == [LAT0, LAT0 + 37, LAT0 + 74]
        assert svc.link.outages >= 1
    finally:
        server.close()


def test_a_missing_serial_device_is_a_fault_not_a_crash(bridge: Any, tmp_path: Path) -> None:
    svc, _, w = bridge({"bridge-mavlink.connection": str(tmp_path / "ttyNOPE"),
                        "bridge-mavlink.reconnect_interval": 0.2})
    assert wait_until(lambda: w.said("not available", 40) == 1, 3)
    time.sleep(0.5)  # retried, said once
    assert w.said("not available", 40) == 1 and svc.state == "fault" and not svc.link.up


# ------------------------------------------------------------------ the simulation feeds an autopilot
@pytest.mark.parametrize("kind", ["hil_gps", "gps_input"])
def test_the_simulated_gps_and_imu_go_to_the_autopilot(bridge: Any, kind: str) -> None:
    """The test plays the simulation (truth/odom, gps/fix, imu on Zenoh) and the autopilot (UDP,
    HEARTBEATs): what it receives decodes to the simulated values; the bridge's HEARTBEATs come; the
    autopilot is present, lost when it stops, present again (each said once)."""
    svc, port, w = bridge({"bridge-mavlink.to_autopilot.gps": kind}, overlay=AUTOPILOT)
    ap = Peer(port, system=1, component=1)
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           0, 0, mavlink.MAV_STATE_STANDBY, 3)
    pubs = {t: w.session.declare_publisher(KEYS.topic(t)) for t in ("truth/odom", "gps/fix", "imu")}
    beating = threading.Event()
    beating.set()
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(0.1):
            if beating.is_set():
                ap.send(hb)

    th = threading.Thread(target=beat, daemon=True)
    th.start()
    c = math.sqrt(0.5)
    try:
        assert wait_until(lambda: w.said("autopilot present: system 1 component 1 (GROUND_ROVER, autopilot "
                                         "ARDUPILOTMEGA)") == 1, 3)
        sent_fix, sent_imu = [], []
        odom = msgs.Odometry(header=msgs.header(0, "world"))
        odom.pose.pose.position.z = 0.25
        odom.pose.pose.orientation = msgs.Quaternion(w=c, x=0.0, y=0.0, z=c)  # facing +Y: east
        odom.twist.twist.linear.x = 0.8
        pubs["truth/odom"].put(msgs.encode(odom))  # the bridge sends nothing before the first truth
        time.sleep(0.1)
        for k in range(1, 11):  # 100 Hz IMU, 10 Hz GPS in sim time
            t = k * 10_000_000
            odom.header = msgs.header(t, "world")
            pubs["truth/odom"].put(msgs.encode(odom))
            imu = _imu((c, 0, 0, c), (0.3, -0.1, 9.8 + k * 1e-3), (0.01, -0.02, 0.5))
            imu.header = msgs.header(t, "imu")
            pubs["imu"].put(msgs.encode(imu))
            sent_imu.append(imu)
            if k % 10 == 0:
                fix = msgs.NavSatFix(header=msgs.header(t, "gps"), status=msgs.NavSatStatus(status=0, service=1),
                                     latitude=41.17790123456, longitude=-8.5977654321, altitude=90.7531,
                                     position_covariance=[1, 0, 0, 0, 1, 0, 0, 0, 4], position_covariance_type=2)
                pubs["gps/fix"].put(msgs.encode(fix))
                sent_fix.append(fix)
            time.sleep(0.01)
        gps_type = "HIL_GPS" if kind == "hil_gps" else "GPS_INPUT"
        assert wait_until(lambda: len(ap.of_type("HIL_SENSOR")) >= 10 and ap.of_type(gps_type), 3)
        sensors = ap.of_type("HIL_SENSOR")
        for got, imu in zip(sensors, sent_imu, strict=True):
            a, g = imu.linear_acceleration, imu.angular_velocity
            assert got.time_usec == msgs.ns_of(imu.header.stamp) // 1000
            assert (got.xacc, got.yacc, got.zacc) == pytest.approx((a.x, a.y, -a.z), rel=1e-6)
            assert (got.xgyro, got.ygyro, got.zgyro) == pytest.approx((-g.x, -g.y, g.z), rel=1e-6)
            assert (got.xmag, got.ymag, got.zmag) == pytest.approx((-0.01, -0.27, 0.34), rel=1e-5)
            assert got.pressure_alt == pytest.approx(90.25) and got.abs_pressure == pytest.approx(
                mg.isa_pressure_hpa(90.25), rel=1e-6)
        (g,) = ap.of_type(gps_type)
        f = sent_fix[0]
        assert (g.lat, g.lon, g.fix_type, g.satellites_visible) == (411779012, -85977654, 3, 12)
        if kind == "hil_gps":
            assert (g.alt, g.eph, g.epv, g.time_usec) == (90753, 100, 200, 100_000)
            assert (g.vn, g.ve, g.vd, g.vel, g.cog) == (0, 80, 0, 80, 9000)  # 0.8 m/s east, at the antenna
        else:
            assert g.alt == pytest.approx(f.altitude, rel=1e-7) and (g.horiz_accuracy, g.vert_accuracy) == (1.0, 2.0)
            assert g.ve == pytest.approx(0.8, abs=1e-6) and abs(g.vn) < 1e-6 and g.time_usec == 100_000
        beats = [m for m in ap.of_type("HEARTBEAT")]
        assert beats and beats[-1].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        assert beats[-1].get_srcSystem() == 255 and beats[-1].get_srcComponent() == 191
        assert wait_until(lambda: "present: system 1 component 1" in w.health.get("autopilot", ""), 3)
        beating.clear()
        assert wait_until(lambda: w.said("autopilot lost: no HEARTBEAT from system 1 component 1", 40) == 1, 3)
        assert svc.state == "fault"
        beating.set()
        assert wait_until(lambda: w.said("autopilot present again") == 1, 3)
        assert svc.state == "running" and w.said("autopilot lost", 40) == 1
    finally:
        stop.set()
        th.join(2)
        for p in pubs.values():
            p.undeclare()
        ap.close()


# ------------------------------------------------------------------ the GPS emulator
def test_the_emulator_sends_the_true_antenna_position(router: str, run_service: Callable[[Any], Any]) -> None:
    """Truth of a chassis at (12.5, -7.25, 1.5) yawed 0.4 rad, moving: the GPS_RAW_INT received (the
    test listens where the bridge would) is the antenna site there, by the GPS sensor's own
    conversion, to the resolution of degE7 and mm; HEARTBEATs say MAV_TYPE_GPS."""
    port = udp_port()
    sc = load_scenario(OUTDOOR, {"zenoh.connect": [router], "bridge-mavlink.connection": f"udpin:127.0.0.1:{port}",
                                 "gps-emulator.rate_hz": 20.0, "gps-emulator.heartbeat_period": 0.1},
                       overlays=[HIL])
    host = Peer(port, system=255, component=191, listen=True)
    session = transport.open_session(ZenohConfig(connect=[router]))
    pub = session.declare_publisher(KEYS.truth("odom"))
    svc = GpsEmulatorService(sc)
    odom = msgs.Odometry(header=msgs.header(5_000_000_000, "world"))
    odom.pose.pose.position = msgs.Point(x=12.5, y=-7.25, z=1.5)
    odom.pose.pose.orientation = msgs.Quaternion(w=math.cos(0.2), x=0.0, y=0.0, z=math.sin(0.2))
    odom.twist.twist.linear.x = 0.6
    try:
        with run_service(svc):
            assert wait_until(lambda: host.of_type("HEARTBEAT"), 3)
            assert not host.of_type("GPS_RAW_INT")  # no truth yet: no fix
            for _ in range(20):
                pub.put(msgs.encode(odom))
                time.sleep(0.01)
            assert wait_until(lambda: len(host.of_type("GPS_RAW_INT")) >= 3, 3)
        m = host.of_type("GPS_RAW_INT")[-1]
        site, _ = svc.gps.frame.world_pose(odom)
        lat, lon, alt = svc.gps.geodetic(*site)
        assert abs(m.lat - lat * 1e7) <= 0.5 and abs(m.lon - lon * 1e7) <= 0.5
        assert abs(m.alt / 1000 - alt) <= 0.0005 and m.alt_ellipsoid == m.alt
        assert (m.fix_type, m.satellites_visible, m.h_acc, m.v_acc) == (3, 12, 10, 10)
        assert m.vel == 60 and m.cog == round(math.degrees(0.4) * 100)  # 0.6 m/s on a 0.4 rad heading
        hb = host.of_type("HEARTBEAT")[-1]
        assert hb.type == mavlink.MAV_TYPE_GPS and (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 220)
    finally:
        pub.undeclare()
        session.close()
        host.close()
