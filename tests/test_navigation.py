"""Rover navigation without transport: the occupancy grid (rasterising, inflation), SE(2) planning
validity, the path follower on a kinematic base, the navigator's config and goal checks, the nav
messages, --world and plan evaluate for rover goals."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from hilsim.core import msgs
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario
from hilsim.navigation import grid as gridmod
from hilsim.navigation.follower import Follower, FollowerParams, split_at_cusps
from hilsim.navigation.planner import Footprint, SE2Planner, directions, path_length, smoothness

REPO = Path(__file__).resolve().parent.parent
INDOOR = REPO / "models" / "worlds" / "indoor.xml"
OUTDOOR = REPO / "models" / "worlds" / "outdoor.xml"

BOX_WORLD = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <geom name="block" type="box" pos="1 0 0.5" size="0.25 0.25 0.5"/>
    <geom name="post" type="cylinder" pos="-1 1 0.5" size="0.2 0.5"/>
    <geom name="low" type="box" pos="0 -1.5 0.02" size="0.3 0.3 0.02"/>
    <geom name="high" type="box" pos="0 1.5 2.0" size="0.3 0.3 0.2"/>
    <body name="robot" pos="-1.5 -1.5 0.2"><freejoint/><geom type="box" size="0.2 0.2 0.1"/></body>
  </worldbody>
</mujoco>"""


@pytest.fixture
def box_world(tmp_path: Path) -> Path:
    p = tmp_path / "box.xml"
    p.write_text(BOX_WORLD)
    return p


def test_grid_rasterises_static_obstacles_in_the_band(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0))
    assert (g.width, g.height) == (80, 80)
    assert not g.free(1.0, 0.0, inflated=False) and not g.free(1.2, 0.2, inflated=False)  # inside the box
    assert g.free(1.3, 0.0, inflated=False) and g.free(0.7, 0.0, inflated=False)  # just outside it
    assert not g.free(-1.0, 1.0, inflated=False) and not g.free(-1.0, 1.17, inflated=False)  # the cylinder
    assert g.free(-1.0, 1.25, inflated=False) and g.free(-0.75, 1.1, inflated=False)  # outside its radius
    assert g.free(0.0, -1.5, inflated=False)  # 4 cm tall: below the band (0.1–0.7 m)
    assert g.free(0.0, 1.5, inflated=False)  # at 1.8–2.2 m: above it
    assert g.free(-1.5, -1.5, inflated=False)  # the robot (a free body) is not an obstacle
    assert not g.free(5.0, 0.0, inflated=False)  # outside the map is never free
    # the box covers 10×10 cells, the cylinder about π·0.2²/0.05² ≈ 50
    assert int(g.occ.sum()) == pytest.approx(100 + 50, abs=12)


def test_grid_inflation_grows_obstacles_by_the_radius(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0)).inflate(0.3)
    assert g.radius == 0.3
    # the box's face is at x = 1.25: blocked up to 0.3 m (+ half a cell diagonal) beyond, free after
    assert not g.free(1.25 + 0.28, 0.0) and g.free(1.25 + 0.4, 0.0)
    assert not g.free(1.0 - 0.25 - 0.28, 0.0) and g.free(1.0 - 0.25 - 0.4, 0.0)
    # around the cylinder: a disc of radius 0.2 + 0.3
    assert not g.free(-1.0 + 0.47, 1.0) and g.free(-1.0 + 0.6, 1.0)
    assert g.inflated[g.occ].all()  # inflation never frees a cell
    # a corner is rounded: the diagonal point at 0.25 m from the corner is blocked, at 0.42 m it is free
    c = 0.25 / math.sqrt(2)
    assert not g.free(1.25 + c, 0.25 + c)
    c = 0.42 / math.sqrt(2)
    assert g.free(1.25 + c, 0.25 + c)


def test_grid_message_round_trip(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.1, bounds=(-2.0, 2.0, -1.0, 1.0))
    m = msgs.decode(msgs.OccupancyGrid, msgs.encode(g.to_msg(5_000_000_000)))
    assert (m.info.width, m.info.height) == (40, 20) and m.header.frame_id == "world"
    assert m.info.origin.position.x == -2.0 and m.info.origin.position.y == -1.0
    data = np.array(m.data).reshape(20, 40)
    assert set(np.unique(data)) == {0, 100}
    assert (data == 100).sum() == g.occ.sum()
    r, c = g.cell(1.0, 0.0)
    assert data[int(r), int(c)] == 100  # row-major, rows along +y, as nav_msgs says
    bad = g.to_msg(0)
    bad.data = bad.data[:-1]
    with pytest.raises(msgs.BadMessage, match="cells for 40x20"):
        msgs.decode(msgs.OccupancyGrid, msgs.encode(bad))


def test_indoor_world_walls_and_doorway() -> None:
    g = gridmod.from_model(INDOOR, resolution=0.05).inflate(0.57)
    assert not g.free(4.0, 2.4, inflated=False) and not g.free(-2.0, 0.0, inflated=False)  # walls
    assert g.free(4.0, 0.0, inflated=False) and g.free(4.0, 0.0)  # the middle of the doorway (1.6 m)
    assert not g.free(4.0, 0.5)  # 0.3 m from the door frame: within the footprint's reach
    assert g.free(0.0, 0.0)  # where the rover starts


def test_footprint_covering_circles_cover_the_rectangle() -> None:
    fp = Footprint.covering(1.0, 0.9, 2)
    assert fp.centres == (-0.25, 0.25)
    corners = [(sx * 0.5, sy * 0.45) for sx in (-1, 1) for sy in (-1, 1)]
    for cx, cy in corners:
        assert min(math.hypot(cx - c, cy) for c in fp.centres) <= fp.radius + 1e-9
    px, py = fp.points(1.0, 2.0, math.pi / 2)  # rotated: the circles lie along y
    assert px == pytest.approx([1.0, 1.0]) and py == pytest.approx([1.75, 2.25])


def test_planner_validity_and_a_path_around_an_obstacle(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0))
    pl = SE2Planner(g, Footprint(0.2, (0.0,)), turning_radius=0.4, clearance=0.05)
    assert pl.why_invalid(0.0, 0.0, 0.0) is None
    assert "too close to an obstacle" in (pl.why_invalid(1.0, 0.0, 0.0) or "")
    assert "too close" in (pl.why_invalid(1.45, 0.0, 0.0) or "")  # 0.2 m from the box: the circle touches
    assert "outside the map" in (pl.why_invalid(2.5, 0.0, 0.0) or "")
    assert pl.why_invalid(math.nan, 0.0, 0.0) == "not a finite pose"
    start, goal = (0.3, 0.0, 0.0), (1.7, 0.0, 0.0)  # the box is in between
    res = pl.plan(start, goal, max_iterations=20000, time_limit=20.0, seed=1, attempts=2)
    assert res.path is not None, res.message
    assert res.path[0] == pytest.approx(start) and res.path[-1] == pytest.approx(goal)
    # every point valid, points about 5 cm apart, and the path goes round the box (longer than 1.4 m)
    assert all(pl.is_valid(*p) for p in res.path)
    assert np.max(np.hypot(*np.diff(res.path[:, :2], axis=0).T)) < 0.1
    assert path_length(res.path) > 1.6
    assert np.max(np.abs(res.path[:, 1])) > 0.45  # it left the straight line by the box's half width + r
    bad = pl.plan(start, (1.0, 0.0, 0.0), max_iterations=100)
    assert bad.path is None and bad.message.startswith("goal invalid")


def test_a_start_a_little_inside_the_inflation_plans_from_the_nearest_free_pose(box_world: Path) -> None:
    """The rover stopped a few cm inside the inflated zone (a goal near a wall, odometry): the plan
    starts where it is and goes through the nearest valid pose instead of failing."""
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0))
    pl = SE2Planner(g, Footprint(0.2), turning_radius=0.4, clearance=0.05)
    start = (1.25 + 0.2, 0.0, 0.0)  # 0.2 m from the box's face: inside the 0.25 m (+ margin) inflation
    assert pl.why_invalid(*start) is not None
    near = pl.nearest_valid(start)
    assert near is not None and pl.is_valid(*near) and math.hypot(near[0] - start[0], near[1] - start[1]) < 0.15
    res = pl.plan(start, (1.7, 1.0, 0.0), max_iterations=20000, time_limit=20.0)
    assert res.path is not None, res.message
    assert tuple(res.path[0]) == pytest.approx(start) and tuple(res.path[1]) == pytest.approx(near)
    assert pl.nearest_valid((1.0, 0.0, 0.0)) is None  # deep inside the box: nothing near is free
    bad = pl.plan((1.0, 0.0, 0.0), (1.7, 1.0, 0.0), max_iterations=100)
    assert bad.path is None and bad.message.startswith("start invalid")


def test_planner_yaw_is_wrapped_and_unknown_planner_refused(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0))
    with pytest.raises(ValueError, match="no geometric planner"):
        SE2Planner(g, Footprint(0.2), planner="NoSuchPlanner")
    pl = SE2Planner(g, Footprint(0.2), turning_radius=0.4)
    res = pl.plan((-1.0, -1.0, 0.0), (0.0, -1.0, 3.1416), max_iterations=20000, time_limit=20.0)
    assert res.path is not None, res.message
    assert abs(math.remainder(res.path[-1, 2] - 3.1416, 2 * math.pi)) < 1e-9


def test_cusps_split_a_path_into_forward_and_backward_segments() -> None:
    fwd = np.array([[0.1 * i, 0.0, 0.0] for i in range(6)])
    back = np.array([[0.5 - 0.1 * i, 0.0, 0.0] for i in range(1, 4)])
    path = np.vstack([fwd, back])
    assert list(directions(path)) == [1] * 5 + [-1] * 3
    segs = split_at_cusps(path)
    assert [s for _, s in segs] == [1, -1]
    assert segs[0][0][-1] == pytest.approx(segs[1][0][0])  # the cusp ends one and starts the next
    assert smoothness(fwd) == 0.0


def drive(f: Follower, pose: tuple[float, float, float], steps: int = 3000, dt: float = 0.05,
          lag: float = 0.0) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """A kinematic four-wheel-steer base (body twist integrated exactly), optionally with a first-order lag."""
    x, y, th = pose
    v = np.zeros(3)
    cmds = []
    for _ in range(steps):
        if f.done:
            break
        cmd = np.array(f.step(x, y, th))
        cmds.append(tuple(cmd))
        v = cmd if lag == 0 else v + (cmd - v) * min(1.0, dt / lag)
        c, s = math.cos(th), math.sin(th)
        x += (c * v[0] - s * v[1]) * dt
        y += (s * v[0] + c * v[1]) * dt
        th += v[2] * dt
    return (x, y, th), cmds


def test_follower_reaches_goal_and_final_yaw_within_tolerance(box_world: Path) -> None:
    g = gridmod.from_model(box_world, resolution=0.05, bounds=(-2.0, 2.0, -2.0, 2.0))
    pl = SE2Planner(g, Footprint(0.2), turning_radius=0.4)
    res = pl.plan((0.3, 0.0, 0.0), (1.7, 0.5, 1.0), max_iterations=20000, time_limit=20.0, seed=2)
    assert res.path is not None
    p = FollowerParams(max_speed=0.6, xy_tolerance=0.05, yaw_tolerance=0.05)
    f = Follower(res.path, p, final_yaw=1.0)
    (x, y, th), cmds = drive(f, (0.3, 0.0, 0.0), lag=0.15)
    assert f.done and f.at_goal and f.progress > 0.95
    assert math.hypot(x - 1.7, y - 0.5) < 0.08
    assert abs(math.remainder(th - 1.0, 2 * math.pi)) < 0.06
    speeds = [math.hypot(c[0], c[1]) for c in cmds]
    assert max(speeds) <= 0.6 + 1e-9 and max(abs(c[2]) for c in cmds) <= p.max_yaw_rate + 1e-9
    assert f.step(x, y, th) == (0.0, 0.0, 0.0)  # done: stands still


def test_follower_drives_backwards_on_a_reverse_segment_and_corrects_sideways() -> None:
    path = np.array([[-0.05 * i, 0.0, 0.0] for i in range(41)])  # 2 m straight back, facing +x
    f = Follower(path, FollowerParams(), final_yaw=None)
    vx, vy, wz = f.step(0.0, 0.1, 0.0)  # 10 cm left of the path
    assert vx < 0 and vy < 0 and wz == pytest.approx(0.0)  # backwards, crabbing right, no turn
    (x, y, _), _ = drive(f, (0.0, 0.1, 0.0))
    assert f.done and math.hypot(x + 2.0, y) < 0.07


def test_follower_without_final_yaw_stops_at_the_position() -> None:
    path = np.array([[0.05 * i, 0.0, 0.0] for i in range(21)])
    f = Follower(path, FollowerParams(xy_tolerance=0.05), final_yaw=None)
    (x, y, _), _ = drive(f, (0.0, 0.0, 0.3))  # starts turned away from the path's heading
    assert f.done and math.hypot(x - 1.0, y) < 0.06


# ------------------------------------------------------------------ the navigator's config and goals
def test_navigator_config_errors_are_one_line() -> None:
    from hilsim.services.navigator import NavigatorService

    cases = [
        ({"navigator.rate_hz": 30}, "navigator.rate_hz (30) must divide controller.rate_hz"),
        ({"navigator.resolution": -0.1}, "navigator.resolution"),
        ({"navigator.z_band": [0.7, 0.1]}, "z_band must be"),
        ({"navigator.planner": "NoSuchPlanner"}, "navigator.planner"),
        ({"navigator.speed": 2}, "navigator.speed"),
        ({"task.targets": [[1.0, 2.0, 0.0, 4.0]]}, "task.targets[0]: a rover target is [x, y] or [x, y, yaw]"),
    ]
    for over, text in cases:
        with pytest.raises(ConfigError) as e:
            NavigatorService(load_scenario("rover", over))
        assert text in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_navigator_checks_goals_against_the_map() -> None:
    from hilsim.services.navigator import NavigatorService, initial_pose

    nav = NavigatorService(load_scenario("rover"))
    assert nav.origin == (0.0, 0.0, 0.0)
    assert initial_pose(__import__("mujoco").MjModel.from_xml_path(str(OUTDOOR)))[:2] == (0.0, 0.0)
    assert nav.check_goal(5.0, 2.5, 1.5708) is None
    assert nav.check_goal(5.0, 2.5, None) is None
    code, why = nav.check_goal(4.0, 2.4, None) or (0, "")
    assert code == msgs.GOAL_IN_COLLISION and why.startswith("GOAL_IN_COLLISION")
    code, why = nav.check_goal(50.0, 0.0, 0.0) or (0, "")
    assert code == msgs.GOAL_OUT_OF_LIMITS and "outside the map" in why
    # through the queryable's handler: a joints goal, a non-unit quaternion, a reserved id
    nav.pub_cmd = nav.pub_plan = nav.pub_result = nav.pub_feedback = None  # type: ignore[assignment]
    r = nav.on_goal(msgs.MoveGoal(target_kind="joints", joint_positions=[0.0]))
    assert not r.accepted and "target_kind 'pose'" in r.reason
    r = nav.on_goal(msgs.MoveGoal(target_kind="pose", use_orientation=True,
                                  pose=msgs.Pose(orientation=msgs.Quaternion(w=2.0))))
    assert not r.accepted and "not unit" in r.reason
    r = nav.on_goal(msgs.MoveGoal(goal_id="task-1", target_kind="pose"))
    assert not r.accepted and "reserved" in r.reason
    r = nav.on_goal(msgs.MoveGoal(goal_id="g", target_kind="pose", pose=msgs.Pose(position=msgs.Point(x=2.0))))
    assert r.accepted and nav.pending[-1].goal_id == "g" and nav.pending[-1].yaw is None


def test_navigator_is_a_lockstep_participant_at_its_rate() -> None:
    from hilsim.core import registry

    sc = load_scenario("rover")
    assert registry.lockstep_participants(sc) == {"controller": 5, "navigator": 25}
    assert registry.lockstep_participants(load_scenario("rover", {"navigator.rate_hz": 10})) == {
        "controller": 5, "navigator": 50}


def test_world_flag_picks_the_scenario_variant() -> None:
    from hilsim.launch.launcher import world_scenario

    assert world_scenario("rover", "indoor").endswith("config/rover.yaml")
    assert world_scenario("rover", "outdoor").endswith("config/rover-outdoor.yaml")
    with pytest.raises(ConfigError) as e:
        world_scenario("rover", "moon")
    assert str(e.value).startswith("--world moon: scenario rover has no such world (worlds: indoor, outdoor")
    outdoor = load_scenario(world_scenario("rover", "outdoor"))
    assert outdoor.world.model.name == "outdoor.xml" and "gps" in outdoor.sensors


def test_plan_evaluate_rover_goals(tmp_path: Path) -> None:
    from hilsim.cli import main

    goals = tmp_path / "goals.yaml"
    goals.write_text("targets: [[5.0, 2.5, 1.5708], [8.5, -1.2], [4.0, 2.4]]\ntarget_names: [corridor, room_b, wall]\n")
    csv_path = tmp_path / "eval.csv"
    rc = main(["plan", "evaluate", "--scenario", "rover", "--targets", str(goals), "--csv", str(csv_path)])
    assert rc == 1  # one goal is inside a wall
    rows = list(csv.reader(csv_path.open()))
    assert rows[0][:10] == ["goal", "x", "y", "yaw", "length_m", "smoothness_rad_per_m", "cusps", "planning_time_s",
                            "iterations", "chosen"]
    corridor, room_b, wall = rows[1:]
    assert float(corridor[4]) > math.hypot(5.0, 2.5) and float(room_b[4]) > 3.0  # longer than straight lines
    assert float(corridor[7]) > 0 and int(corridor[8]) > 0
    assert wall[4] == "" and "goal invalid" in wall[-1]
    assert sum(int(r[9]) for r in (corridor, room_b, wall)) == 1


@pytest.mark.serial
def test_bench_rover_laser_alone_counts_rays() -> None:
    """``hilsim bench rover``'s laser figure: the scenario's own sensor, 541 rays per scan."""
    from hilsim.tools.bench.rover import bench_laser

    r = bench_laser("indoor", scans=20)
    assert r["rays_per_scan"] == 541 and r["rays_per_s"] == pytest.approx(541 * r["scans_per_s"])
    assert r["rays_per_s"] > 1e4


def test_compose_rover_runs_the_navigator() -> None:
    """docker/compose-rover.yaml (generated from the rover scenario, issue 12) runs the navigator
    like any service, and physics waits for it."""
    import yaml

    from hilsim.cli import build_parser

    comp = yaml.safe_load((REPO / "docker" / "compose-rover.yaml").read_text())["services"]
    nav = comp["navigator"]
    assert not nav.get("profiles")  # not a hardware profile: part of the rover scenario itself
    cmd = [a.split(":-", 1)[1].rstrip("}") if a.startswith("${") else a for a in nav["command"]]
    assert cmd[0] == "--hold"  # python -m hilsim.launch.deploy --hold: `hilsim up … --only navigator`, held
    args = build_parser().parse_args(cmd[1:])
    assert args.cmd == "up" and args.only == "navigator"
    assert "navigator" in load_scenario(REPO / args.scenario).services
    assert "navigator" in comp["physics"]["depends_on"]


class _Sink:
    def __init__(self) -> None:
        self.got: list = []  # type: ignore[type-arg]

    def put(self, m: object) -> None:
        self.got.append(m)


def _odom(t_ns: int, x: float, y: float, yaw: float) -> msgs.Odometry:
    return msgs.Odometry(header=msgs.header(t_ns, "odom"), pose=msgs.PoseWithCovariance(pose=msgs.Pose(
        position=msgs.Point(x=x, y=y), orientation=msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)))))


def test_navigator_ticks_one_cmd_vel_each_and_replans_a_rover_off_its_path() -> None:
    """The service's decisions without transport: the task's first goal is planned at the first
    tick; every tick sends exactly one cmd_vel; odometry between ticks sends nothing; a rover 0.8 m
    off its path is planned again from where it is (and stands still that tick)."""
    from hilsim.services.navigator import NavigatorService

    nav = NavigatorService(load_scenario("rover", {"navigator.max_replans": 1}))
    for name in ("pub_cmd", "pub_map", "pub_plan", "pub_feedback", "pub_result", "pub_task_result"):
        setattr(nav, name, _Sink())
    nav.on_odom(_odom(0, 0.0, 0.0, 0.0), "k")
    assert nav.plans == 1 and nav.active is not None and nav.active.goal_id == "task-1"
    assert len(nav.pub_cmd.got) == 1 and len(nav.pub_map.got) == 1  # type: ignore[attr-defined]
    plan = nav.pub_plan.got[-1]  # type: ignore[attr-defined]
    assert plan.poses[-1].pose.position.x == pytest.approx(5.0) and plan.poses[-1].pose.position.y == pytest.approx(2.5)
    nav.on_odom(_odom(10_000_000, 0.0, 0.0, 0.0), "k")  # not a decision step (every 50 ms)
    assert len(nav.pub_cmd.got) == 1  # type: ignore[attr-defined]
    nav.on_odom(_odom(50_000_000, 0.0, 0.0, 0.0), "k")
    cmd = nav.pub_cmd.got[-1]  # type: ignore[attr-defined]
    assert len(nav.pub_cmd.got) == 2 and math.hypot(cmd.linear.x, cmd.linear.y) > 0  # type: ignore[attr-defined]
    nav.on_odom(_odom(100_000_000, 0.5, -0.8, 0.0), "k")  # pushed 0.8 m off the path
    assert nav.plans == 2 and nav.active.replans == 1
    assert nav.pub_cmd.got[-1] == msgs.Twist() and len(nav.pub_cmd.got) == 3  # type: ignore[attr-defined]
    assert nav.pub_plan.got[-1].poses[0].pose.position.y == pytest.approx(-0.8)  # type: ignore[attr-defined]
    nav.on_odom(_odom(150_000_000, 0.5, 0.8, 0.0), "k")  # off again: no replans left, it follows on
    assert nav.plans == 2 and nav.active is not None and nav.active.state == "executing"
