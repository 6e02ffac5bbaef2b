"""``hilsim plan evaluate`` for a mobile robot: every rover goal planned from the start, compared.

The shape of :mod:`hilsim.tools.planning_eval.arm` (the arm's Table III), with what matters for a base:
for each goal, planned in turn from the previous goal's pose (the scenario's start pose for the
first, as the task drives them) with the scenario's navigator settings, the table gives

- ``length`` — the path's length in the plane [m];
- ``smoothness`` — mean absolute heading change per metre [rad/m] (0 on a straight line);
- ``cusps`` — how often the path changes between forwards and backwards;
- ``planning_time`` — wall seconds of OMPL's planning and simplification, and its iterations.

The best goal minimises ``length``, ``smoothness``, or both normalised by their smallest value
(``weighted``). Goals: the scenario task's (``task.targets``) unless ``--targets FILE`` gives a
YAML ``targets: [[x, y(, yaw)], …]`` with optional ``target_names`` and ``start: [x, y, yaw]``.
The table goes to a CSV (default ``runs/<timestamp>-plan-evaluate/plan_evaluate.csv``).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilsim.core.config import ConfigError, Scenario
from hilsim.navigation.planner import PlanResult, directions, path_length, smoothness
from hilsim.tools.planning_eval.common import choose, execute, output_csv, read_targets


@dataclass
class GoalEvaluation:
    name: str
    goal: tuple[float, float, float | None]
    result: PlanResult

    @property
    def ok(self) -> bool:
        return self.result.path is not None

    @property
    def length(self) -> float:
        return path_length(self.result.path) if self.result.path is not None else math.nan

    @property
    def smoothness(self) -> float:
        return smoothness(self.result.path) if self.result.path is not None else math.nan

    @property
    def cusps(self) -> int:
        if self.result.path is None or len(self.result.path) < 3:
            return 0
        return int(np.count_nonzero(np.diff(directions(self.result.path))))


def load_goals(path: str | Path) -> tuple[list[str], list[tuple[float, float, float | None]],
                                          tuple[float, float, float] | None]:
    p = Path(path)
    names, targets, data = read_targets(p, what="goals", form="[x, y(, yaw)]", lengths=(2, 3),
                                        each="[x, y] or [x, y, yaw]", default_name="goal")
    goals = [(t[0], t[1], t[2] if len(t) == 3 else None) for t in targets]
    start = data.get("start")
    if start is not None and (not isinstance(start, list) or len(start) != 3):
        raise ConfigError(f"{p}: start: expected [x, y, yaw]")
    return names, goals, None if start is None else (float(start[0]), float(start[1]), float(start[2]))


def evaluate_goals(
    sc: Scenario,
    goals: list[tuple[float, float, float | None]],
    names: list[str],
    start: tuple[float, float, float] | None = None,
) -> list[GoalEvaluation]:
    """Plan every goal in turn (from the previous goal, or the start), with the navigator's settings."""
    import mujoco

    from hilsim.core.config import NavigatorConfig
    from hilsim.services.navigator import build, initial_pose

    cfg = NavigatorConfig.model_validate(sc.section("navigator"))
    _, planner = build(sc, cfg)
    here = start or initial_pose(mujoco.MjModel.from_xml_path(str(sc.world.model)))
    out = []
    for k, (name, (x, y, yaw)) in enumerate(zip(names, goals, strict=True)):
        gyaw = yaw if yaw is not None else math.atan2(y - here[1], x - here[0])
        res = planner.plan(here, (x, y, gyaw), max_iterations=cfg.iterations, time_limit=cfg.planning_time,
                           seed=sc.seed + k, attempts=cfg.attempts)
        out.append(GoalEvaluation(name, (x, y, yaw), res))
        if res.path is not None:
            here = (x, y, float(res.path[-1, 2]))
    return out


def format_table(evals: list[GoalEvaluation], best: int | None) -> str:
    rows = [f"{'goal':<12}{'x':>8}{'y':>8}{'yaw':>8}{'length m':>11}{'rad/m':>9}{'cusps':>7}"
            f"{'plan s':>9}{'iters':>8}  status"]
    for i, e in enumerate(evals):
        x, y, yaw = e.goal
        ys = f"{yaw:8.2f}" if yaw is not None else f"{'free':>8}"
        if e.ok:
            cells = f"{e.length:11.2f}{e.smoothness:9.3f}{e.cusps:7d}"
        else:
            cells = f"{'—':>11}{'—':>9}{'—':>7}"
        rows.append(f"{e.name + (' *' if i == best else ''):<12}{x:8.2f}{y:8.2f}{ys}{cells}"
                    f"{e.result.planning_time:9.3f}{e.result.iterations:8d}  {e.result.message}")
    return "\n".join(rows)


def write_csv(path: str | Path, evals: list[GoalEvaluation], best: int | None) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["goal", "x", "y", "yaw", "length_m", "smoothness_rad_per_m", "cusps", "planning_time_s",
                    "iterations", "chosen", "status"])
        for i, e in enumerate(evals):
            x, y, yaw = e.goal
            w.writerow([e.name, x, y, "" if yaw is None else yaw,
                        f"{e.length:.4f}" if e.ok else "", f"{e.smoothness:.5f}" if e.ok else "",
                        e.cusps if e.ok else "", f"{e.result.planning_time:.4f}", e.result.iterations,
                        int(i == best), e.result.message])


def cmd_evaluate_goals(sc: Scenario, args: argparse.Namespace) -> int:
    """``hilsim plan evaluate --scenario rover [--targets FILE]``."""
    from hilsim.services.navigator import rover_targets

    if args.targets:
        names, goals, start = load_goals(args.targets)
    else:
        goals, start = rover_targets(sc), None
        names = [f"task-{i + 1}" for i in range(len(goals))]
        if not goals:
            raise ConfigError(f"{sc.source}: task.targets is empty: give --targets FILE")
    evals = evaluate_goals(sc, goals, names, start)
    best = choose(evals, args.criterion)
    print(f"rover goals, planner {sc.section('navigator').get('planner', 'RRTConnect')}, criterion {args.criterion}")
    print(format_table(evals, best))
    csv_path = output_csv(sc, args.csv, args.out)
    write_csv(csv_path, evals, best)
    print(f"CSV: {csv_path}")
    if best is None:
        print("no goal could be planned", file=sys.stderr)
        return 1
    print(f"chosen: {evals[best].name}")
    if args.execute:
        return _execute(sc, evals[best])
    return 0 if all(e.ok for e in evals) else 1


def _execute(sc: Scenario, e: GoalEvaluation) -> int:
    """Send the chosen goal to the running rover's navigator and wait for its result."""
    from hilsim.core import msgs

    x, y, yaw = e.goal
    pose = msgs.Pose(position=msgs.Point(x=x, y=y))
    if yaw is not None:
        pose.orientation = msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    goal = msgs.MoveGoal(goal_id=f"evaluate-{e.name}", target_kind="pose", pose=pose, use_orientation=yaw is not None)
    return execute(sc, goal, 300.0, service="navigator")
