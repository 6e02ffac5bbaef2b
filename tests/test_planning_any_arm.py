"""Planning for an arm that is not the built-in one: the UR5 of example-robot-data (a real third-party URDF,
built into a world by tests/thirdparty_arms.py), with ±2π joints and a continuous wrist."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilsim.core.config import REPO_ROOT
from hilsim.planning.collision import ArmModel
from hilsim.planning.improved import ImprovedRRTStar
from hilsim.planning.library import PlannerLibrary
from hilsim.planning.problem import PlannerConfigError, Problem
from hilsim.planning.scenes import sample_queries
from tests.thirdparty_arms import erd_root, ur5_world

needs_erd = pytest.mark.skipif(erd_root() is None,
                               reason="example-robot-data is not unpacked (tests/thirdparty_arms.py)")


@pytest.fixture(scope="module")
def ur5(tmp_path_factory: pytest.TempPathFactory) -> ArmModel:
    return ArmModel(ur5_world(tmp_path_factory.mktemp("ur5")), 0.005)


def test_limits_are_sized_to_the_arm_and_default_to_the_models() -> None:
    lib = PlannerLibrary.load()
    # the built-in arm: its own values, by joint name
    v, a, j = lib.joint_limits(6, np.full(6, 2.0), [f"joint_{i}" for i in range(1, 7)])
    assert v.tolist() == [1.0, 1.0, 1.0, 1.5, 1.5, 1.5] and a.tolist() == [2.0, 2.0, 2.0, 3.0, 3.0, 3.0]
    assert j.tolist() == [10.0, 10.0, 10.0, 15.0, 15.0, 15.0]
    # nine joints of another arm: the model's velocity limits, acceleration 2x, jerk 10x
    names = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]
    model_v = np.array([2.175] * 4 + [2.61] * 3 + [0.2, 0.2])
    v, a, j = lib.joint_limits(9, model_v, names)
    assert np.allclose(v, model_v) and np.allclose(a, 2 * model_v) and np.allclose(j, 10 * model_v)
    # a number for all, a list of the wrong length refused naming the file and the joints
    lib.limits = {"velocity": 0.5, "acceleration": [1.0] * 8}
    with pytest.raises(PlannerConfigError, match=r"planners.yaml: limits.acceleration: expected a number, 9 numbers"):
        lib.joint_limits(9, model_v, names)
    lib.limits = {"velocity": 0.5, "jerk": {"default": 7.0, "panda_joint1": 3.0}}
    v, a, j = lib.joint_limits(9, model_v, names)
    assert np.allclose(v, np.minimum(0.5, model_v)) and j[0] == 3.0 and np.all(j[1:] == 7.0)


@needs_erd
def test_collision_messages_name_the_links_of_unnamed_geoms(tmp_path: Path) -> None:
    arm = ArmModel(ur5_world(tmp_path, name_geoms=False), 0.005)
    assert all(arm.model.geom(g).name == "" for g in range(arm.model.ngeom) if arm.model.geom_bodyid[g] != 0)
    kind, why = arm.why_invalid(np.zeros(6))  # the UR5 at zero lies in the table
    assert kind == "collision" and "table" in why and "wrist_3_link" in why, why
    assert why.split(" ")[0] and "  " not in why


@needs_erd
def test_continuous_joints_plan_within_a_turn_either_way(ur5: ArmModel) -> None:
    i = ur5.joint_names.index("wrist_3_joint")
    assert ur5.continuous[i] and ur5.lower[i] == -2 * np.pi and ur5.upper[i] == 2 * np.pi
    lo, hi = ur5.sampling_bounds()  # one turn about home for the joints that turn more
    assert np.all(hi - lo <= 2 * np.pi + 1e-9) and np.all(lo <= ur5.home()) and np.all(ur5.home() <= hi)


@needs_erd
def test_the_default_planner_solves_the_ur5_where_improved_rrtstar_alone_does_not(ur5: ArmModel) -> None:
    """Query 3 of these: the improved RRT* alone finds no path in 4 budgets; the library's entry (a first path
    by RRT-Connect, then improved) solves every query, with a collision-free path from start to goal."""
    lib = PlannerLibrary.load()
    queries = sample_queries(ur5, 4, np.random.default_rng(3))
    start, goal = queries[3]
    alone = ImprovedRRTStar("alone", {k: v for k, v in lib.specs["improved_rrtstar"]["params"].items()
                                      if k != "first_path"})
    out = alone.solve(Problem(ur5, start, goal, seed=3, max_iterations=1000, time_limit=600))
    assert not out.success
    for k, (start, goal) in enumerate(queries):
        out = lib.create("improved_rrtstar").solve(Problem(ur5, start, goal, seed=k, max_iterations=1000,
                                                           time_limit=600))
        assert out.success, out.message
        assert np.array_equal(out.path[0], start) and np.array_equal(out.path[-1], goal)
        assert all(ur5.motion_valid(a, b, 0.01) for a, b in zip(out.path[:-1], out.path[1:], strict=True))
        if k == 3:
            assert out.extra.get("first_path") == "rrtconnect" and "first path by rrtconnect" in out.message


@needs_erd
def test_auto_on_an_arm_its_model_does_not_know_says_so_and_plans_with_the_default(ur5: ArmModel) -> None:
    lib = PlannerLibrary.load()
    auto = lib.create("auto")
    niryo = ArmModel(REPO_ROOT / "models" / "arm" / "tabletop.xml")
    assert auto.unfit(niryo) == ""  # the model's own arm
    why = auto.fallback_text(ur5)
    assert "\n" not in why and "joint_1" in why and "shoulder_pan_joint" in why and "hilsim plan learn" in why
    reports: list[tuple[str, str]] = []
    start, goal = sample_queries(ur5, 1, np.random.default_rng(5))[0]
    out = auto.solve(Problem(ur5, start, goal, seed=0, max_iterations=1000, time_limit=600,
                             report=lambda p, w: reports.append((p, w))))
    assert out.success and out.extra["auto_fallback"] == "robot" and out.extra["planner"] == "improved_rrtstar"
    assert reports == [("improved_rrtstar", why)]


@needs_erd
def test_a_lab_retrains_the_choice_for_its_arm_by_one_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                               ) -> None:
    """`hilsim plan learn --scenario FILE --out DIR` on the UR5: scenes of its world sized to its reach, a model
    whose manifest names the UR5; a library naming that model lets auto choose for the UR5, and `plan
    evaluate --scenario` runs it there."""
    import json

    import yaml

    from hilsim.cli import main

    world = ur5_world(tmp_path)
    scenario = tmp_path / "ur5.yaml"
    lib = tmp_path / "planners.yaml"
    out = tmp_path / "choice"
    data = yaml.safe_load((REPO_ROOT / "config" / "planners.yaml").read_text())
    data["planners"]["auto"]["params"]["model"] = str(out)
    lib.write_text(yaml.safe_dump(data))
    scenario.write_text(yaml.safe_dump({
        "name": "ur5", "robot": "ur5", "services": ["physics", "sensors", "controller", "planner"],
        "world": {"model": world.name}, "controller": {"gains": {"default": {"kp": 100.0, "ki": 0.0, "kd": 10.0}}},
        "planner": {"planner": "improved_rrtstar", "library": lib.name}}))
    # the built-in arm's model directory is not another arm's
    assert main(["plan", "learn", "--scenario", str(scenario), "--seeds", "1"]) == 2
    assert "another arm's goes into its own directory" in capsys.readouterr().err
    assert main(["plan", "learn", "--scenario", str(scenario), "--out", str(out), "--scenes", "2", "--queries", "2",
                 "--seeds", "1", "--planners", "rrtconnect,bitstar", "--iterations", "300", "--jobs", "2"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["robot"]["joints"][0] == "shoulder_pan_joint" and "--scenario" in manifest["command"]
    assert all(s["kind"] != "shipped" for s in manifest["scenes"].values())  # the built-in arm's scenes: not here
    auto = PlannerLibrary.load(lib).create("auto")
    assert auto.unfit(ArmModel(world)) == ""
    capsys.readouterr()
    assert main(["plan", "evaluate", "--scenario", str(scenario), "--scenes", str(out / "scenes.yaml"),
                 "--planners", "rrtconnect,bitstar,auto,oracle", "--seeds", "1", "--jobs", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["planners"]["auto"]["success_rate"] == 1.0


@needs_erd
def test_evaluating_auto_on_an_arm_its_model_does_not_know_is_refused_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    from hilsim.cli import main

    world = ur5_world(tmp_path)
    scenario = tmp_path / "ur5.yaml"
    scenario.write_text(yaml.safe_dump({
        "name": "ur5", "robot": "ur5", "services": ["physics", "sensors", "controller", "planner"],
        "world": {"model": world.name}, "controller": {"gains": {"default": {"kp": 100.0, "ki": 0.0, "kd": 10.0}}},
        "planner": {"planner": "improved_rrtstar"}}))
    assert main(["plan", "scenes", "--scenario", str(scenario), "--out", str(tmp_path / "s"), "--count", "1",
                 "--queries", "1"]) == 0
    capsys.readouterr()
    assert main(["plan", "evaluate", "--scenario", str(scenario), "--scenes", str(tmp_path / "s" / "scenes.yaml"),
                 "--planners", "rrtconnect,auto"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "planner auto: its model" in err and "shoulder_pan_joint" in err, err
