"""Several targets, the best one (the paper's Table III): ``hilsim plan evaluate`` for an arm.

For each target the scenario's planner plans from the start configuration, the path is timed
with ruckig (:mod:`hilsim.planning.trajectory`), and per joint ``i``:

- ``P_i = Σ_j |p_i^{j+1} − p_i^j|`` — path length of the joint over the timed samples (rad);
- ``A_i = D(a_i)`` — the variance of the joint's acceleration along the timed trajectory.

The best target minimises ``Σ_i P_i`` (``length``), ``Σ_i A_i`` (``smoothness``), or a weighted
sum of both, each normalised by its smallest value over the targets (``weighted``, weights ``W_LENGTH`` of
:mod:`hilsim.planning.scoring`).
The table goes to a CSV and the chosen plan to a Rerun recording next to it, by default in a new
``runs/<timestamp>-plan-evaluate/``; the plan can be executed on a running system.

Targets file (YAML): ``targets: [[q1..q6], …]``, optional ``target_names`` and ``start``
(or ``home``), e.g. ``models/arm/targets.yaml``.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilsim.core.config import ConfigError, Scenario
from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlannerLibrary, Problem
from hilsim.planning.trajectory import (
    TimedTrajectory,
    acceleration_variance,
    joint_path_lengths,
    time_parameterize,
)
from hilsim.tools.planning_eval.common import choose, execute, output_csv, read_targets


@dataclass
class Evaluation:
    name: str
    target: np.ndarray
    ok: bool
    message: str
    path: np.ndarray | None = None
    traj: TimedTrajectory | None = None
    P: np.ndarray | None = None  # per joint
    A: np.ndarray | None = None  # per joint

    @property
    def length(self) -> float:
        """Σ_i P_i, what ``length`` minimises."""
        return float(np.sum(self.P))

    @property
    def smoothness(self) -> float:
        """Σ_i A_i, what ``smoothness`` minimises."""
        return float(np.sum(self.A))


def load_targets(path: str | Path, n: int) -> tuple[list[str], list[np.ndarray], np.ndarray | None]:
    names, targets, data = read_targets(path, what="targets", form=f"[q1 … q{n}]", lengths=(n,),
                                        each=f"{n} numbers", default_name="target")
    start = data.get("start", data.get("home"))
    return names, [np.array(t, float) for t in targets], None if start is None else np.array(start, float)


def evaluate(
    sc: Scenario,
    targets: list[np.ndarray],
    names: list[str],
    start: np.ndarray,
    library: PlannerLibrary | None = None,
    planner: str | None = None,
) -> list[Evaluation]:
    lib = library or PlannerLibrary.load(sc.planner.library)
    arm = ArmModel(sc.world.model, sc.planner.clearance)
    vmax, amax, jmax = lib.joint_limits(arm.n, arm.velocity_limits(), arm.joint_names)
    name = planner or sc.planner.planner
    out = []
    for k, (nm, q) in enumerate(zip(names, targets, strict=True)):
        bad = arm.why_invalid(q)
        if bad is not None:
            out.append(Evaluation(nm, q, False, f"target rejected: {bad[1]}"))
            continue
        pb = Problem(arm, start, q, seed=sc.seed + k, max_iterations=lib.iterations,
                     time_limit=sc.planner.planning_time * lib.wall_cap_factor, resolution=lib.resolution)
        res = lib.create(name, criterion=sc.planner.criterion).solve(pb)
        if res.path is None:
            out.append(Evaluation(nm, q, False, res.message))
            continue
        traj = time_parameterize(res.path, vmax, amax, jmax, dt=0.01)
        P, A = joint_path_lengths(traj.q), acceleration_variance(traj.qdd)
        out.append(Evaluation(nm, q, True, "ok", res.path, traj, P, A))
    return out


def format_table(evals: list[Evaluation], joint_names: list[str], best: int | None) -> str:
    head = f"{'joint':<10}" + "".join(f"{e.name + (' *' if i == best else ''):>22}" for i, e in enumerate(evals))
    sub = f"{'':<10}" + "".join(f"{'P [rad]':>11}{'A':>11}" for _ in evals)
    rows = [head, sub]
    for j, jn in enumerate(joint_names):
        cells = "".join(f"{e.P[j]:>11.3f}{e.A[j]:>11.4f}" if e.ok else f"{'—':>11}{'—':>11}" for e in evals)
        rows.append(f"{jn:<10}{cells}")
    rows.append(f"{'sum':<10}" + "".join(
        f"{np.sum(e.P):>11.3f}{np.sum(e.A):>11.4f}" if e.ok else f"{'failed':>22}" for e in evals))
    rows.append(f"{'duration':<10}" + "".join(f"{e.traj.duration:>20.2f} s" if e.ok else f"{'':>22}" for e in evals))
    return "\n".join(rows)


def write_csv(path: str | Path, evals: list[Evaluation], joint_names: list[str], best: int | None) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["target", "joint", "P", "A", "duration_s", "chosen", "status"])
        for i, e in enumerate(evals):
            for j, jn in enumerate(joint_names):
                w.writerow([e.name, jn, f"{e.P[j]:.6f}" if e.ok else "", f"{e.A[j]:.6f}" if e.ok else "",
                            f"{e.traj.duration:.3f}" if e.ok else "", int(i == best), e.message])


def log_rerun(path: Path, e: Evaluation, joint_names: list[str]) -> None:
    """The chosen plan as a Rerun recording: per-joint position / velocity / acceleration over time."""
    from hilsim.core.recording import disable_analytics

    disable_analytics()
    import rerun as rr

    rec = rr.RecordingStream("hilsim_plan_evaluate")
    rec.save(str(path))
    assert e.traj is not None
    times = rr.TimeColumn("time", duration=e.traj.t)
    for j, jn in enumerate(joint_names):
        for what, arr in (("position", e.traj.q), ("velocity", e.traj.qd), ("acceleration", e.traj.qdd)):
            cols = rr.Scalars.columns(scalars=arr[:, j])
            rec.send_columns(f"plan/{e.name}/{jn}/{what}", indexes=[times], columns=cols)
    rec.flush()


def cmd_evaluate_targets(sc: Scenario, args: argparse.Namespace) -> int:
    """``hilsim plan evaluate [--scenario arm] --targets FILE``."""
    if not args.targets:
        raise ConfigError("hilsim plan evaluate: --targets FILE is required for an arm scenario")
    arm = ArmModel(sc.world.model, sc.planner.clearance)
    names, targets, start = load_targets(args.targets, arm.n)
    start = np.zeros(arm.n) if start is None else start
    evals = evaluate(sc, targets, names, start)
    best = choose(evals, args.criterion)
    print(f"planner {sc.planner.planner}, start {np.round(start, 3).tolist()}, criterion {args.criterion}")
    print(format_table(evals, arm.joint_names, best))
    for e in evals:
        if not e.ok:
            print(f"{e.name}: {e.message}")
    csv_path = output_csv(sc, args.csv, args.out)
    write_csv(csv_path, evals, arm.joint_names, best)
    print(f"CSV: {csv_path}")
    if best is None:
        print("no target could be planned", file=sys.stderr)
        return 1
    rrd = csv_path.with_suffix(".rrd")
    log_rerun(rrd, evals[best], arm.joint_names)
    print(f"chosen: {evals[best].name} (Rerun recording {rrd})")
    if args.execute:
        return _execute(sc, evals[best])
    return 0


def _execute(sc: Scenario, e: Evaluation) -> int:
    from hilsim.core import msgs

    goal = msgs.MoveGoal(goal_id=f"evaluate-{e.name}", joint_positions=[float(x) for x in e.target])
    return execute(sc, goal, sc.task.target_timeout + 60.0, service="planner")
