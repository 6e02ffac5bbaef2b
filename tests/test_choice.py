"""The learned planner choice (hilsim.planning.choice): the data set and model rebuild bit for bit and
resume, the choice beats a fixed planner on scenes it was not trained on (and does not with its
features shuffled), ``auto`` decides deterministically and falls back, ``plan evaluate --scenes``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from hilsim.cli import main
from hilsim.planning.choice import MODEL_DIR, choice_report, load_model, query_table, train_forest
from hilsim.planning.collision import ArmModel
from hilsim.planning.experiments import RunContext, RunRecord, RunTask, run_all
from hilsim.planning.library import PlannerLibrary
from hilsim.planning.problem import PlanOutcome, Problem
from hilsim.planning.scenes import SCENES, load_scenes
from hilsim.tools.planning_eval.learn import split_scenes
from hilsim.tools.planning_eval.scenes import ORACLE, summarise

TINY = ["--scenes", "1", "--queries", "1", "--seeds", "1", "--planners", "rrtconnect,bitstar", "--iterations", "300"]


def _built(out: Path) -> tuple[str, bytes, list[bytes]]:
    manifest = json.loads((out / "manifest.json").read_text())
    xmls = [p.read_bytes() for p in sorted((out / "scenes").glob("*.xml"))]
    return manifest["data"]["sha256_without_measured"], (out / "model.pkl").read_bytes(), xmls


def test_learn_rebuilds_bit_for_bit_and_resumes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Same seed: the same scenes, data set (but its measured times) and model, byte for byte, whatever
    the number of workers; an interrupted data set goes on where it stopped and ends the same."""
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["plan", "learn", "--out", str(a), "--jobs", "2", *TINY]) == 0
    assert main(["plan", "learn", "--out", str(b), "--jobs", "1", *TINY]) == 0
    assert _built(a) == _built(b)
    rows = (b / "data.csv").read_text().splitlines(keepends=True)
    assert len(rows) == 1 + 2 * 8  # 8 queries (the shipped 4 + 1 sampled in each of 3 scenes + 1 generated)
    (b / "data.csv").write_text("".join(rows[:-5]))  # stopped five runs short
    capsys.readouterr()
    assert main(["plan", "learn", "--out", str(b), "--jobs", "2", *TINY]) == 0
    assert "11 runs there already, 5 to go" in capsys.readouterr().err
    assert _built(a) == _built(b)


def _shipped_table() -> tuple[object, object, list[str]]:
    manifest = load_model().manifest
    with (MODEL_DIR / "data.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    table = query_table(rows, manifest["planners"])
    _, test_names = split_scenes(list(load_scenes(MODEL_DIR / "scenes.yaml")), manifest["seed"])
    is_test = np.array([k[0] in test_names for k in table.keys])
    return table.subset(np.flatnonzero(~is_test)), table.subset(np.flatnonzero(is_test)), manifest["planners"]


def _report(train: object, test: object, planners: list[str]) -> dict[str, dict[str, float]]:
    forest = train_forest(train, 0)  # type: ignore[arg-type]
    y = forest.predict(test.X)  # type: ignore[attr-defined]
    P = len(planners)
    pred = {c: y[:, P * (k + 1): P * (k + 2)] for k, c in enumerate(("length", "smoothness", "weighted"))}
    return choice_report(pred, test, train)  # type: ignore[arg-type]


def test_the_choice_beats_a_fixed_planner_on_scenes_it_never_saw() -> None:
    """Trained on the shipped data set's training scenes, the choice scores better on its test scenes
    than every single planner, even the one best on those test scenes, under every criterion; trained
    on features shuffled across the queries (the model then knows nothing of the query) it does not."""
    train, test, planners = _shipped_table()

    def gains(rep: dict[str, dict[str, float]]) -> dict[str, float]:
        """Per criterion: how much better than the best single planner on the test scenes."""
        return {c: min(r[p] for p in planners) - r["auto"] for c, r in rep.items()}

    rep = _report(train, test, planners)
    assert all(g > 0.02 for g in gains(rep).values()), rep
    shuffled = train.subset(np.arange(len(train.keys)))  # type: ignore[attr-defined]
    shuffled.X = shuffled.X[np.random.default_rng(0).permutation(len(shuffled.X))]
    blind = _report(shuffled, test, planners)
    assert not any(g > 0.02 for g in gains(blind).values()), blind


def test_auto_decides_deterministically_and_falls_back(monkeypatch: pytest.MonkeyPatch) -> None:
    lib = PlannerLibrary.load()
    auto = lib.create("auto", criterion="weighted")
    scene = load_scenes(SCENES)["table_obstacle"]
    arm = ArmModel(scene.model)
    start, goal = scene.queries[0]
    d1, d2 = auto.decide(arm, start, goal), auto.decide(arm, start, goal)  # type: ignore[attr-defined]
    assert d1.ranking == d2.ranking and d1.score == d2.score and sorted(d1.ranking) == sorted(auto.candidates)
    assert 0 < d1.seconds
    first, second = d1.ranking[:2]
    create = lib.create

    class Fails:
        name = first

        def solve(self, pb: Problem) -> PlanOutcome:
            return PlanOutcome(None, "no solution within 1 iterations", 1, 0.0)

    monkeypatch.setattr(lib, "create", lambda n, *a, **k: Fails() if n == first else create(n, *a, **k))
    told: list[tuple[str, str]] = []
    out = auto.solve(Problem(arm, start, goal, seed=3, max_iterations=300, time_limit=60.0,  # type: ignore[attr-defined]
                             report=lambda p, why: told.append((p, why))))
    assert out.success and out.extra["planner"] == second, out.extra
    assert out.extra["choice"].endswith(f"; {first} failed, {second} planned"), out.extra["choice"]
    assert told == [(first, d1.text())]


def test_evaluate_scenes_prints_the_figures_and_refuses_a_bad_query(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    scene = load_scenes(SCENES)["free"]
    f = tmp_path / "scenes.yaml"
    f.write_text(yaml.safe_dump({"scenes": {"free": {"model": str(scene.model), "queries": [
        {"start": scene.queries[0][0].tolist(), "goal": scene.queries[0][1].tolist()}]}}}))
    assert main(["plan", "evaluate", "--scenes", str(f), "--planners", "rrtconnect,bitstar", "--seeds", "2",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["criterion"] == "weighted" and set(out["planners"]) == {"rrtconnect", "bitstar"}
    for r in out["planners"].values():
        assert set(r) == {"success_rate", "score", "mean_P", "mean_A", "mean_time_s"} and r["success_rate"] == 1.0
    assert min(r["score"] for r in out["planners"].values()) >= 1.0
    # a goal inside the table: one line naming the file, the field and why
    data = yaml.safe_load(f.read_text())
    data["scenes"]["free"]["queries"][0]["goal"] = [0.0, -1.5, 0.0, 0.0, 0.0, 0.0]
    f.write_text(yaml.safe_dump(data))
    assert main(["plan", "evaluate", "--scenes", str(f), "--planners", "bitstar"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{f}: scenes.free.queries[0].goal: " in err, err


def test_the_oracle_is_each_querys_best_planner() -> None:
    def rec(q: int, p: str, seed: int, ok: int, length: float) -> RunRecord:
        return RunRecord("s", q, p, seed, ok, length, 1.0, 1.0, 2, 1, 0, p, "ok", 0.01)

    runs = [rec(0, "a", 0, 1, 1.0), rec(0, "a", 1, 1, 1.0), rec(0, "b", 0, 1, 2.0), rec(0, "b", 1, 0, 0.0),
            rec(1, "a", 0, 1, 3.0), rec(1, "a", 1, 1, 3.0), rec(1, "b", 0, 1, 1.5), rec(1, "b", 1, 1, 1.5)]
    s = summarise(runs, ["a", "b", ORACLE], ["a", "b"], "length")
    assert s["a"]["score"] == pytest.approx((1.0 + 2.0) / 2)  # query 1: 3.0 / 1.5
    assert s["b"]["score"] == pytest.approx(((2.0 + 3.0) / 2 + 1.0) / 2)  # query 0: 2.0 and a failure (3)
    assert s["b"]["success_rate"] == pytest.approx(3 / 4)
    assert s[ORACLE]["score"] == pytest.approx(1.0) and s[ORACLE]["success_rate"] == 1.0  # a, then b


def test_auto_runs_are_the_runs_of_the_planner_it_picks() -> None:
    """Same seed, same choice, same plan: auto's run in a fresh process twice, and the run of the
    planner it picked with that seed, are one and the same (but for the measured times)."""
    lib = PlannerLibrary.load()
    scene = load_scenes(SCENES)["table_obstacle"]
    ctx = RunContext(lib, {"t": scene.model}, {"t": scene.queries}, 0.005, 300, "length",
                     lambda arm: lib.create("auto", criterion="length").prepare(arm))  # type: ignore[attr-defined]
    recs: list[RunRecord] = []
    run_all(ctx, [RunTask("t", 0, "auto", 5), RunTask("t", 0, "auto", 5)], 2, recs.append)
    picked = recs[0].used
    run_all(ctx, [RunTask("t", 0, picked, 5)], 1, recs.append)

    def same(r: RunRecord) -> tuple[object, ...]:
        return (r.success, r.sum_P, r.sum_A, r.duration_s, r.waypoints, r.iterations, r.checks, r.used)

    assert recs[0].success and picked != "auto"
    assert same(recs[0]) == same(recs[1]) == same(recs[2]), recs
