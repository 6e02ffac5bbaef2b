"""Laser and GPS of a mobile robot, in process: the laser against walls at known distances in a
small test world (max range, min range, no hit, the robot not seeing itself, noise), the GPS
against the truth (mean error within 3σ/√n, spread ≈ σ, north is +X, east is +Y), and bad
configuration as one line naming the field."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from hilsim.core import msgs
from hilsim.core.config import ConfigError, SensorConfig
from hilsim.core.scenario import load_scenario
from hilsim.sim.sensing import make_sensor

REPO = Path(__file__).resolve().parent.parent

# a box robot with a laser 0.2 m up at its centre; walls whose faces are at x = +3, x = -1.5, y = +2
# (no wall towards -y); the robot's own shell (group 1) and a mast on its body (group 0) around the laser
WORLD = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="10 10 0.1"/>
    <geom name="wall_east" type="box" pos="3.05 0 0.5" size="0.05 5 0.5"/>
    <geom name="wall_west" type="box" pos="-1.55 0 0.5" size="0.05 5 0.5"/>
    <geom name="wall_north" type="box" pos="0 2.05 0.5" size="5 0.05 0.5"/>
    <body name="base" pos="0 0 0.1">
      <freejoint/>
      <geom name="shell" type="box" size="0.3 0.3 0.3" group="1" contype="0" conaffinity="0"/>
      <geom name="mast" type="cylinder" pos="0.15 0 0.1" size="0.02 0.2" contype="0" conaffinity="0"/>
      <site name="laser" pos="0 0 0.1"/>
      <site name="gps" pos="-0.2 0 0.5"/>
      <body name="wheel" pos="0.1 0.1 0"><joint name="wheel" type="hinge"/><geom type="sphere" size="0.05"/></body>
    </body>
  </worldbody>
  <actuator><motor joint="wheel"/></actuator>
</mujoco>"""


def world(tmp_path: Path, text: str = WORLD) -> SimpleNamespace:
    p = tmp_path / "w.xml"
    p.write_text(text)
    return SimpleNamespace(world=SimpleNamespace(model=p))


def sensor(kind: str, sc: Any, seed: int = 0, **params: Any) -> Any:
    cfg = SensorConfig(type=kind, **params)
    return make_sensor(kind, cfg, seed=seed, dt_ns=2_000_000, scenario=sc)


def odom(x: float = 0.0, y: float = 0.0, yaw: float = 0.0, z: float = 0.1) -> msgs.Odometry:
    return msgs.Odometry(pose=msgs.PoseWithCovariance(pose=msgs.Pose(
        position=msgs.Point(x=x, y=y, z=z),
        orientation=msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)))))


# ---------------------------------------------------------------- laser
def test_laser_ranges_to_known_walls(tmp_path: Path) -> None:
    sc = world(tmp_path)
    las = sensor("laser", sc, rate_hz=10, fov=2 * math.pi, resolution=math.pi / 2, range_max=10.0)
    scan = las.measure(odom(), 0)
    # rays at -pi, -pi/2, 0, pi/2 (full circle: 4 rays, the last is not the first again)
    assert len(scan.ranges) == 4 and scan.angle_min == pytest.approx(-math.pi)
    assert scan.angle_max == pytest.approx(math.pi / 2) and scan.angle_increment == pytest.approx(math.pi / 2)
    assert scan.ranges[0] == pytest.approx(1.5) and scan.ranges[2] == pytest.approx(3.0)
    assert scan.ranges[3] == pytest.approx(2.0)
    assert scan.ranges[1] == math.inf  # nothing towards -y: no return, REP 117
    # moved and turned: the scanner's frame moves with the chassis
    scan = las.measure(odom(x=0.5, yaw=math.pi / 2), 0)
    # at (0.5, 0) facing +y its rays (-pi, -pi/2, 0, pi/2) point to world -y (nothing), +x, +y, -x
    assert scan.ranges == pytest.approx([math.inf, 2.5, 2.0, 2.0])
    assert scan.header.frame_id == "laser"
    msgs.decode(msgs.LaserScan, msgs.encode(scan))  # inf is a valid range on the wire


def test_laser_min_and_max_range(tmp_path: Path) -> None:
    sc = world(tmp_path)
    las = sensor("laser", sc, fov=2 * math.pi, resolution=math.pi / 2, range_min=1.6, range_max=2.5)
    r = las.measure(odom(), 0).ranges
    assert r[0] == -math.inf  # 1.5 m: closer than range_min
    assert r[2] == math.inf  # 3.0 m: beyond range_max, reported as no return
    assert r[3] == pytest.approx(2.0)


def test_laser_noise_is_gaussian_and_seeded(tmp_path: Path) -> None:
    sc = world(tmp_path)
    las = sensor("laser", sc, fov=math.pi / 2, resolution=math.pi / 4, noise_std=0.02)  # -45°, 0, +45°
    r = np.array([las.measure(odom(), 0).ranges for _ in range(2000)])
    assert abs(r[:, 1].mean() - 3.0) < 3 * 0.02 / math.sqrt(2000)
    assert r[:, 1].std() == pytest.approx(0.02, rel=0.1)
    again = sensor("laser", sc, fov=math.pi / 2, resolution=math.pi / 4, noise_std=0.02)
    assert again.measure(odom(), 0).ranges == pytest.approx(r[0].tolist(), abs=1e-6)


def test_laser_in_the_indoor_world_sees_walls_not_itself() -> None:
    sc = load_scenario("config/rover.yaml")
    las = sensor("laser", sc, fov=math.radians(270), resolution=math.radians(0.5), range_max=20.0)
    scan = las.measure(odom(z=0.25), 0)
    r = np.array(scan.ranges)
    assert len(r) == 541
    assert r.min() > 0.3  # nothing of the rover itself (wheels, mast) in the scan
    # straight ahead through the doorway (x 4) into the corridor: the wall at x = 6 (face 5.95), laser at x 0.38
    assert r[270] == pytest.approx(5.95 - 0.38, abs=1e-6)
    # to the left (+90°, at x 0.38, clear of the sofa at x 0.8..2.8): the north wall's face at y 3.95
    assert r[270 + 180] == pytest.approx(3.95, abs=1e-6)


@pytest.mark.parametrize(("params", "field"), [
    ({"fov": 7.0}, "sensors.laser.fov"),
    ({"frame": "nowhere"}, "sensors.laser.frame"),
    ({"range_min": 5.0, "range_max": 1.0}, "sensors.laser"),
    ({"resolution": -0.1}, "sensors.laser.resolution"),
])
def test_laser_bad_config_is_one_line(tmp_path: Path, params: dict[str, Any], field: str) -> None:
    with pytest.raises(ConfigError) as e:
        sensor("laser", world(tmp_path), **params)
    assert field in str(e.value) and "\n" not in str(e.value)


def test_negative_rate_is_one_line() -> None:
    with pytest.raises(ConfigError) as e:
        load_scenario("config/rover.yaml", {"sensors.laser.rate_hz": -10})
    assert "sensors.laser.rate_hz" in str(e.value) and "\n" not in str(e.value)


# ---------------------------------------------------------------- GPS
DATUM = (41.17788, -8.59779, 90.0)


def test_gps_north_is_plus_x_and_east_is_plus_y(tmp_path: Path) -> None:
    gps = sensor("gps", world(tmp_path), horizontal_std=0.0, vertical_std=0.0, datum=list(DATUM))
    lat0, lon0, alt0 = gps.geodetic(0, 0, 0)
    assert (lat0, lon0, alt0) == pytest.approx(DATUM, abs=1e-9)
    lat, lon, _ = gps.geodetic(1000.0, 0, 0)  # 1 km along +X
    assert lat - lat0 == pytest.approx(1000 / 111_100, rel=0.01) and abs(lon - lon0) < 0.001
    lat, lon, _ = gps.geodetic(0, 1000.0, 0)  # 1 km along +Y
    assert lon - lon0 == pytest.approx(1000 / (111_320 * math.cos(math.radians(lat0))), rel=0.01)
    assert abs(lat - lat0) < 0.001
    # the antenna's offset on the chassis counts: 0.2 m behind the chassis centre (south), 0.5 m up
    fix = gps.measure(odom(z=0.0), 0)
    assert fix.altitude == pytest.approx(90.5) and fix.latitude < lat0
    assert fix.status.status == 0 and fix.position_covariance_type == 2


def test_gps_error_statistics_against_truth(tmp_path: Path) -> None:
    sh, sv, n = 1.5, 3.0, 4000
    gps = sensor("gps", world(tmp_path), seed=3, horizontal_std=sh, vertical_std=sv, datum=list(DATUM))
    truth = odom(x=20.0, y=-35.0, z=0.0)
    exact = gps.geodetic(20.0 - 0.2, -35.0, 0.5)
    m_per_deg_lat = 111_100.0
    m_per_deg_lon = 111_320.0 * math.cos(math.radians(DATUM[0]))
    fixes = [gps.measure(truth, 0) for _ in range(n)]
    north = np.array([(f.latitude - exact[0]) * m_per_deg_lat for f in fixes])
    east = np.array([(f.longitude - exact[1]) * m_per_deg_lon for f in fixes])
    up = np.array([f.altitude - exact[2] for f in fixes])
    for err, s in ((north, sh), (east, sh), (up, sv)):
        assert abs(err.mean()) < 3 * s / math.sqrt(n), err.mean()
        assert err.std() == pytest.approx(s, rel=0.05)
    assert fixes[0].position_covariance == pytest.approx([sh**2, 0, 0, 0, sh**2, 0, 0, 0, sv**2])


def test_gps_datum_from_the_outdoor_world() -> None:
    sc = load_scenario("config/rover-outdoor.yaml")
    gps = sensor("gps", sc)
    assert gps.datum == pytest.approx(DATUM)


@pytest.mark.parametrize(("params", "field"), [
    ({"datum": [85.0, 0.0, 0.0]}, "sensors.gps.datum"),
    ({"datum": [-81.0, 0.0, 0.0]}, "sensors.gps.datum"),
    ({"frame": "antenna"}, "sensors.gps.frame"),
    ({"horizontal_std": -1}, "sensors.gps.horizontal_std"),
    ({}, "sensors.gps.datum"),  # the test world has no geodetic_datum
])
def test_gps_bad_config_is_one_line(tmp_path: Path, params: dict[str, Any], field: str) -> None:
    with pytest.raises(ConfigError) as e:
        sensor("gps", world(tmp_path), **params)
    assert field in str(e.value) and "\n" not in str(e.value), str(e.value)
