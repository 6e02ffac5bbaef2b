"""What the recorder draws: the worlds' static geometry (checked against the MJCF files, read here
with ElementTree), laser scans as points in the laser frame, GPS fixes as GeoPoints and in the
world, odometry against truth, the occupancy grid and plan; and one lean end-to-end rover run
read back from its .rrd."""

from __future__ import annotations

import datetime
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from util import finish, up

from hilsim.core import msgs, recording

REPO = Path(__file__).resolve().parent.parent
WORLDS = REPO / "models" / "worlds"
ARM_WORLD = REPO / "models" / "arm" / "tabletop.xml"
ROVER_URDF = REPO / "models" / "rover" / "rover.urdf"
ARM_URDF = REPO / "models" / "arm" / "arm.urdf"


def _xml_geoms(path: Path) -> dict[str, dict[str, Any]]:
    """The named geoms directly in a world file's <worldbody> (its own, not the included robot's)."""
    out = {}
    for g in ET.parse(path).getroot().find("worldbody").findall("geom"):  # type: ignore[union-attr]
        out[g.get("name")] = {
            "type": g.get("type", "sphere"),
            "size": [float(v) for v in g.get("size", "0").split()],
            "pos": [float(v) for v in g.get("pos", "0 0 0").split()],
            "quat": [float(v) for v in g.get("quat", "1 0 0 0").split()],
        }
    return out


def _scene(world: Path, urdf: Path) -> Any:
    from hilsim.sim.kinematics import RobotModel
    from hilsim.sim.scene import Scene

    m = RobotModel.load(urdf)
    return Scene.load(world, m.links, m.root)


@pytest.mark.parametrize("world,urdf", [(WORLDS / "indoor.xml", ROVER_URDF), (WORLDS / "outdoor.xml", ROVER_URDF),
                                        (ARM_WORLD, ARM_URDF)], ids=["indoor", "outdoor", "arm"])
def test_static_geometry_matches_the_model(world: Path, urdf: Path) -> None:
    """Every geom of the world file and nothing of the robot: same kinds, sizes, places, rotations."""
    scene = _scene(world, urdf)
    expected = _xml_geoms(world)
    got = {g.name: g for g in scene.geoms}
    assert set(got) == set(expected), "static geoms are exactly the world file's own"
    assert scene.skipped == []
    for name, e in expected.items():
        g = got[name]
        assert g.kind == e["type"], name
        np.testing.assert_allclose(g.pos, e["pos"], atol=1e-9, err_msg=name)
        w, x, y, z = np.array(e["quat"]) / np.linalg.norm(e["quat"])
        assert abs(abs(np.dot(g.quat, [x, y, z, w])) - 1.0) < 1e-9, name  # same rotation (q or -q)
        if g.kind == "plane":  # drawn no larger than the model's, yet covering every other geom
            assert all(0 < s <= e["size"][i] or e["size"][i] == 0 for i, s in enumerate(g.size[:2])), name
            for o in scene.geoms:
                if o.kind != "plane":
                    assert np.all(np.abs(o.pos[:2] - g.pos[:2]) <= g.size[:2]), (name, o.name)
        else:
            np.testing.assert_allclose(g.size[:len(e["size"])], e["size"], rtol=1e-9, err_msg=name)


def test_the_arms_table_and_obstacle_and_the_rovers_base() -> None:
    """The two things missing from the arm's view so far, by size; the rover's chassis box, the datum."""
    arm = {g.name: g for g in _scene(ARM_WORLD, ARM_URDF).geoms}
    np.testing.assert_allclose(arm["table"].size, [0.45, 0.6, 0.375])
    np.testing.assert_allclose(arm["table"].pos, [0.15, 0.0, -0.375])
    np.testing.assert_allclose(arm["obstacle"].size, [0.03, 0.03, 0.125])
    np.testing.assert_allclose(arm["obstacle"].pos, [0.25, 0.0, 0.125])
    assert {g.kind for g in arm.values()} == {"plane", "box"}
    scene = _scene(ARM_WORLD, ARM_URDF)
    assert scene.base is None and scene.root_pose is not None
    np.testing.assert_allclose(scene.root_pose[0], [0, 0, 0], atol=1e-12)  # base_link at the world origin

    indoor = _scene(WORLDS / "indoor.xml", ROVER_URDF)
    walls = [g for g in indoor.geoms if g.name.startswith("wall_")]
    assert len(walls) == 11 and all(g.kind == "box" and g.size[2] == 0.5 for g in walls)
    assert indoor.base == "base_link" and indoor.datum is None
    np.testing.assert_allclose(indoor.base_box[1], [0.45, 0.22, 0.08], atol=1e-9)  # type: ignore[index]

    outdoor = _scene(WORLDS / "outdoor.xml", ROVER_URDF)
    assert outdoor.datum is not None and (outdoor.datum.lat, outdoor.datum.lon) == (41.17788, -8.59779)
    ground = next(g for g in outdoor.geoms if g.name == "ground")
    assert ground.size[0] < 100 and ground.size[1] < 100  # cut down from 200 m to what is there


# ---------------------------------------------------------------- rows of messages, read back
def _writer(tmp_path: Path, world: Path = WORLDS / "outdoor.xml") -> tuple[Any, Any, Path]:
    from hilsim.record.rows import RowWriter, rr
    from hilsim.sim.kinematics import RobotModel
    from hilsim.sim.scene import Scene

    rrd = tmp_path / "rows.rrd"
    rec = rr.RecordingStream("test_views")
    rec.save(rrd)
    model = RobotModel.load(ROVER_URDF)
    faults: list[str] = []
    rows = RowWriter(rec, "rover", model, lambda text, exc=None: faults.append(text),
                     Scene.load(world, model.links, model.root))
    rows.log_model()
    rows.log_scene()
    return rows, faults, rrd


def _close(rows: Any, rrd: Path) -> dict[str, list[dict[str, Any]]]:
    """Flush, close, and read the file back: per entity, its rows as {column: value}, by sim time."""
    from rerun.chunk import RrdReader

    assert rows.flush()
    rows.rec.flush()
    rows.rec.disconnect()
    recording.verify_rrd(rrd)
    out: dict[str, list[dict[str, Any]]] = {}
    for chunk in RrdReader(rrd).stream().to_chunks():
        rb = chunk.to_record_batch()
        # every column but wall-clock ones (log_time, of rec.log): pyarrow cannot make those datetimes
        d = {f.name: rb.column(i).to_pylist() for i, f in enumerate(rb.schema) if str(f.type).find("timestamp") < 0}
        n = rb.num_rows
        out.setdefault(chunk.entity_path, []).extend({k: v[i] for k, v in d.items()} for i in range(n))
    for entity_rows in out.values():
        entity_rows.sort(key=lambda r: r.get("sim_time") or datetime.timedelta(0))
    return out


def test_a_scan_becomes_points_in_the_laser_frame(tmp_path: Path) -> None:
    """Rays counter-clockwise from angle_min; ±inf (no return, too close) and NaN are no point."""
    from hilsim.record.rows import scan_points

    ranges = [1.0, 2.0, math.inf, -math.inf, 3.0, math.nan]
    scan = msgs.LaserScan(header=msgs.header(100_000_000, "laser"), angle_min=-math.pi / 2,
                          angle_max=-math.pi / 2 + 5 * math.pi / 4, angle_increment=math.pi / 4,
                          range_min=0.1, range_max=20.0, ranges=ranges)
    scan = msgs.decode(msgs.LaserScan, msgs.encode(scan))  # as the recorder gets it: float32 angles
    expected = [[0.0, -1.0, 0.0], [2 * math.cos(-math.pi / 4), 2 * math.sin(-math.pi / 4), 0.0],
                [3 * math.cos(math.pi / 2), 3.0, 0.0]]
    np.testing.assert_allclose(scan_points(scan), expected, atol=1e-6)

    rows, faults, rrd = _writer(tmp_path)
    rows.message("hilsim/rover/scan", scan)
    data = _close(rows, rrd)
    assert not faults
    row = next(r for r in data["/scan"] if r.get("Points3D:positions"))
    np.testing.assert_allclose(row["Points3D:positions"], expected, atol=1e-6)
    assert row["CoordinateFrame:frame"] == ["laser"]  # drawn under the laser's transform
    assert row["sim_time"] is not None


def test_gps_fixes_become_geopoints_and_world_points(tmp_path: Path) -> None:
    """A fix made by the GPS sensor of a known world point: the same lat/lon on the map, and back at
    that point in the world (X north, Y east)."""
    from hilsim.sim.sensors_mobile import Gps

    gps = Gps.__new__(Gps)  # only its geodetic conversion, the sensor's own (no sampling)
    gps.p = Gps.Params(horizontal_std=0.0, vertical_std=0.0)
    gps.set_datum(41.17788, -8.59779, 90.0)
    points = [(0.0, 0.0, 0.3), (10.0, 0.0, 0.3), (10.0, 5.0, 0.5)]
    rows, faults, rrd = _writer(tmp_path)
    fixes = []
    for k, (x, y, z) in enumerate(points):
        lat, lon, alt = gps.geodetic(x, y, z)
        fixes.append((lat, lon))
        rows.message("hilsim/rover/gps/fix", msgs.NavSatFix(header=msgs.header(k * 200_000_000, "gps"),
                                                            latitude=lat, longitude=lon, altitude=alt))
    rows.message("hilsim/rover/truth/odom", _odom(700_000_000, "world", 0.0, 0.0, 0.0))
    lat, lon, alt = gps.geodetic(12.0, -3.0, 3.0)
    rows.message("hilsim/rover/gps/fix", msgs.NavSatFix(header=msgs.header(800_000_000, "gps"), latitude=lat,
                                                        longitude=lon, altitude=alt))
    data = _close(rows, rrd)
    assert not faults
    geo = [r["GeoPoints:positions"] for r in data["/geo/gps/0"] if r.get("GeoPoints:positions")]
    assert len(geo) == 4 and [len(g) for g in geo] == [1, 2, 3, 4]  # the track so far, at each fix
    np.testing.assert_allclose(geo[2], fixes, rtol=0, atol=1e-12)
    assert fixes[1][0] > fixes[0][0] and abs(fixes[1][1] - fixes[0][1]) < 1e-6  # +X is north
    world = [r["Points3D:positions"] for r in data["/paths/gps/0"] if r.get("Points3D:positions")]
    np.testing.assert_allclose(world[2], points, atol=1e-3)  # no truth yet: at the fix's altitude
    np.testing.assert_allclose(world[-1][-1], [12.0, -3.0, 0.25], atol=1e-3)  # then at the chassis' height
    assert data["/geo/gps/0"][0].get("GeoPoints:colors") or any(r.get("GeoPoints:colors") for r in data["/geo/gps/0"])


def _odom(t: int, frame: str, x: float, y: float, yaw: float, vx: float = 0.0) -> msgs.Odometry:
    return msgs.Odometry(header=msgs.header(t, frame), child_frame_id="base_link", pose=msgs.PoseWithCovariance(
        pose=msgs.Pose(position=msgs.Point(x=x, y=y, z=0.25 if frame == "world" else 0.0),
                       orientation=msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)))),
        twist=msgs.TwistWithCovariance(twist=msgs.Twist(linear=msgs.Vector3(x=vx))))


def _trails(data: dict[str, list[dict[str, Any]]]) -> tuple[Any, Any]:
    truth = [r["LineStrips3D:strips"] for r in data["/paths/truth/0"] if r.get("LineStrips3D:strips")][-1][0]
    odom = [r["LineStrips3D:strips"] for r in data["/paths/odom/0"] if r.get("LineStrips3D:strips")][-1][0]
    return truth, odom


def test_odometry_is_drawn_against_the_truth(tmp_path: Path) -> None:
    """The odom frame is where the rover starts in the model (the origin, chassis 0.255 m up): an
    odometry 10 % long is drawn ahead of the truth, in the world, with plots and the chassis box."""
    rows, faults, rrd = _writer(tmp_path)
    for k in range(11):  # 1 s: a point every 100 ms
        t = k * 100_000_000
        rows.message("hilsim/rover/truth/odom", _odom(t, "world", 0.1 * k, 0.0, 0.0, 0.1))
        rows.message("hilsim/rover/odom", _odom(t, "odom", 0.11 * k, 0.0, 0.0, 0.11))
    data = _close(rows, rrd)
    assert not faults
    truth, odom = _trails(data)
    assert len(truth) == len(odom) == 11
    np.testing.assert_allclose(truth[-1], [1.0, 0.0, 0.25], atol=1e-9)
    np.testing.assert_allclose(odom[-1], [1.1, 0.0, 0.255], atol=1e-9)  # where it thinks it is
    xs = [r["Scalars:scalars"][0] for r in data["/odometry/x/odom"] if r.get("Scalars:scalars")]
    assert xs[-1] == pytest.approx(1.1) and len(xs) == 11
    ghost = [r for r in data["/odom/estimate"] if r.get("Boxes3D:centers")]
    np.testing.assert_allclose(ghost[-1]["Boxes3D:centers"][0], [1.1, 0.0, 0.255], atol=1e-9)


def test_odometry_without_a_scene_starts_at_the_first_truth(tmp_path: Path) -> None:
    """No world model: the odom frame is the first truth's pose (here (1, 2) facing +y), so 'x = 1.1 m'
    in the odometry is drawn 1.1 m along the world's +y from there."""
    from hilsim.record.rows import RowWriter, rr

    rrd = tmp_path / "rows.rrd"
    rec = rr.RecordingStream("test_views")
    rec.save(rrd)
    rows = RowWriter(rec, "rover", None, lambda text, exc=None: None)
    for k in range(11):
        t = k * 100_000_000
        rows.message("hilsim/rover/truth/odom", _odom(t, "world", 1.0, 2.0 + 0.1 * k, math.pi / 2, 0.1))
        rows.message("hilsim/rover/odom", _odom(t, "odom", 0.11 * k, 0.0, 0.0, 0.11))
    truth, odom = _trails(_close(rows, rrd))
    np.testing.assert_allclose(truth[-1], [1.0, 3.0, 0.25], atol=1e-9)
    np.testing.assert_allclose(odom[-1], [1.0, 3.1, 0.25], atol=1e-9)


def test_occupancy_grid_and_plan(tmp_path: Path) -> None:
    """The grid as a textured quad where its cells are (occupied dark, free light, unknown grey),
    the plan as a line through its poses."""
    rows, faults, rrd = _writer(tmp_path, WORLDS / "indoor.xml")
    w, h, res = 4, 2, 0.5
    data_cells = [0, 100, -1, 50, 0, 0, 0, 100]
    grid = msgs.OccupancyGrid(header=msgs.header(0, "world"), info=msgs.MapMetaData(
        resolution=res, width=w, height=h, origin=msgs.Pose(position=msgs.Point(x=-1.0, y=-0.5))), data=data_cells)
    poses = [msgs.PoseStamped(pose=msgs.Pose(position=msgs.Point(x=float(i), y=0.5 * i))) for i in range(3)]
    rows.message("hilsim/rover/map", msgs.decode(msgs.OccupancyGrid, msgs.encode(grid)))
    rows.message("hilsim/rover/plan", msgs.Path(header=msgs.header(0, "world"), poses=poses))
    data = _close(rows, rrd)
    assert not faults
    quad = next(r for r in data["/map"] if r.get("Mesh3D:vertex_positions"))
    np.testing.assert_allclose(np.array(quad["Mesh3D:vertex_positions"])[:, :2],
                               [[-1.0, -0.5], [1.0, -0.5], [1.0, 0.5], [-1.0, 0.5]])
    buf = quad["Mesh3D:albedo_texture_buffer"][0]
    texture = np.frombuffer(bytes(buf), np.uint8).reshape(h, w, 3)[:, :, 0]
    assert texture[0, 0] > texture[0, 3] > texture[0, 1]  # free > half occupied > occupied
    assert texture[0, 2] == 128 and texture[1, 3] == texture[0, 1]  # unknown mid grey
    line = next(r for r in data["/plan"] if r.get("LineStrips3D:strips"))["LineStrips3D:strips"][0]
    np.testing.assert_allclose(np.array(line)[:, :2], [[0, 0], [1, 0.5], [2, 1.0]])


# ---------------------------------------------------------------- end to end
@pytest.mark.e2e
def test_rover_recording_holds_the_views(router: str, tmp_path: Path) -> None:
    """A short lockstep run of the rover outdoors (scripted drive, no navigator), recorded by the real
    logger process, read back: the world's geometry, scan points, truth and odometry trails, GPS
    fixes on the map, the rover's transforms and the stored layout."""
    from rerun.chunk import RrdReader

    run = tmp_path / "run"
    p = up("config/rover-outdoor.yaml", "--router", router, "--duration", "2.5", "--out", str(run),
           "--set", "services=[physics, sensors, controller, logger]",
           "--set", "controller.params.script=[[0.2, 0.6, 0.0, 0.3]]")
    out = finish(p, 90)
    assert p.returncode == 0, out
    rrd = run / "recording.rrd"
    rows = recording.entity_rows(rrd)
    n_geoms = len(_xml_geoms(WORLDS / "outdoor.xml"))
    assert len([e for e in rows if e.startswith("/world/")]) == n_geoms
    assert rows["/scan"] >= 20  # 10 Hz for 2.5 s
    assert rows["/paths/truth/0"] >= 20 and rows["/paths/odom/0"] >= 20
    assert rows["/geo/gps/0"] >= 10 and rows["/paths/gps/0"] >= 10  # 5 Hz
    assert rows["/tf/base_link"] >= 200  # every 10 ms
    assert rows["/odom/estimate"] >= 200
    assert RrdReader(rrd).blueprints(), "the default layout is stored"
    # the rover moved, in the truth and in its odometry alike
    data = {}
    for chunk in RrdReader(rrd).stream().to_chunks():
        if chunk.entity_path in ("/paths/truth/0", "/paths/odom/0", "/scan"):
            d = chunk.to_record_batch().to_pydict()
            data.setdefault(chunk.entity_path, []).extend(v for v in d.get("LineStrips3D:strips", d.get(
                "Points3D:positions", [])) if v)
    truth = max(data["/paths/truth/0"], key=lambda s: len(s[0]))[0]
    odom = max(data["/paths/odom/0"], key=lambda s: len(s[0]))[0]
    assert truth[-1][0] - truth[0][0] > 0.5
    assert np.linalg.norm(np.subtract(truth[-1][:2], odom[-1][:2])) < 0.3
    assert all(len(pts) > 10 for pts in data["/scan"])  # walls and rocks are hit


def _views(container: Any) -> list[Any]:
    """The views of a blueprint container, depth first."""
    out = []
    for c in vars(container)["contents"]:
        out += _views(c) if hasattr(c, "contents") and not hasattr(c, "class_identifier") else [c]
    return out


@pytest.mark.parametrize("world,urdf,expected", [
    (WORLDS / "indoor.xml", ROVER_URDF, {"world", "log", "odometry"}),
    (WORLDS / "outdoor.xml", ROVER_URDF, {"world", "log", "odometry", "map"}),
    (ARM_WORLD, ARM_URDF, {"world", "log"}),
], ids=["indoor", "outdoor", "arm"])
def test_default_layout(world: Path, urdf: Path, expected: set[str]) -> None:
    """A 3D view of the world for every robot; the odometry tab for a mobile one; the map where the
    world has a datum (only there can a GPS track be placed on it)."""
    from hilsim.record.viewer import default_blueprint
    from hilsim.sim.kinematics import RobotModel
    from hilsim.sim.scene import Scene

    model = RobotModel.load(urdf)
    bp = default_blueprint(model, Scene.load(world, model.links, model.root))
    views = _views(bp.root_container)
    names = {str(vars(v).get("name")) for v in views}
    grids = {vars(c).get("name") for c in vars(vars(bp.root_container)["contents"][1])["contents"]}
    assert {"world", "log"} <= names
    assert ("odometry" in grids) == ("odometry" in expected)
    assert ("map" in names) == ("map" in expected)
    spatial = next(v for v in views if vars(v).get("name") == "world")
    assert str(vars(spatial)["properties"]["SpatialInformation"].target_frame.as_arrow_array()[0]) == "world"


def test_every_geom_kind_is_drawn(tmp_path: Path) -> None:
    """A world of one geom of each kind: each one read at its place and size (a mesh's vertices in
    the world, a capsule's length) and logged; a height field is listed as not drawn."""
    xml = tmp_path / "kinds.xml"
    xml.write_text("""<mujoco>
  <asset>
    <mesh name="tetra" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/>
    <hfield name="hills" nrow="2" ncol="2" size="1 1 0.1 0.1"/>
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
    <geom name="ball" type="sphere" pos="1 0 0.5" size="0.5"/>
    <geom name="pill" type="capsule" pos="-1 0 1" size="0.1 0.4" euler="90 0 0"/>
    <geom name="egg" type="ellipsoid" pos="0 2 1" size="0.1 0.2 0.3"/>
    <geom name="rock" type="mesh" mesh="tetra" pos="3 0 0"/>
    <geom name="hills" type="hfield" hfield="hills" pos="0 -3 0"/>
    <body name="lid" pos="0 0 2"><geom name="lid" type="box" size="0.1 0.1 0.1"/></body>
    <body name="door" pos="0 0 3"><joint type="hinge"/><geom name="door" type="box" size="0.1 0.1 0.1"/></body>
  </worldbody>
</mujoco>""")
    from hilsim.record.rows import rr
    from hilsim.sim.scene import Scene

    scene = Scene.load(xml)
    got = {g.name: g for g in scene.geoms}
    assert set(got) == {"ground", "ball", "pill", "egg", "rock", "lid"}  # the door can move
    assert scene.skipped == ["hills"]
    assert got["ball"].kind == "sphere" and got["ball"].size[0] == 0.5
    np.testing.assert_allclose(got["pill"].half_extent, [0.1, 0.5, 0.1], atol=1e-9)  # lying along y
    np.testing.assert_allclose(got["egg"].size, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(got["lid"].pos, [0, 0, 2])  # welded to the world: static
    rock = got["rock"]
    assert rock.vertices is not None and rock.faces is not None and len(rock.faces) == 4
    np.testing.assert_allclose(rock.vertices.min(axis=0), [3, 0, 0], atol=1e-6)
    np.testing.assert_allclose(rock.vertices.max(axis=0), [4, 1, 1], atol=1e-6)
    ground = got["ground"]  # infinite: as far as the rest reaches, plus the margin
    assert 4.0 < ground.size[0] < 6.0 and 3.0 < ground.size[1] < 5.0

    rrd = tmp_path / "kinds.rrd"
    rec = rr.RecordingStream("test_views")
    rec.save(rrd)
    scene.log_static(rec)
    rec.flush()
    rec.disconnect()
    rows = recording.entity_rows(rrd)
    assert {e for e in rows if e.startswith("/world/")} == {f"/world/{n}" for n in got}
