"""MAVLink <-> ROS conversions of the GPS and the IMU, shared by the MAVLink bridge and the GPS
emulator (pure functions: no I/O).

**In** (a real GPS -> ``gps/fix``): GPS_RAW_INT, GPS2_RAW and GLOBAL_POSITION_INT become a
sensor_msgs/NavSatFix. Latitude and longitude are degE7 integers -> degrees (``lat / 1e7``: the
double nearest the exact value); altitude mm -> m. Which altitude: ``msl`` (``alt``, above mean
sea level), ``ellipsoid`` (``alt_ellipsoid``, above WGS 84, a MAVLink 2 extension), or ``auto``:
``alt_ellipsoid`` when the message carries it (non-zero), else ``alt``. The covariance (ENU, m²,
diagonal): from ``h_acc`` / ``v_acc`` (mm, 1σ) when the receiver gives them
(``COVARIANCE_TYPE_DIAGONAL_KNOWN``), else from the dilutions of precision ``eph`` / ``epv`` (DOP ×
100) times ``uere``, the user equivalent range error (``COVARIANCE_TYPE_APPROXIMATED``), else
unknown (type 0, zeros). GLOBAL_POSITION_INT (an autopilot's fused estimate) has neither: its
covariance is unknown and its status is a fix unless latitude and longitude are both zero.

Fix type (MAVLink GPS_FIX_TYPE) -> NavSatStatus.status: NO_GPS, NO_FIX -> ``STATUS_NO_FIX`` (-1);
2D, 3D, STATIC, PPP -> ``STATUS_FIX`` (0); DGPS -> ``STATUS_SBAS_FIX`` (1); RTK float and fixed ->
``STATUS_GBAS_FIX`` (2, corrections from a ground station). Service: GPS.

**Out** (the simulation -> an autopilot): the simulated fix (``gps/fix``) and the simulated IMU
(``imu``) as HIL_GPS, GPS_INPUT and HIL_SENSOR. Body and world axes: hilsim's world is X north,
Y east, Z up (the thesis' GPS convention, :mod:`hilsim.sim.sensors_mobile`). That map of MuJoCo's
right-handed world onto north, east, up is a mirror image, so a body axis that is "left" in
MuJoCo points to the vehicle's right in the geographic world. MAVLink wants FRD (forward,
right, down) body axes and NED velocities, consistent with the GPS track; so, from the ROS/MuJoCo
body axes (x, y, z): accelerations and magnetic field ``(x, y, -z)``, angular rates
``(-x, -y, z)`` (a pseudovector changes sign under a mirror); world velocities ``(vn, ve, vd) =
(vx, vy, -vz)``. A rover at rest reads ``zacc = -9.81``, and turning from north towards east
(MuJoCo's positive yaw rate) reads a positive ``zgyro``, as an autopilot expects.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario

UINT16_MAX = 65535
EARTH_RADIUS = 6_371_008.8  # m, mean radius: for distances between fixes (gates), not for positions

# NavSatStatus
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
SERVICE_GPS = 1
# NavSatFix.position_covariance_type
COV_UNKNOWN, COV_APPROXIMATED, COV_DIAGONAL_KNOWN = 0, 1, 2

FIX_STATUS = {
    mavlink.GPS_FIX_TYPE_NO_GPS: STATUS_NO_FIX,
    mavlink.GPS_FIX_TYPE_NO_FIX: STATUS_NO_FIX,
    mavlink.GPS_FIX_TYPE_2D_FIX: STATUS_FIX,
    mavlink.GPS_FIX_TYPE_3D_FIX: STATUS_FIX,
    mavlink.GPS_FIX_TYPE_DGPS: STATUS_SBAS_FIX,
    mavlink.GPS_FIX_TYPE_RTK_FLOAT: STATUS_GBAS_FIX,
    mavlink.GPS_FIX_TYPE_RTK_FIXED: STATUS_GBAS_FIX,
    mavlink.GPS_FIX_TYPE_STATIC: STATUS_FIX,
    mavlink.GPS_FIX_TYPE_PPP: STATUS_FIX,
}
FIX_NAMES = {v: k.removeprefix("GPS_FIX_TYPE_") for k, v in vars(mavlink).items() if k.startswith("GPS_FIX_TYPE_")}

# the messages a GPS position is read from
GPS_MESSAGES = ("GPS_RAW_INT", "GPS2_RAW", "GLOBAL_POSITION_INT")

# HIL_SENSOR.fields_updated: accel, gyro, mag (bits 0-8), abs pressure (9), pressure alt (11), temperature (12)
HIL_SENSOR_FIELDS = 0x1FF | 1 << 9 | 1 << 11 | 1 << 12


def navsat_status(fix_type: int) -> int:
    """NavSatStatus.status of a MAVLink GPS_FIX_TYPE (an unknown value is no fix)."""
    return FIX_STATUS.get(int(fix_type), STATUS_NO_FIX)


def covariance_of(msg: Any, uere: float) -> tuple[list[float], int]:
    """Diagonal ENU position covariance [m²] and its NavSatFix covariance type (see the module doc)."""
    if msg.get_type() == "GLOBAL_POSITION_INT":
        return [0.0] * 9, COV_UNKNOWN
    h_acc, v_acc = getattr(msg, "h_acc", 0), getattr(msg, "v_acc", 0)
    sh = sv = None
    known = True
    if h_acc:
        sh = h_acc / 1000.0
    elif msg.eph != UINT16_MAX:
        sh, known = msg.eph / 100.0 * uere, False
    if v_acc:
        sv = v_acc / 1000.0
    elif msg.epv != UINT16_MAX:
        sv, known = msg.epv / 100.0 * uere, False
    if sh is None or sv is None:
        return [0.0] * 9, COV_UNKNOWN
    h, v = sh * sh, sv * sv
    return [h, 0.0, 0.0, 0.0, h, 0.0, 0.0, 0.0, v], COV_DIAGONAL_KNOWN if known else COV_APPROXIMATED


def altitude_of(msg: Any, mode: str) -> float:
    """Altitude [m] of a GPS message: ``msl``, ``ellipsoid`` or ``auto`` (see the module doc)."""
    ell = getattr(msg, "alt_ellipsoid", 0)
    if mode == "ellipsoid" or (mode == "auto" and ell):
        return ell / 1000.0
    return msg.alt / 1000.0


def fix_of(msg: Any, *, stamp_ns: int, frame: str, altitude: str = "auto", uere: float = 4.0) -> msgs.NavSatFix:
    """The NavSatFix of a GPS_RAW_INT, GPS2_RAW or GLOBAL_POSITION_INT message."""
    if msg.get_type() == "GLOBAL_POSITION_INT":
        status = STATUS_NO_FIX if msg.lat == 0 and msg.lon == 0 else STATUS_FIX
        alt = msg.alt / 1000.0
    else:
        status = navsat_status(msg.fix_type)
        alt = altitude_of(msg, altitude)
    cov, cov_type = covariance_of(msg, uere)
    return msgs.NavSatFix(
        header=msgs.header(stamp_ns, frame),
        status=msgs.NavSatStatus(status=status, service=SERVICE_GPS),
        latitude=msg.lat / 1e7,
        longitude=msg.lon / 1e7,
        altitude=alt,
        position_covariance=cov,
        position_covariance_type=cov_type,
    )


def distance(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Horizontal distance [m] between two nearby points (equirectangular; for gates of metres to
    kilometres its error is far below the gate)."""
    dn = math.radians(lat2 - lat1)
    de = math.radians(lon2 - lon1) * math.cos(math.radians((lat1 + lat2) / 2))
    return EARTH_RADIUS * math.hypot(dn, de)


def deg_e7(x: float) -> int:
    return round(x * 1e7)


# ---------------------------------------------------------------------- the scenario's GPS
def scenario_gps(sc: Scenario, name: str | None = None, where: str = "") -> Any:
    """The scenario's simulated GPS (:class:`hilsim.sim.sensors_mobile.Gps`, bound to the world: datum,
    antenna site), enabled or not: whoever stands in for it uses its datum and antenna. ``name``
    picks one sensor; by default the only sensor of type ``gps``. One-line ConfigError if none."""
    from hilsim.sim.sensing import make_sensor, sensor_class
    from hilsim.sim.sensors_mobile import Gps

    found = [n for n, c in sc.sensors.items() if _is_gps(sensor_class, c.type, Gps)]
    if name is None:
        if len(found) != 1:
            what = "no sensor" if not found else f"several sensors ({', '.join(found)})"
            raise ConfigError(f"{where}sensors: {what} of type gps; the MAVLink GPS stands in for exactly one "
                              f"(name it with the gps option)")
        name = found[0]
    elif name not in found:
        raise ConfigError(f"{where}sensors.{name}: no GPS sensor of that name "
                          f"(GPS sensors: {', '.join(found) or 'none'})")
    src = f"{sc.source}: " if sc.source else where
    return make_sensor(name, sc.sensors[name], seed=sc.seed, dt_ns=sc.dt_ns, where=src, scenario=sc)


def _is_gps(sensor_class: Any, type_name: str, gps: type) -> bool:
    try:
        return issubclass(sensor_class(type_name), gps)
    except ConfigError:
        return False


# ---------------------------------------------------------------------- out: simulation -> MAVLink
def ned_velocity(odom: msgs.Odometry, antenna: np.ndarray | None = None) -> tuple[float, float, float]:
    """North, east, down velocity [m/s] of the antenna (its offset in the chassis frame; the chassis
    origin if None), from the chassis twist of ``truth/odom`` (in the chassis frame)."""
    from hilsim.sim.sensors_mobile import quat_matrix

    r = quat_matrix(odom.pose.pose.orientation)
    t = odom.twist.twist
    v = np.array([t.linear.x, t.linear.y, t.linear.z])
    if antenna is not None:
        v = v + np.cross([t.angular.x, t.angular.y, t.angular.z], antenna)
    w = r @ v
    return float(w[0]), float(w[1]), float(-w[2])


def course_cdeg(vn: float, ve: float) -> int:
    """Course over ground in centidegrees [0, 36000) (0 north, 9000 east)."""
    return round(math.degrees(math.atan2(ve, vn)) * 100.0) % 36000


def sigma_of(fix: msgs.NavSatFix) -> tuple[float, float]:
    """Horizontal and vertical 1σ [m] of a fix's covariance (0 where unknown)."""
    c = fix.position_covariance
    if fix.position_covariance_type == COV_UNKNOWN:
        return 0.0, 0.0
    return math.sqrt(max(c[0], c[4], 0.0)), math.sqrt(max(c[8], 0.0))


def mavlink_fix_type(fix: msgs.NavSatFix) -> int:
    s = fix.status.status
    if s < STATUS_FIX:
        return mavlink.GPS_FIX_TYPE_NO_FIX
    return {STATUS_SBAS_FIX: mavlink.GPS_FIX_TYPE_DGPS, STATUS_GBAS_FIX: mavlink.GPS_FIX_TYPE_RTK_FIXED}.get(
        s, mavlink.GPS_FIX_TYPE_3D_FIX)


def _i16(x: float) -> int:
    return max(-32768, min(32767, round(x)))


def _u16(x: float) -> int:
    return max(0, min(UINT16_MAX - 1, round(x)))


def hil_gps(fix: msgs.NavSatFix, vel_ned: tuple[float, float, float], *, satellites: int,
            gps_id: int = 0) -> Any:
    """HIL_GPS (113): degE7, mm, cm/s; ``eph``/``epv`` carry the fix's 1σ in cm, as PX4 reads them."""
    sh, sv = sigma_of(fix)
    vn, ve, vd = vel_ned
    return mavlink.MAVLink_hil_gps_message(
        time_usec=msgs.ns_of(fix.header.stamp) // 1000, fix_type=mavlink_fix_type(fix),
        lat=deg_e7(fix.latitude), lon=deg_e7(fix.longitude), alt=round(fix.altitude * 1000.0),
        eph=_u16(sh * 100.0) if sh else UINT16_MAX, epv=_u16(sv * 100.0) if sv else UINT16_MAX,
        vel=_u16(math.hypot(vn, ve) * 100.0), vn=_i16(vn * 100.0), ve=_i16(ve * 100.0), vd=_i16(vd * 100.0),
        cog=course_cdeg(vn, ve), satellites_visible=satellites, id=gps_id, yaw=0)


def gps_week(unix_s: float) -> tuple[int, int]:
    """GPS week and milliseconds into it of a UNIX time (GPS time = UTC + 18 s since 2017)."""
    gps_s = unix_s - 315_964_800.0 + 18.0
    week = int(gps_s // 604_800)
    return week, round((gps_s - week * 604_800) * 1000.0)


def gps_input(fix: msgs.NavSatFix, vel_ned: tuple[float, float, float], *, satellites: int, unix_s: float,
              speed_accuracy: float, dop: float = 1.0, gps_id: int = 0) -> Any:
    """GPS_INPUT (232), as ArduPilot takes it (GPS1_TYPE = 14): degE7, altitude in m (float),
    velocities in m/s, the fix's 1σ as horizontal and vertical accuracy."""
    sh, sv = sigma_of(fix)
    week, week_ms = gps_week(unix_s)
    ignore = 0
    if not sh:
        ignore |= mavlink.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY
    if not sv:
        ignore |= mavlink.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
    if not speed_accuracy:
        ignore |= mavlink.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
    vn, ve, vd = vel_ned
    return mavlink.MAVLink_gps_input_message(
        time_usec=msgs.ns_of(fix.header.stamp) // 1000, gps_id=gps_id, ignore_flags=ignore,
        time_week_ms=week_ms, time_week=week, fix_type=mavlink_fix_type(fix),
        lat=deg_e7(fix.latitude), lon=deg_e7(fix.longitude), alt=fix.altitude, hdop=dop, vdop=dop,
        vn=vn, ve=ve, vd=vd, speed_accuracy=speed_accuracy, horiz_accuracy=sh, vert_accuracy=sv,
        satellites_visible=satellites, yaw=0)


def isa_pressure_hpa(altitude: float) -> float:
    """Static pressure [hPa] of the ICAO standard atmosphere at ``altitude`` [m] (troposphere)."""
    return 1013.25 * (1.0 - 2.25577e-5 * altitude) ** 5.25588


def frd(v: msgs.Vector3) -> tuple[float, float, float]:
    """A polar body vector (acceleration, magnetic field) in MAVLink's FRD axes (module doc)."""
    return v.x, v.y, -v.z


def frd_rate(w: msgs.Vector3) -> tuple[float, float, float]:
    """An angular rate (a pseudovector) in MAVLink's FRD axes (module doc)."""
    return -w.x, -w.y, w.z


def body_field(imu: msgs.Imu, field_ned: tuple[float, float, float]) -> msgs.Vector3:
    """The Earth's magnetic field ``field_ned`` [gauss] in the IMU's body axes (ROS/MuJoCo x, y, z),
    from the IMU's orientation (body -> world)."""
    from hilsim.sim.sensors_mobile import quat_matrix

    n, e, d = field_ned
    b = quat_matrix(imu.orientation).T @ np.array([n, e, -d])
    return msgs.Vector3(x=float(b[0]), y=float(b[1]), z=float(b[2]))


def hil_sensor(imu: msgs.Imu, *, altitude: float, field_ned: tuple[float, float, float],
               temperature: float, sensor_id: int = 0) -> Any:
    """HIL_SENSOR (107): acceleration [m/s²], rates [rad/s], field [gauss] in FRD; barometric
    pressure [hPa] and pressure altitude [m] of the ISA at ``altitude``; no airspeed."""
    ax, ay, az = frd(imu.linear_acceleration)
    gx, gy, gz = frd_rate(imu.angular_velocity)
    mx, my, mz = frd(body_field(imu, field_ned))
    return mavlink.MAVLink_hil_sensor_message(
        time_usec=msgs.ns_of(imu.header.stamp) // 1000, xacc=ax, yacc=ay, zacc=az, xgyro=gx, ygyro=gy, zgyro=gz,
        xmag=mx, ymag=my, zmag=mz, abs_pressure=isa_pressure_hpa(altitude), diff_pressure=0.0,
        pressure_alt=altitude, temperature=temperature, fields_updated=HIL_SENSOR_FIELDS, id=sensor_id)


def gps_raw_int(lat: float, lon: float, alt: float, *, unix_us: int, vel_ned: tuple[float, float, float],
                h_acc: float, v_acc: float, satellites: int, fix_type: int = mavlink.GPS_FIX_TYPE_3D_FIX,
                dop: float = 1.0) -> Any:
    """GPS_RAW_INT (24) as a receiver sends it: degE7, mm (``alt`` and ``alt_ellipsoid`` both the
    given altitude: the simulated world has no geoid), 1σ accuracies in mm, DOPs × 100."""
    vn, ve, _ = vel_ned
    return mavlink.MAVLink_gps_raw_int_message(
        time_usec=unix_us, fix_type=fix_type, lat=deg_e7(lat), lon=deg_e7(lon), alt=round(alt * 1000.0),
        eph=_u16(dop * 100.0), epv=_u16(dop * 100.0), vel=_u16(math.hypot(vn, ve) * 100.0),
        cog=course_cdeg(vn, ve), satellites_visible=satellites, alt_ellipsoid=round(alt * 1000.0),
        h_acc=max(1, round(h_acc * 1000.0)), v_acc=max(1, round(v_acc * 1000.0)), vel_acc=0, hdg_acc=0, yaw=0)
