"""``hilsim bench plan``: every planner on the shipped scenes, beside plain OMPL RRT* in the same run.

Scenes are in ``config/scenes/scenes.yaml`` (free space, the table with its obstacle, a narrow
passage); each has start/goal queries. Every planner solves every query once per seed with the
same deterministic iteration budget (``iterations`` of ``config/planners.yaml``). Reported per
scene and planner: success rate, median planning time, median path length and median summed
turning angle of the successful paths, time per iteration, and the last three as ratios to
RRT* (the baseline). Then the same again at equal wall time: each query gets the time RRT*
needed on its scene (``--no-equal-time`` skips this pass).

Seeds: the improved RRT* draws from a generator seeded per run; OMPL planners share OMPL's
process-wide generator (seeded once), so their runs differ by their position in the sequence.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core.config import CONFIG_DIR, ConfigError
from hilsim.planning import scenes as scenes_file
from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlannerLibrary, Problem
from hilsim.planning.objectives import path_length, summed_turning_angle

SCENES = CONFIG_DIR / "scenes" / "scenes.yaml"
BASELINE = "rrtstar"
PLANNERS = ("rrtstar", "improved_rrtstar", "informed_rrtstar", "rrtconnect")


def load_scenes(path: Path = SCENES) -> dict[str, dict[str, Any]]:
    """The scenes of a scenes file (:func:`hilsim.planning.scenes.load_scenes`), as the bench takes them."""
    return {name: {"model": s.model, "queries": s.queries} for name, s in scenes_file.load_scenes(path).items()}


def run_bench(
    seeds: int,
    planners: tuple[str, ...] = PLANNERS,
    clearance: float = 0.005,
    time_cap: float = 30.0,
    scenes: dict[str, dict[str, Any]] | None = None,
    library: PlannerLibrary | None = None,
    equal_time: bool = False,
) -> dict[str, Any]:
    """Every planner with the library's iteration budget; with ``equal_time`` then again, each
    query given the wall time RRT* took for it (its median per scene), iterations unbounded —
    planners judged on the same time budget, not only the same iteration count."""
    lib = library or PlannerLibrary.load()
    scenes = scenes or load_scenes()
    rep = _run(seeds, planners, clearance, scenes, lib, {s: None for s in scenes}, time_cap)
    rep.update({"seeds": seeds, "iterations": lib.iterations, "baseline": BASELINE})
    if equal_time:
        budget = {r["scene"]: r["median_time_s"] for r in rep["results"] if r["planner"] == BASELINE}
        rep["equal_time"] = _run(seeds, planners, clearance, scenes, lib, budget, time_cap)
    return rep


def _run(seeds: int, planners: tuple[str, ...], clearance: float, scenes: dict[str, dict[str, Any]],
         lib: PlannerLibrary, wall: dict[str, float | None], time_cap: float) -> dict[str, Any]:
    """One pass; ``wall[scene]``: None = the iteration budget, else that many seconds per query."""
    rows = []
    for sname, scene in scenes.items():
        arm = ArmModel(scene["model"], clearance)
        for q_start, q_goal in scene["queries"]:
            for bad in (arm.why_invalid(q_start), arm.why_invalid(q_goal)):
                if bad is not None:
                    raise ConfigError(f"scene {sname}: a query is invalid: {bad[1]}")
        for pname in planners:
            times, per_it, lengths, turns, ok, runs = [], [], [], [], 0, 0
            for seed in range(seeds):
                for qi, (q_start, q_goal) in enumerate(scene["queries"]):
                    w = wall[sname]
                    pb = Problem(arm, q_start, q_goal, seed=1000 * seed + qi,
                                 max_iterations=lib.iterations if w is None else None,
                                 time_limit=time_cap if w is None else w, resolution=lib.resolution)
                    res = lib.create(pname).solve(pb)
                    runs += 1
                    times.append(res.planning_time)
                    per_it.append(res.planning_time / max(res.iterations, 1))
                    if res.path is not None:
                        ok += 1
                        lengths.append(path_length(res.path))
                        turns.append(summed_turning_angle(res.path))
            rows.append({
                "scene": sname,
                "planner": pname,
                "runs": runs,
                "success_rate": ok / runs,
                "median_time_s": statistics.median(times),
                "median_iteration_us": 1e6 * statistics.median(per_it),
                "iterations_per_query": lib.iterations if wall[sname] is None else None,
                "wall_budget_s": wall[sname],
                "median_length_rad": statistics.median(lengths) if lengths else None,
                "median_turn_rad": statistics.median(turns) if turns else None,
            })
    base = {r["scene"]: r for r in rows if r["planner"] == BASELINE}
    for r in rows:
        b = base.get(r["scene"])
        for key, out in (("median_length_rad", "length_vs_rrtstar"), ("median_turn_rad", "turn_vs_rrtstar"),
                         ("median_iteration_us", "iteration_time_vs_rrtstar")):
            ok = b is not None and r[key] is not None and b[key]
            r[out] = r[key] / b[key] if ok else None
    return {"results": rows}


def format_report(rep: dict[str, Any]) -> str:
    def f(v: Any, fmt: str) -> str:
        return "—" if v is None else format(v, fmt)

    def table(rows: list[dict[str, Any]], budget: str) -> list[str]:
        out = [
            f"| scene | planner | {budget} | success | median time [s] | time per iteration [µs] "
            "| median length [rad] | median turn [rad] | iteration time / RRT* | length / RRT* | turn / RRT* |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            b = f"{r['iterations_per_query']} it" if r["wall_budget_s"] is None else f"{r['wall_budget_s']:.3f} s"
            out.append(
                f"| {r['scene']} | {r['planner']} | {b} | {100 * r['success_rate']:.0f} % "
                f"| {f(r['median_time_s'], '.3f')} | {f(r['median_iteration_us'], '.0f')} "
                f"| {f(r['median_length_rad'], '.2f')} | {f(r['median_turn_rad'], '.2f')} "
                f"| {f(r['iteration_time_vs_rrtstar'], '.2f')} | {f(r['length_vs_rrtstar'], '.2f')} "
                f"| {f(r['turn_vs_rrtstar'], '.2f')} |"
            )
        return out

    lines = [f"seeds {rep['seeds']}, budget {rep['iterations']} iterations per query, baseline {rep['baseline']}", ""]
    lines += table(rep["results"], "budget")
    if "equal_time" in rep:
        lines += ["", "Equal wall time: each query gets the median time RRT* took on its scene above, "
                  "iterations unbounded.", ""]
        lines += table(rep["equal_time"]["results"], "budget")
    return "\n".join(lines)


def bench_choice(scenes: Path | None = None, repeat: int = 5, scenario: str = "arm") -> dict[str, Any]:
    """``planner: auto``: what loading its model costs, and what a decision costs (CPU of the deciding thread:
    features and model) on every query of ``scenes`` (default: the held-out ones), ``repeat`` times each, after
    the warm-up decision a service makes at its start; the 99th percentile against the bound."""
    import time

    from hilsim.core.config import MODELS_DIR
    from hilsim.core.scenario import load_scenario

    sc = load_scenario(scenario)
    lib = PlannerLibrary.load(sc.planner.library)
    autos = [n for n, spec in lib.specs.items() if spec.get("kind") == "auto"]
    if not autos:
        raise ConfigError(f"{lib.path}: no planner of kind auto")
    t0, c0 = time.perf_counter(), time.process_time()
    auto = lib.create(autos[0])
    load_wall, load_cpu = time.perf_counter() - t0, time.process_time() - c0
    path = scenes or MODELS_DIR / "planner_choice" / "heldout" / "scenes.yaml"
    ms = []
    for s in scenes_file.load_scenes(path).values():
        arm = ArmModel(s.model, sc.planner.clearance)
        if auto.unfit(arm):  # type: ignore[attr-defined]
            raise ConfigError(f"{path}: {auto.fallback_text(arm)}")  # type: ignore[attr-defined]
        auto.prepare(arm)  # type: ignore[attr-defined]
        for _ in range(repeat):
            for a, b in s.queries:
                ms.append(1e3 * auto.decide(arm, a, b).seconds)  # type: ignore[attr-defined]
    bound = float(auto.bound_ms)  # type: ignore[attr-defined]
    p99 = float(np.percentile(ms, 99))
    return {"scenes": str(path), "decisions": len(ms), "decision_ms_median": float(np.median(ms)),
            "decision_ms_p95": float(np.percentile(ms, 95)), "decision_ms_p99": p99,
            "decision_ms_max": float(np.max(ms)), "bound_ms": bound, "within_bound": p99 <= bound,
            "load_ms_wall": 1e3 * load_wall, "load_ms_cpu": 1e3 * load_cpu}


def cmd_choice(args: argparse.Namespace) -> int:
    """``hilsim bench choice``: exit 1 when the decision's 99th percentile is over its bound."""
    from hilsim.planning import quiet_ompl_at_exit

    quiet_ompl_at_exit()
    rep = bench_choice(Path(args.scenes) if getattr(args, "scenes", None) else None, getattr(args, "repeat", 5),
                       getattr(args, "scenario", None) or "arm")
    print(json.dumps(rep, indent=2) if args.json else (
        f"planner: auto: model loaded in {rep['load_ms_wall']:.1f} ms ({rep['load_ms_cpu']:.1f} ms CPU); "
        f"{rep['decisions']} decisions on {rep['scenes']}: median {rep['decision_ms_median']:.2f} ms, "
        f"p95 {rep['decision_ms_p95']:.2f} ms, p99 {rep['decision_ms_p99']:.2f} ms, max {rep['decision_ms_max']:.2f} "
        f"ms CPU; bound {rep['bound_ms']:g} ms: {'held' if rep['within_bound'] else 'NOT held'}"))
    return 0 if rep["within_bound"] else 1


def cmd_bench(args: argparse.Namespace) -> int:
    from hilsim.planning import quiet_ompl_at_exit

    quiet_ompl_at_exit()
    if getattr(args, "choice", False):
        args.scenes, args.repeat = None, 5
        return cmd_choice(args)
    if args.seeds < 1:
        print("hilsim bench plan: --seeds must be at least 1")
        return 2
    scenes = load_scenes(Path(args.scenes)) if getattr(args, "scenes", None) else None
    library, clearance = None, 0.005
    if getattr(args, "scenario", None):
        from hilsim.core.scenario import load_scenario

        sc = load_scenario(args.scenario)
        library, clearance = PlannerLibrary.load(sc.planner.library), sc.planner.clearance
        if scenes is None and Path(sc.world.model).resolve() != (CONFIG_DIR.parent / "models" / "arm" /
                                                                  "tabletop.xml").resolve():
            raise ConfigError(f"hilsim bench plan --scenario {args.scenario}: the shipped scenes hold the built-in "
                              "arm: give --scenes (e.g. from `hilsim plan scenes --scenario ...`)")
    rep = run_bench(args.seeds, clearance=clearance, scenes=scenes, library=library,
                    equal_time=not args.no_equal_time)
    print(json.dumps(rep, indent=2) if args.json else format_report(rep))
    return 0
