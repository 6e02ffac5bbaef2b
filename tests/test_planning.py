"""Planning library: collision checking, planners by name and by entry point, trajectories, Table III metrics."""

from __future__ import annotations

import importlib.metadata
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.core.scenario import load_scenario
from hilsim.planning.collision import ArmModel
from hilsim.planning.ik import IKError, rpy_to_matrix, solve_ik
from hilsim.planning.library import PlannerConfigError, PlannerLibrary, PlanOutcome, Problem, UnknownPlanner
from hilsim.planning.objectives import path_length, summed_turning_angle, turning_angles
from hilsim.planning.trajectory import time_parameterize, to_msg
from hilsim.tools.planning_eval import arm as ev

REPO = Path(__file__).resolve().parent.parent
TABLETOP = REPO / "models" / "arm" / "tabletop.xml"
LEFT = np.array([0.866, -0.789, -0.399, 0.0, -0.382, 0.0])
RIGHT = np.array([-0.866, -0.789, -0.399, 0.0, -0.382, 0.0])


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(TABLETOP, 0.005)


def test_collision_limits_and_reasons(arm: ArmModel) -> None:
    assert arm.joint_names == [f"joint_{i}" for i in range(1, 7)]
    assert arm.is_valid(np.zeros(6)) and arm.is_valid(LEFT) and arm.is_valid(RIGHT)
    kind, why = arm.why_invalid((LEFT + RIGHT) / 2)
    assert kind == "collision" and "obstacle" in why
    kind, why = arm.why_invalid(np.array([4.0, 0, 0, 0, 0, 0]))
    assert kind == "limits" and "joint_1" in why
    assert not arm.motion_valid(LEFT, RIGHT, 0.01)
    # clearance: a configuration 3 mm from the obstacle is valid at 0 clearance, invalid at 5 mm
    tight = ArmModel(TABLETOP, 0.0)
    q = LEFT.copy()
    lo, hi = 0.0, 0.866
    for _ in range(40):  # bisect joint_1 towards the obstacle until just touching
        q[0] = (lo + hi) / 2
        lo, hi = (lo, q[0]) if tight.is_valid(q) else (q[0], hi)
    q[0] = hi + 0.004
    assert tight.is_valid(q) and not arm.is_valid(q)


@pytest.mark.parametrize("name", ["rrtstar", "improved_rrtstar", "rrtconnect", "informed_rrtstar"])
def test_planners_by_name_avoid_the_obstacle(arm: ArmModel, name: str) -> None:
    lib = PlannerLibrary.load()
    # OMPL's planners draw from one process-wide generator, so their runs depend on what ran
    # before in the process: a budget that solves this query whatever the draw
    res = lib.create(name).solve(Problem(arm, LEFT, RIGHT, seed=1, max_iterations=1000, time_limit=20))
    assert res.success, res.message
    assert np.allclose(res.path[0], LEFT) and np.allclose(res.path[-1], RIGHT)
    assert all(arm.motion_valid(a, b, 0.01) for a, b in zip(res.path[:-1], res.path[1:], strict=True))


def test_improved_rrtstar_is_deterministic_per_seed(arm: ArmModel) -> None:
    lib = PlannerLibrary.load()
    # the iterations decide, not the wall clock (Problem's 1 s cap stopped both seeds early on a loaded CI
    # machine: the same path from seeds 3 and 4); the planner service gives 20 s in lockstep
    runs = [lib.create("improved_rrtstar").solve(Problem(arm, LEFT, RIGHT, seed=s, max_iterations=150,
                                                         time_limit=60.0)) for s in (3, 3, 4)]
    assert np.array_equal(runs[0].path, runs[1].path)
    assert not np.array_equal(runs[0].path, runs[2].path)


def test_unknown_planner_lists_available() -> None:
    lib = PlannerLibrary.load()
    with pytest.raises(UnknownPlanner, match=r"available: .*improved_rrtstar.*rrtstar"):
        lib.create("warp_drive")
    with pytest.raises(PlannerConfigError, match="no parameter"):
        PlannerLibrary({"x": {"kind": "ompl", "class": "RRTstar", "params": {"warp": 1}}}).create("x")
    with pytest.raises(PlannerConfigError, match="no geometric planner"):
        PlannerLibrary({"x": {"kind": "ompl", "class": "Nope"}}).create("x")


class StraightLine:
    """Test plug-in: the straight joint line if it is free, else no solution."""

    def __init__(self, name: str, params: dict[str, Any]) -> None:
        self.name = name
        self.params = params

    def solve(self, pb: Problem) -> PlanOutcome:
        if pb.arm.motion_valid(pb.start, pb.goal, pb.resolution):
            return PlanOutcome(np.array([pb.start, pb.goal]), "ok", 1)
        return PlanOutcome(None, "straight line blocked", 1)


def make_straight(name: str, params: dict[str, Any]) -> StraightLine:
    return StraightLine(name, params)


def test_entry_point_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, arm: ArmModel) -> None:
    """A planner registered in the hilsim.planners entry-point group by an installed distribution."""
    dist = tmp_path / "straight_planner-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: straight-planner\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[hilsim.planners]\nstraight = test_planning:make_straight\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(sys.modules, "test_planning", sys.modules[__name__])
    importlib.invalidate_caches()
    lib = PlannerLibrary.load()
    assert "straight" in lib.names()
    p = lib.create("straight")
    assert isinstance(p, StraightLine)
    assert p.solve(Problem(arm, np.zeros(6), LEFT)).success
    assert not p.solve(Problem(arm, LEFT, RIGHT)).success


def test_trajectory_respects_limits_and_stays_on_path() -> None:
    path = np.array([[0.0] * 6, [0.5, 0.2, 0, 0, 0, 0], [0.5, 0.2, 0.6, 0.1, 0, 0]])
    v, a, j = np.full(6, 1.0), np.full(6, 2.0), np.full(6, 10.0)
    tr = time_parameterize(path, v, a, j, dt=0.01)
    assert np.all(np.abs(tr.qd) <= v + 1e-9) and np.all(np.abs(tr.qdd) <= a + 1e-9)
    jerk = np.diff(tr.qdd, axis=0) / np.diff(tr.t)[:, None]
    assert np.all(np.abs(jerk) <= j * 1.05 + 1e-6)
    assert np.max(np.diff(tr.t)) <= 0.01 + 1e-9
    assert np.allclose(tr.q[0], path[0]) and np.allclose(tr.q[-1], path[-1]) and np.allclose(tr.qd[-1], 0)
    # every sample lies on one of the two straight segments
    for q in tr.q:
        on1 = np.allclose(q[2:], 0) and np.isclose(q[1], 0.4 * q[0])
        on2 = np.allclose(q[:2], [0.5, 0.2]) and np.isclose(q[3], q[2] / 6)
        assert on1 or on2
    assert len(tr.knots) == 3
    msg = to_msg(tr, [f"joint_{i}" for i in range(1, 7)], 1_000_000_000)
    assert msg.header.stamp.sec == 1 and len(msg.points) == len(tr.t)


def test_turning_angle_and_length() -> None:
    p = np.array([[0, 0], [1, 0], [1, 1], [1, 2]], float)
    assert path_length(p) == pytest.approx(3.0)
    assert turning_angles(p) == pytest.approx([np.pi / 2, 0.0])
    assert summed_turning_angle(p) == pytest.approx(np.pi / 2)


def test_table_iii_metrics_known_answers() -> None:
    # joint 0 goes 0 → 1 → 0.5 (P = 1.5); joint 1 stays (P = 0)
    q = np.array([[0.0, 2.0], [1.0, 2.0], [0.5, 2.0]])
    assert ev.joint_path_lengths(q) == pytest.approx([1.5, 0.0])
    # accelerations 1, -1, 1, -1 → variance 1; constant 3 → variance 0
    qdd = np.array([[1.0, 3.0], [-1.0, 3.0], [1.0, 3.0], [-1.0, 3.0]])
    assert ev.acceleration_variance(qdd) == pytest.approx([1.0, 0.0])
    mk = ev.Evaluation
    evals = [
        mk("short", np.zeros(2), True, "ok", P=np.array([1.0, 1.0]), A=np.array([2.0, 2.0])),
        mk("smooth", np.zeros(2), True, "ok", P=np.array([1.5, 1.5]), A=np.array([0.5, 0.5])),
        mk("failed", np.zeros(2), False, "no"),
    ]
    assert ev.choose(evals, "length") == 0
    assert ev.choose(evals, "smoothness") == 1
    assert ev.choose(evals, "weighted") == 1  # 0.5·1.5 + 0.5·1 = 1.25 < 0.5·1 + 0.5·4 = 2.5


def test_evaluate_targets_file(tmp_path: Path) -> None:
    sc = load_scenario("arm", {"planner.planner": "improved_rrtstar"})
    names, targets, start = ev.load_targets(REPO / "models" / "arm" / "targets.yaml", 6)
    assert names == ["left", "right", "over"] and start is not None
    lib = PlannerLibrary.load()
    lib.iterations = 150
    evals = ev.evaluate(sc, targets, names, start, library=lib)
    assert all(e.ok for e in evals)
    best = ev.choose(evals, "length")
    table = ev.format_table(evals, [f"joint_{i}" for i in range(1, 7)], best)
    assert "left" in table and "*" in table
    ev.write_csv(tmp_path / "t.csv", evals, [f"joint_{i}" for i in range(1, 7)], best)
    assert len((tmp_path / "t.csv").read_text().splitlines()) == 1 + 3 * 6


def test_plan_evaluate_writes_into_its_own_run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hilsim import cli

    monkeypatch.setattr("hilsim.planning.quiet_ompl_at_exit", lambda: None)  # pytest's own exit keeps stderr
    monkeypatch.chdir(tmp_path)
    targets = tmp_path / "targets.yaml"
    over = [0.0, -0.167, 0.031, 0.0, -1.435, 0.0]
    targets.write_text(f"start: [0, 0, 0, 0, 0, 0]\ntarget_names: [over]\ntargets: [{over}]\n")
    assert cli.main(["plan", "evaluate", "--targets", str(targets)]) == 0
    (run,) = (tmp_path / "runs").glob("*-plan-evaluate")
    assert sorted(p.name for p in run.iterdir()) == ["plan_evaluate.csv", "plan_evaluate.rrd"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs", "targets.yaml"]  # nothing in the working dir
    # an explicit --csv is taken as it is (the recording goes next to it), --out names the directory
    sc = load_scenario("arm")
    assert ev.output_csv(sc, "a/t.csv", None) == Path("a/t.csv") and (tmp_path / "a").is_dir()
    assert ev.output_csv(sc, None, "b") == Path("b/plan_evaluate.csv") and (tmp_path / "b").is_dir()


def test_ik_reaches_pose_with_orientation(arm: ArmModel) -> None:
    down = rpy_to_matrix(0.0, np.pi / 2, 0.0)
    q = solve_ik(arm, np.array([0.17, -0.2, 0.08]), down, np.zeros(6))
    pos, rot = arm.site_pose(q)
    assert np.allclose(pos, [0.17, -0.2, 0.08], atol=1e-3) and np.allclose(rot, down, atol=1e-2)
    assert arm.is_valid(q)
    with pytest.raises(IKError):
        solve_ik(arm, np.array([1.5, 0.0, 0.2]), restarts=2)


@pytest.mark.serial
def test_bench_reports_against_baseline() -> None:
    from hilsim.planning import bench

    scenes = bench.load_scenes()
    assert set(scenes) == {"free", "table_obstacle", "narrow_passage"}
    lib = PlannerLibrary.load()
    lib.iterations = 100
    one = {"table_obstacle": scenes["table_obstacle"]}
    rep = bench.run_bench(1, ("rrtstar", "improved_rrtstar"), scenes=one, library=lib, equal_time=True)
    rows = {r["planner"]: r for r in rep["results"]}
    assert rows["rrtstar"]["runs"] == 1 and rows["improved_rrtstar"]["runs"] == 1
    if rows["rrtstar"]["success_rate"]:
        assert rows["rrtstar"]["turn_vs_rrtstar"] == pytest.approx(1.0)
    assert rows["rrtstar"]["iteration_time_vs_rrtstar"] == pytest.approx(1.0)
    assert rows["improved_rrtstar"]["median_iteration_us"] > 0
    # equal wall time: every planner got the time RRT* took, and no iteration budget
    same = {r["planner"]: r for r in rep["equal_time"]["results"]}
    assert {r["wall_budget_s"] for r in same.values()} == {rows["rrtstar"]["median_time_s"]}
    assert all(r["iterations_per_query"] is None for r in same.values())
    text = bench.format_report(rep)
    assert "| table_obstacle | improved_rrtstar | 100 it |" in text and "Equal wall time" in text


def test_stop_on_segment_brakes_on_the_checked_segment() -> None:
    from hilsim.planning.trajectory import stop_on_segment, time_parameterize

    path = np.array([[0.0] * 6, [1.0, 0.5, 0, 0, 0, 0], [1.0, 0.5, 0.8, 0, 0, 0]])
    vmax, amax, jmax = np.full(6, 1.0), np.full(6, 2.0), np.full(6, 10.0)
    traj = time_parameterize(path, vmax, amax, jmax)
    t = float(traj.knots[1]) * 0.4  # mid first segment, moving fast
    k = int(np.searchsorted(traj.t, t))
    stop = stop_on_segment(traj, t, vmax, amax, jmax)
    # starts where the arm is, with its velocity; ends at rest well before the waypoint
    assert np.allclose(stop.q[0], traj.q[k]) and np.allclose(stop.qd[0], traj.qd[k])
    assert np.allclose(stop.qd[-1], 0.0)
    assert stop.duration < traj.knots[1] - t
    # every sample lies on the first segment, beyond the start point, and limits hold
    u = path[1] / np.linalg.norm(path[1])
    for q in stop.q:
        assert np.allclose(q, u * (q @ u), atol=1e-9)
    assert np.all(np.abs(stop.qd) <= vmax + 1e-9) and np.all(np.abs(stop.qdd) <= amax + 1e-6)
    # right before a waypoint, braking would overshoot: it stops at the waypoint instead
    late = stop_on_segment(traj, float(traj.knots[1]) - 0.02, vmax, amax, jmax)
    assert np.allclose(late.q[-1], path[1])


def test_improved_rrtstar_beats_rrtstar_on_the_obstacle_scene() -> None:
    """The bench's headline, at a small budget: around the obstacle the improved RRT* turns far
    less than OMPL's RRT* and is not markedly longer (medians over three seeds, same iteration
    budget; OMPL's runs depend on its process-wide generator, hence the 10 % on length)."""
    from hilsim.planning import bench
    from hilsim.planning.library import reseed_ompl

    # OMPL's generator seeded here: without it the result depended on which tests ran before in the same
    # worker (CI: RRT*'s median 3.60 rad, the improved 4.01, over the 10 %); with seeds 1-6 all pass
    reseed_ompl(1)
    lib = PlannerLibrary.load()
    lib.iterations = 300
    one = {"table_obstacle": bench.load_scenes()["table_obstacle"]}
    rows = {r["planner"]: r for r in bench.run_bench(3, ("rrtstar", "improved_rrtstar"), scenes=one,
                                                      library=lib)["results"]}
    imp, base = rows["improved_rrtstar"], rows["rrtstar"]
    assert imp["success_rate"] == 1.0 and base["success_rate"] > 0, rows
    assert imp["median_turn_rad"] < 0.8 * base["median_turn_rad"], (imp, base)
    assert imp["median_length_rad"] <= 1.1 * base["median_length_rad"], (imp, base)
