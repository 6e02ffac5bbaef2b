"""Sensors of a mobile robot: a 2D laser scanner and a GPS receiver, both from ``truth/odom``.

**laser** (``scan``, sensor_msgs/LaserScan). A sensor gets truth messages, not physics' MuJoCo
model, so the laser loads its *own* copy of the scenario's world (``world.model``) once
(:meth:`Laser.bind`). For each scan it puts that copy's free-floating base where ``truth/odom``
says the chassis is (the wheels stay at rest: they are not what it sees), runs MuJoCo's
kinematics and casts every ray of the scan in one ``mujoco.mj_multiRay`` call from the laser
frame (a site on the chassis, ``frame``), in the frame's x-y plane, counter-clockwise from
``−fov/2``. The robot does not see itself: the chassis body is excluded and so are the geom groups
``exclude_groups`` (the rover's geoms are in group 1). The world is assumed static (its bodies
are where the model puts them). Readings follow REP 117: no return within ``range_max`` is
``+inf``, a return closer than ``range_min`` is ``−inf``; the others get Gaussian noise
(``noise_std``), clipped to ``[range_min, range_max]``.

**gps** (``gps/fix``, sensor_msgs/NavSatFix), as the thesis' Gazebo plug-in does it: the world's
geodetic datum (``datum`` [lat, lon, alt], else the world model's custom numeric
``geodetic_datum``) is converted to UTM (pyproj; the zone of the datum's longitude, north or south
by its latitude), the antenna's true position (``frame``, a site on the chassis) is added with
**world X = north and Y = east** (the thesis' convention; Z up = altitude), Gaussian error is added
(``horizontal_std`` to northing and easting, ``vertical_std`` to altitude) and the result is converted
back to latitude and longitude. The fix reports ``STATUS_FIX`` by GPS and the diagonal covariance
of that error (``COVARIANCE_TYPE_DIAGONAL_KNOWN``). UTM grid north differs from true north by
the grid convergence (under a degree near the zone's centre); like the thesis, we take it as north.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from hilsim.core import msgs
from hilsim.core.config import ConfigError
from hilsim.sim.sensing import Sensor, SensorParams

TWO_PI = 2.0 * math.pi


def quat_matrix(q: msgs.Quaternion) -> np.ndarray:
    """Rotation matrix of a (unit) geometry_msgs quaternion."""
    w, x, y, z = q.w, q.x, q.y, q.z
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class _ChassisFrame:
    """A site fixed to the free-floating base of a world model: its offset from the chassis."""

    def __init__(self, model_path: Any, site: str, field: str) -> None:
        import mujoco

        try:
            self.model = mujoco.MjModel.from_xml_path(str(model_path))
        except ValueError as e:
            raise ConfigError(f"world.model: cannot load {model_path}: {str(e).splitlines()[0]}") from None
        m = self.model
        free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
                and m.body_parentid[m.jnt_bodyid[j]] == 0]
        if not free:
            raise ConfigError(f"{field}: {model_path} has no free-floating base (a mobile robot's chassis)")
        self.base = int(m.jnt_bodyid[free[0]])
        self.qadr = int(m.jnt_qposadr[free[0]])
        sites = [m.site(i).name for i in range(m.nsite)]
        if site not in sites:
            raise ConfigError(f"{field}: no site named {site!r} in {model_path} (sites: {', '.join(sites)})")
        sid = m.site(site).id
        if m.site_bodyid[sid] != self.base:
            raise ConfigError(f"{field}: site {site!r} is not on the chassis ({m.body(self.base).name})")
        self.pos = m.site_pos[sid].copy()
        q = m.site_quat[sid]
        self.rot = quat_matrix(msgs.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))

    def world_pose(self, odom: msgs.Odometry) -> tuple[np.ndarray, np.ndarray]:
        """Position and rotation of the site in the world, for the chassis pose of ``odom``."""
        p = odom.pose.pose.position
        r = quat_matrix(odom.pose.pose.orientation)
        return np.array([p.x, p.y, p.z]) + r @ self.pos, r @ self.rot


# ---------------------------------------------------------------- laser
class LaserParams(SensorParams):
    frame: str = Field("laser", description="site on the chassis the scanner sits at (x forward, z up)")
    fov: float = Field(1.5 * math.pi, gt=0, le=TWO_PI, description="field of view [rad], centred on x")
    resolution: float = Field(math.radians(0.5), gt=0, description="angle between rays [rad]")
    range_min: float = Field(0.1, ge=0, description="[m]")
    range_max: float = Field(20.0, gt=0, description="[m]")
    noise_std: float = Field(0.0, ge=0, description="Gaussian range noise [m]")
    exclude_groups: list[int] = Field(default_factory=lambda: [1], description="geom groups the rays ignore "
                                      "(the robot's own; 0-5)")

    @model_validator(mode="after")
    def _consistent(self) -> LaserParams:
        if self.range_min >= self.range_max:
            raise ValueError(f"range_min ({self.range_min}) must be below range_max ({self.range_max})")
        if self.resolution > self.fov:
            raise ValueError(f"resolution ({self.resolution}) must not exceed fov ({self.fov})")
        if any(not 0 <= g <= 5 for g in self.exclude_groups):
            raise ValueError(f"exclude_groups must be geom groups 0..5 (got {self.exclude_groups})")
        return self


class Laser(Sensor):
    """2D laser scanner by MuJoCo ray casting (one ``mj_multiRay`` per scan); see the module doc."""

    type_name = "laser"
    truth_topic = "odom"
    output_topic = "scan"
    truth_type = msgs.Odometry
    Params = LaserParams
    p: LaserParams

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        p = self.p
        closed = p.fov >= TWO_PI - p.resolution / 2  # a full circle: the last ray would repeat the first
        self.n = max(1, round(p.fov / p.resolution) + (0 if closed else 1))
        self.angle_min = -p.fov / 2
        self.angles = self.angle_min + p.resolution * np.arange(self.n)
        self._dirs = np.stack([np.cos(self.angles), np.sin(self.angles), np.zeros(self.n)], axis=1)
        self.frame: _ChassisFrame | None = None

    def bind(self, scenario: Any, where: str = "") -> None:
        import mujoco

        self.frame = _ChassisFrame(scenario.world.model, self.p.frame, f"{where}sensors.{self.name}.frame")
        self.data = mujoco.MjData(self.frame.model)
        self._group = np.ones(6, np.uint8)
        self._group[self.p.exclude_groups] = 0
        self._geomid = np.zeros(self.n, np.int32)
        self._dist = np.zeros(self.n)

    def ranges(self, odom: msgs.Odometry) -> np.ndarray:
        """True ranges [m] of every ray for a chassis pose (−1 where a ray hits nothing)."""
        import mujoco

        assert self.frame is not None, "Laser.bind() was not called"
        f, d = self.frame, self.data
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        d.qpos[f.qadr:f.qadr + 7] = (p.x, p.y, p.z, q.w, q.x, q.y, q.z)
        mujoco.mj_kinematics(f.model, d)
        origin, rot = f.world_pose(odom)
        vec = (self._dirs @ rot.T).reshape(-1)
        mujoco.mj_multiRay(f.model, d, origin, vec, self._group, 1, f.base, self._geomid, self._dist, None,
                           self.n, self.p.range_max)
        return self._dist.copy()

    def measure(self, truth: msgs.Odometry, stamp_ns: int) -> msgs.LaserScan:
        p = self.p
        r = self.ranges(truth)
        hit = r >= 0.0
        out = np.full(self.n, math.inf)
        if p.noise_std > 0.0:
            noisy = r + self.rng.normal(0.0, p.noise_std, self.n)  # one draw per ray, always: reproducible
            out[hit] = np.clip(noisy[hit], p.range_min, p.range_max)
        else:
            out[hit] = r[hit]
        out[hit & (r > p.range_max)] = math.inf
        out[hit & (r < p.range_min)] = -math.inf
        return msgs.LaserScan(
            header=msgs.header(stamp_ns, p.frame),
            angle_min=float(self.angle_min),
            angle_max=float(self.angles[-1]),
            angle_increment=float(p.resolution),
            time_increment=0.0,
            scan_time=1.0 / self.rate_hz,
            range_min=float(p.range_min),
            range_max=float(p.range_max),
            ranges=out.tolist(),
        )


# ---------------------------------------------------------------- GPS
class GpsParams(SensorParams):
    frame: str = Field("gps", description="site on the chassis where the antenna is")
    horizontal_std: float = Field(1.0, ge=0, description="σ of the northing and of the easting error [m]")
    vertical_std: float = Field(2.0, ge=0, description="σ of the altitude error [m]")
    datum: tuple[float, float, float] | None = Field(
        None, description="latitude [deg], longitude [deg], altitude [m] of the world origin (default: the "
        "world model's custom numeric geodetic_datum)")


def utm_zone(lat: float, lon: float) -> int:
    """EPSG code of the WGS 84 / UTM zone of a point (plain 6° zones, north or south)."""
    zone = min(int((lon + 180.0) // 6.0) + 1, 60)
    return (32600 if lat >= 0.0 else 32700) + zone


class Gps(Sensor):
    """GPS receiver: datum → UTM + true position (X north, Y east) + Gaussian error → lat/lon."""

    type_name = "gps"
    truth_topic = "odom"
    output_topic = "gps/fix"
    truth_type = msgs.Odometry
    Params = GpsParams
    p: GpsParams

    def bind(self, scenario: Any, where: str = "") -> None:
        field = f"{where}sensors.{self.name}"
        self.frame = _ChassisFrame(scenario.world.model, self.p.frame, f"{field}.frame")
        if self.p.datum is not None:
            datum, said = self.p.datum, f"{field}.datum"
        else:
            try:
                datum = tuple(float(x) for x in self.frame.model.numeric("geodetic_datum").data)
            except KeyError:
                raise ConfigError(f"{field}.datum: not given, and {scenario.world.model} has no custom numeric "
                                  "geodetic_datum (lat lon alt)") from None
            said = f"{field}.datum (the world's geodetic_datum)"
            if len(datum) != 3:
                raise ConfigError(f"{said}: expected latitude, longitude, altitude (got {list(datum)})")
        self.set_datum(*datum, field=said)

    def set_datum(self, lat: float, lon: float, alt: float, field: str = "datum") -> None:
        from pyproj import Transformer

        if not -80.0 <= lat <= 84.0:
            raise ConfigError(f"{field}: latitude {lat} is outside UTM's range (-80 to 84 degrees)")
        if not -180.0 <= lon <= 180.0:
            raise ConfigError(f"{field}: longitude {lon} is outside -180 to 180 degrees")
        self.datum = (lat, lon, alt)
        epsg = utm_zone(lat, lon)
        self.to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
        self.to_geo = Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
        self.easting0, self.northing0 = self.to_utm.transform(lon, lat)
        h, v = self.p.horizontal_std ** 2, self.p.vertical_std ** 2
        self._cov = [h, 0.0, 0.0, 0.0, h, 0.0, 0.0, 0.0, v]  # ENU, as sensor_msgs/NavSatFix says

    def geodetic(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """Latitude, longitude, altitude of a world point (X north, Y east, Z up), no error."""
        lon, lat = self.to_geo.transform(self.easting0 + y, self.northing0 + x)
        return lat, lon, self.datum[2] + z

    def measure(self, truth: msgs.Odometry, stamp_ns: int) -> msgs.NavSatFix:
        p = self.p
        pos, _ = self.frame.world_pose(truth)
        e = self.rng.normal(0.0, 1.0, 3)  # north, east, up: three draws per fix, always
        lat, lon, alt = self.geodetic(pos[0] + p.horizontal_std * e[0], pos[1] + p.horizontal_std * e[1],
                                      pos[2] + p.vertical_std * e[2])
        return msgs.NavSatFix(
            header=msgs.header(stamp_ns, p.frame),
            status=msgs.NavSatStatus(status=0, service=1),  # STATUS_FIX, SERVICE_GPS
            latitude=lat,
            longitude=lon,
            altitude=alt,
            position_covariance=list(self._cov),
            position_covariance_type=2,  # COVARIANCE_TYPE_DIAGONAL_KNOWN
        )
