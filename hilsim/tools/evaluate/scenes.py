"""``hilsim plan evaluate --scenes FILE``: every query of a scenes file with every planner named, compared.

Planners (``--planners``, comma-separated): names of the library, ``auto`` (the learned choice,
:mod:`hilsim.planning.choice`, deciding for ``--criterion``) and ``oracle`` (for each query, the single
planner best on it, found by running them all: every planner of the library but ``auto`` then runs).
Each runs every query with seeds ``0 … --seeds−1``, each run in a fresh process
(:mod:`hilsim.planning.runs`), so ``auto``'s run on a query is the very run of the planner it picked.

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
from hilsim.planning.library import PlannerLibrary
from hilsim.planning.runs import BROKEN, RunContext, RunRecord, RunTask, run_all
from hilsim.planning.scenes import load_scenes
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
        s = scores([r.success for r in runs], [r.sum_P for r in runs], [r.sum_A for r in runs],
                   [r.checks for r in runs], criterion)
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
    run = list(dict.fromkeys([*(n for n in names if n != ORACLE), *(singles if ORACLE in names else [])]))
    scenes = load_scenes(args.scenes)
    for sname, s in scenes.items():
        arm = ArmModel(s.model, sc.planner.clearance)
        for qi, (a, b) in enumerate(s.queries):
            for what, q in (("start", a), ("goal", b)):
                if q.shape != (arm.n,):
                    raise ConfigError(f"{args.scenes}: scenes.{sname}.queries[{qi}].{what}: expected {arm.n} values")
                if (bad := arm.why_invalid(q)) is not None:
                    raise ConfigError(f"{args.scenes}: scenes.{sname}.queries[{qi}].{what}: {bad[1]}")
    ctx = RunContext(lib, {n: s.model for n, s in scenes.items()}, {n: s.queries for n, s in scenes.items()},
                     sc.planner.clearance, sc.planner.iterations, args.criterion, _warm(lib, run, args.criterion))
    tasks = [RunTask(sname, qi, p, seed) for sname, s in scenes.items() for qi in range(len(s.queries))
             for p in run for seed in range(args.seeds)]
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
    summary = summarise(records, names, [p for p in singles if p in run], args.criterion)
    n_q = sum(len(s.queries) for s in scenes.values())
    print(format_table(summary, args.criterion, n_q, args.seeds))
    out: dict[str, Any] = {"criterion": args.criterion, "planners": summary}
    auto = [n for n in names if lib.specs.get(n, {}).get("kind") == "auto"]
    if auto:
        dec = [r.decision_ms for r in records if r.planner in auto]
        out["decision_ms"] = {"mean": float(np.mean(dec)), "max": float(np.max(dec))} if dec else None
        model = lib.create(auto[0], criterion=args.criterion).model  # type: ignore[attr-defined]
        hp = model.manifest.get("test_scores", {}).get(args.criterion, {}).get("hyperplan_planner")
        out["hyperplan"] = hp
        if dec:
            print(f"auto's decision: mean {out['decision_ms']['mean']:.2f} ms, max {out['decision_ms']['max']:.2f} ms")
        if hp:
            print(f"hyperplan (the single planner best on the model's training scenes for {args.criterion}): {hp}")
    if args.json:
        print(json.dumps(out, sort_keys=False))
    failed = [r for r in records if r.message.startswith(BROKEN)]
    if failed:
        print(f"{len(failed)} runs broke: {failed[0].message}", file=sys.stderr)
        return 1
    return 0
