"""``hilsim plan evaluate --scenes FILE``: every query of a scenes file with every planner named, compared.

Planners (``--planners``, comma-separated): names of the library, ``auto`` (the learned choice,
:mod:`hilsim.planning.choice`, deciding for ``--criterion``) and ``oracle`` (for each query, the single
planner best on it, found by running them all: every planner of the library but ``auto`` then runs).
Each runs every query with seeds ``0 … --seeds−1``, each run in a fresh process
(:mod:`hilsim.planning.experiments`), so ``auto``'s run on a query is the very run of the planner it picked.

Per planner: the success rate over its runs; the mean ΣP and ΣA of its successful runs (the paper's
P and A summed over the joints); the mean planning time (CPU seconds measured; ``auto``'s includes its
decision); and the score (:mod:`hilsim.planning.scoring`): each run's criterion cost divided by the best
run's on its query, plus planning time, a failure counted as ``FAIL_SCORE``; averaged over the seeds of
a query, then over the queries. The oracle's score on a query is the best planner's there. With
``--json`` the last line is ``{"criterion": …, "planners": {NAME: {"success_rate", "score", "mean_P",
"mean_A", "mean_time_s"}, …}, "hyperplan": …}``, ``hyperplan`` naming the single planner best on the
model's training scenes (HyperPlan's choice: one planner for the class of problems).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core.config import ConfigError, Scenario
from hilsim.planning.collision import ArmModel
from hilsim.planning.experiments import BROKEN, RunContext, RunRecord, RunTask, run_all
from hilsim.planning.library import PlannerLibrary
from hilsim.planning.scenes import Scene, load_scenes, query_sha256, world_sha256
from hilsim.planning.scoring import scores

ORACLE = "oracle"


def read_records(path: Path) -> list[RunRecord]:
    if not path.exists():
        return []
    types = {f.name: f.type for f in fields(RunRecord)}
    conv = {"int": int, "float": float, "str": str}
    with path.open(newline="") as f:
        return [RunRecord(**{k: conv[str(types[k])](v) for k, v in row.items() if k in types})
                for row in csv.DictReader(f)]


def write_records(path: Path, records: list[RunRecord]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, RunRecord.columns(), lineterminator="\n")
        w.writeheader()
        w.writerows(r.row() for r in records)


def append_record(path: Path, rec: RunRecord) -> None:
    with path.open("a", newline="") as f:
        csv.DictWriter(f, RunRecord.columns(), lineterminator="\n").writerow(rec.row())


def _warm(lib: PlannerLibrary, names: list[str], criterion: str) -> Any:
    """Load what choosers need (model, scene features) in the parent, once for every child."""
    planners = [lib.create(n, criterion=criterion) for n in names]
    preps = [p for p in planners if hasattr(p, "prepare")]
    return (lambda arm: [p.prepare(arm) for p in preps]) if preps else None


def summarise(records: list[RunRecord], names: list[str], singles: list[str], criterion: str
              ) -> dict[str, dict[str, float]]:
    """The figures per planner (see the module docstring); ``singles``: the planners the oracle picks from."""
    by_query: dict[tuple[str, int], list[RunRecord]] = {}
    for r in records:
        by_query.setdefault((r.scene, r.query), []).append(r)
    per: dict[str, dict[str, list[float]]] = {n: {"score": [], "ok": [], "P": [], "A": [], "t": []} for n in names}
    for runs in by_query.values():
        # planning time: the checks at the calibration of the planner that planned, plus a choice's decision
        s = scores([r.success for r in runs], [r.sum_P for r in runs], [r.sum_A for r in runs],
                   [r.checks for r in runs], criterion, planners=[r.used for r in runs],
                   extra_s=[r.decision_ms / 1e3 for r in runs])
        mean: dict[str, float] = {}
        for name in {r.planner for r in runs}:
            idx = [i for i, r in enumerate(runs) if r.planner == name]
            mean[name] = float(np.mean(s[idx]))
            if name in per:
                d = per[name]
                d["score"].append(mean[name])
                for i in idx:
                    r = runs[i]
                    d["ok"].append(r.success)
                    d["t"].append(r.cpu_s)
                    if r.success:
                        d["P"].append(r.sum_P)
                        d["A"].append(r.sum_A)
        if ORACLE in per:
            best = min((p for p in singles if p in mean), key=lambda p: (mean[p], p))
            d = per[ORACLE]
            d["score"].append(mean[best])
            for r in runs:
                if r.planner == best:
                    d["ok"].append(r.success)
                    d["t"].append(r.cpu_s)
                    if r.success:
                        d["P"].append(r.sum_P)
                        d["A"].append(r.sum_A)

    def avg(v: list[float]) -> float | None:
        return float(np.mean(v)) if v else None

    return {n: {"success_rate": avg(d["ok"]), "score": avg(d["score"]), "mean_P": avg(d["P"]),
                "mean_A": avg(d["A"]), "mean_time_s": avg(d["t"])} for n, d in per.items()}


def format_table(summary: dict[str, dict[str, Any]], criterion: str, queries: int, seeds: int) -> str:
    def f(v: Any, fmt: str) -> str:
        return "—" if v is None else format(v, fmt)

    lines = [f"{queries} queries x {seeds} seeds, criterion {criterion} (+ planning time); score: 1 = the best "
             "run on each query, smaller is better",
             f"{'planner':<18}{'success':>9}{'score':>8}{'mean ΣP':>10}{'mean ΣA':>10}{'time [s]':>10}"]
    for n, r in sorted(summary.items(), key=lambda kv: (kv[1]["score"] is None, kv[1]["score"] or 0.0)):
        sr = "—" if r["success_rate"] is None else f"{100 * r['success_rate']:.1f} %"
        lines.append(f"{n:<18}{sr:>9}{f(r['score'], '.3f'):>8}{f(r['mean_P'], '.3f'):>10}"
                     f"{f(r['mean_A'], '.3f'):>10}{f(r['mean_time_s'], '.3f'):>10}")
    return "\n".join(lines)


def overlap(scenes: dict[str, Scene], manifest: dict[str, Any]) -> tuple[list[str], int]:
    """(the scenes whose world, obstacles and all, is one the model was trained on; how many queries it was
    trained on) of a scenes file against the model's manifest. A world without obstacles (the table only)
    is new when its queries are."""
    trained = manifest.get("scenes") or {}
    worlds = {v.get("world_sha256") for v in trained.values() if v.get("kind") != "free"}
    queries = {(v.get("world_sha256"), q) for v in trained.values() for q in v.get("query_sha256") or []}
    same, n_q = [], 0
    for name, s in scenes.items():
        w = world_sha256(s.model)
        if w in worlds and s.kind != "free":
            same.append(name)
        n_q += sum((w, query_sha256(a, b)) in queries for a, b in s.queries)
    return same, n_q


def auto_records(ctx: RunContext, auto: Any, records: list[RunRecord], scenes: dict[str, Scene], seeds: int,
                 name: str) -> list[RunRecord]:
    """``auto``'s runs, from the runs of the planners it picks: its decision (made here, once per query, as a
    service makes it; its CPU measured), then per seed the run of its first pick, and of the next while
    one fails (up to its fallbacks). A run of a planner depends on its (query, planner, seed) only, so this
    is the run auto would make (tests/test_choice.py::test_auto_runs_are_the_runs_of_the_planner_it_picks)."""
    by = {(r.scene, r.query, r.planner, r.seed): r for r in records}
    out = []
    for sname, s in scenes.items():
        arm = ctx.arms[sname]
        auto.prepare(arm)
        for qi, (a, b) in enumerate(s.queries):
            d = auto.decide(arm, np.asarray(a, float), np.asarray(b, float))
            for seed in range(seeds):
                tried, checks, cpu, its = [], 0, d.seconds, 0
                rec = None
                for p in d.ranking[: 1 + max(0, auto.fallbacks)]:
                    rec = by[(sname, qi, p, seed)]
                    checks, cpu, its = checks + rec.checks, cpu + rec.cpu_s, its + rec.iterations
                    if rec.success:
                        break
                    tried.append(p)
                assert rec is not None
                planned = rec.planner if rec.success else None
                out.append(RunRecord(sname, qi, name, seed, rec.success, rec.sum_P, rec.sum_A, rec.duration_s,
                                     rec.waypoints, its, checks, planned or d.ranking[0],
                                     d.text(planned, tried), cpu, 1e3 * d.seconds))
    return out


def cmd_evaluate_scenes(sc: Scenario, args: argparse.Namespace) -> int:
    """``hilsim plan evaluate --scenes FILE [--planners NAMES] [--criterion C] [--seeds S] [--json]``."""
    if args.targets:
        raise ConfigError("hilsim plan evaluate: --scenes and --targets exclude each other")
    if args.seeds < 1:
        raise ConfigError("hilsim plan evaluate: --seeds must be at least 1")
    lib = PlannerLibrary.load(sc.planner.library)
    singles = [n for n, s in lib.specs.items() if s.get("kind") != "auto"]
    names = [n.strip() for n in args.planners.split(",") if n.strip()] if args.planners else \
        [*singles, *(n for n, s in lib.specs.items() if s.get("kind") == "auto"), ORACLE]
    for n in names:
        if n != ORACLE and n not in lib.names():
            raise ConfigError(f"--planners: unknown planner {n!r}; available: {', '.join([*lib.names(), ORACLE])}")
    # the oracle picks among the single planners named (all of the library's when none is)
    named = [n for n in names if n in singles]
    if named:
        singles = named
    run = list(dict.fromkeys([*(n for n in names if n != ORACLE), *(singles if ORACLE in names else [])]))
    scenes = load_scenes(args.scenes)
    autos = [n for n in names if lib.specs.get(n, {}).get("kind") == "auto"]
    if autos:
        model = lib.create(autos[0], criterion=args.criterion).model  # type: ignore[attr-defined]
        same, n_q = overlap(scenes, model.manifest)
        if same or n_q:
            what = (f"{args.scenes}: {len(same)} scenes ({', '.join(same[:3])}{', …' if len(same) > 3 else ''}) and "
                    f"{n_q} queries are in the training set of {lib.create(autos[0]).model_dir}: "  # type: ignore[attr-defined]
                    "not unseen")
            if getattr(args, "strict", False):
                raise ConfigError(what + " (--strict)")
            print(f"warning: {what}", file=sys.stderr)
    for sname, s in scenes.items():
        arm = ArmModel(s.model, sc.planner.clearance)
        for n in autos:  # a model never judged on an arm it was not trained for
            chooser = lib.create(n, criterion=args.criterion)
            if chooser.unfit(arm):  # type: ignore[attr-defined]
                raise ConfigError(f"{args.scenes}: scenes.{sname}: planner {n}: {chooser.unfit(arm)}: "  # type: ignore[attr-defined]
                                  "retrain it for this arm (`hilsim plan learn --scenario FILE --out DIR`)")
        for qi, (a, b) in enumerate(s.queries):
            for what, q in (("start", a), ("goal", b)):
                if q.shape != (arm.n,):
                    raise ConfigError(f"{args.scenes}: scenes.{sname}.queries[{qi}].{what}: expected {arm.n} values")
                if (bad := arm.why_invalid(q)) is not None:
                    raise ConfigError(f"{args.scenes}: scenes.{sname}.queries[{qi}].{what}: {bad[1]}")
    ctx = RunContext(lib, {n: s.model for n, s in scenes.items()}, {n: s.queries for n, s in scenes.items()},
                     sc.planner.clearance, sc.planner.iterations, args.criterion, _warm(lib, run, args.criterion))
    # auto's runs are its picks' runs (auto_records) when every planner it can pick runs anyway
    derived = [n for n in autos if set(lib.create(n).candidates) <= set(run)]  # type: ignore[attr-defined]
    tasks = [RunTask(sname, qi, p, seed) for sname, s in scenes.items() for qi in range(len(s.queries))
             for p in run if p not in derived for seed in range(args.seeds)]
    records: list[RunRecord] = []
    keep = None
    if getattr(args, "runs", None):
        # the library's planners' runs are deterministic: those already in the file are taken from it
        # (an interrupted evaluation goes on; auto's runs depend on its model and always run again)
        keep = Path(args.runs)
        chooser = {n for n in run if lib.specs.get(n, {}).get("kind") == "auto"}
        old = [r for r in read_records(keep) if r.planner not in chooser]
        wanted = {t.key for t in tasks}
        records = [r for r in old if (r.scene, r.query, r.planner, r.seed) in wanted]
        have = {(r.scene, r.query, r.planner, r.seed) for r in records}
        tasks = [t for t in tasks if t.key not in have]
        write_records(keep, old)
    jobs = args.jobs or os.cpu_count() or 1

    def on_record(rec: RunRecord) -> None:
        records.append(rec)
        if keep is not None:
            append_record(keep, rec)

    run_all(ctx, tasks, jobs, on_record, what="plan evaluate")
    for n in derived:
        records = [r for r in records if r.planner != n]
        records += auto_records(ctx, lib.create(n, criterion=args.criterion), records, scenes, args.seeds, n)
    summary = summarise(records, names, [p for p in singles if p in run], args.criterion)
    n_q = sum(len(s.queries) for s in scenes.values())
    print(format_table(summary, args.criterion, n_q, args.seeds))
    out: dict[str, Any] = {"criterion": args.criterion, "planners": summary}
    auto = [n for n in names if lib.specs.get(n, {}).get("kind") == "auto"]
    if auto:
        dec = [r.decision_ms for r in records if r.planner in auto and r.seed == 0]
        out["decision_ms"] = {"mean": float(np.mean(dec)), "p99": float(np.percentile(dec, 99)),
                              "max": float(np.max(dec))} if dec else None
        best_single = min((p for p in singles if p in summary and summary[p]["score"] is not None),
                          key=lambda p: summary[p]["score"], default=None)
        if best_single and ORACLE in summary and summary[ORACLE]["score"] is not None:
            b, o, a = summary[best_single]["score"], summary[ORACLE]["score"], summary[auto[0]]["score"]
            out["best_single"] = best_single
            out["gap_closed"] = (b - a) / (b - o) if b > o else None
        model = lib.create(auto[0], criterion=args.criterion).model  # type: ignore[attr-defined]
        hp = model.manifest.get("test_scores", {}).get(args.criterion, {}).get("hyperplan_planner")
        out["hyperplan"] = hp
        if dec:
            print(f"auto's decision: mean {out['decision_ms']['mean']:.2f} ms, p99 {out['decision_ms']['p99']:.2f} ms, "
                  f"max {out['decision_ms']['max']:.2f} ms CPU")
        if out.get("gap_closed") is not None:
            print(f"auto closes {100 * out['gap_closed']:.0f} % of the gap between the best single planner "
                  f"({out['best_single']}) and the oracle")
        if hp:
            print(f"hyperplan (the single planner best on the model's training scenes for {args.criterion}): {hp}")
    if args.json:
        print(json.dumps(out, sort_keys=False))
    failed = [r for r in records if r.message.startswith(BROKEN)]
    if failed:
        print(f"{len(failed)} runs broke: {failed[0].message}", file=sys.stderr)
        return 1
    return 0
