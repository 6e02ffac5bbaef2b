"""The learned planner choice: ``planner: auto`` picks, per goal, the library planner its model predicts best.

The model (scikit-learn's extremely randomised trees, one multi-output regressor) maps a query's features
(:mod:`hilsim.planning.features`) to, for every planner of the library it was trained on, the fraction
of seeds that succeed and the expected score (:mod:`hilsim.planning.scoring`) under each criterion.
It is trained by ``hilsim plan learn`` (:mod:`hilsim.tools.planning_eval.learn`) on a data set of runs and saved in
the repository as ``models/planner_choice/model.pkl`` with ``manifest.json`` (library versions, the data
set's hash, its scenes, the criteria, the scores on its own test split).

:class:`AutoPlanner` (``kind: auto`` in ``config/planners.yaml``) asks it per goal: the planners ranked
by predicted score for the scenario's criterion (``planner.criterion``), the first plans; when it fails
the next one, up to ``fallbacks`` more, each with the goal's seed and budget. Deterministic: the
features are collision checks, the forest a fixed function. Its outcome says what it picked and why
(``extra['choice']``: the ranking with predicted scores and success; the service puts it in the goal's
feedback and result).
"""

from __future__ import annotations

import functools
import hashlib
import json
import pickle
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from hilsim.core.config import MODELS_DIR
from hilsim.planning.collision import ArmModel
from hilsim.planning.features import FEATURES, FeatureModel
from hilsim.planning.problem import Planner, PlannerConfigError, PlanOutcome, Problem
from hilsim.planning.scoring import CONSTANTS, CRITERIA, DEFAULT_CRITERION, TIME_WEIGHT, check_criterion, scores


class PlannerLibrary(Protocol):
    """What the choice needs of :class:`hilsim.planning.library.PlannerLibrary` (which builds ``auto``
    from here: imported the other way round would be a circle)."""

    path: Path
    specs: dict[str, dict[str, Any]]

    def create(self, name: str, overrides: dict[str, Any] | None = None, *, criterion: str | None = None
               ) -> Planner: ...

MODEL_DIR = MODELS_DIR / "planner_choice"
MODEL_FILE = "model.pkl"
MANIFEST_FILE = "manifest.json"
DEFAULT_FALLBACK = "improved_rrtstar"  # auto's planner for an arm its model was not trained for
BOUND_MS = 5.0  # a decision's CPU (features and model) at the 99th percentile, at most
WARM_DECISIONS = 50  # decisions at start (random queries, a fixed seed) that measure whether the bound holds
# extremely randomised trees: chosen over random forests and other leaf sizes and feature fractions by
# a five-fold cross-validation over the training scenes (grouped by scene), the held-out scenes unseen
FOREST = {"n_estimators": 120, "min_samples_leaf": 1, "max_features": 1.0}


# ---------------------------------------------------------------------------------- the data, per query
@dataclass
class QueryTable:
    """One row per query: its features, and per planner its success rate and mean score per criterion."""

    keys: list[tuple[str, int]]  # (scene, query)
    X: np.ndarray  # queries × features
    success: np.ndarray  # queries × planners: fraction of seeds that succeeded
    score: dict[str, np.ndarray]  # criterion -> queries × planners: mean score over the seeds
    planners: list[str]

    def subset(self, rows: np.ndarray) -> QueryTable:
        return QueryTable([self.keys[i] for i in rows], self.X[rows], self.success[rows],
                          {c: s[rows] for c, s in self.score.items()}, self.planners)

    def targets(self) -> np.ndarray:
        """The forest's outputs: success per planner, then each criterion's scores per planner."""
        return np.hstack([self.success, *(self.score[c] for c in CRITERIA)])


def query_table(rows: Sequence[dict[str, Any]], planners: Sequence[str], time_weight: float = TIME_WEIGHT
                ) -> QueryTable:
    """The per-query table of a data set's rows (dicts of CSV strings or values). Every planner must have
    run on every query (with the same seeds): a query that lacks one is an error."""
    by_query: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for r in rows:
        if r["planner"] in planners:
            by_query.setdefault((str(r["scene"]), int(r["query"])), []).append(r)
    keys = sorted(by_query)
    P = len(planners)
    X = np.zeros((len(keys), len(FEATURES)))
    success = np.zeros((len(keys), P))
    score = {c: np.zeros((len(keys), P)) for c in CRITERIA}
    for i, k in enumerate(keys):
        runs = by_query[k]
        X[i] = [float(runs[0][f]) for f in FEATURES]
        idx = np.array([planners.index(r["planner"]) for r in runs])
        if set(idx.tolist()) != set(range(P)):
            missing = sorted(set(planners) - {r["planner"] for r in runs})
            raise ValueError(f"query {k[0]}#{k[1]}: no runs of {', '.join(missing)}")
        ok = np.array([int(r["success"]) for r in runs])
        sp, sa = (np.array([float(r[c]) for r in runs]) for c in ("sum_P", "sum_A"))
        checks = np.array([int(r["checks"]) for r in runs])
        names = [str(r["planner"]) for r in runs]
        for p in range(P):
            success[i, p] = ok[idx == p].mean()
        for c in CRITERIA:
            s = scores(ok, sp, sa, checks, c, time_weight, names)
            for p in range(P):
                score[c][i, p] = s[idx == p].mean()
    return QueryTable(keys, X, success, score, list(planners))


@dataclass
class Forest:
    """A trained forest as plain arrays (trees × nodes, padded): predicting needs NumPy only, no
    scikit-learn import (two seconds of CPU) and no per-tree Python call; loading is a few milliseconds.
    The same arithmetic as scikit-learn's trees: each feature cast to float32, ``x <= threshold`` goes left,
    the leaves' values averaged over the trees."""

    feature: np.ndarray  # int32, trees × nodes (leaves: 0)
    threshold: np.ndarray  # float64
    left: np.ndarray  # int32 (-1: a leaf)
    right: np.ndarray  # int32
    value: np.ndarray  # float64, trees × nodes × outputs
    depth: int

    @classmethod
    def from_sklearn(cls, forest: Any) -> Forest:
        trees = [e.tree_ for e in forest.estimators_]
        T, N = len(trees), max(t.node_count for t in trees)
        out = trees[0].value.shape[1]
        feature, left, right = (np.zeros((T, N), np.int32) for _ in range(3))
        left[:] = -1
        threshold = np.zeros((T, N))
        value = np.zeros((T, N, out))
        for k, t in enumerate(trees):
            n = t.node_count
            feature[k, :n] = np.maximum(t.feature, 0)
            threshold[k, :n] = t.threshold
            left[k, :n], right[k, :n] = t.children_left, t.children_right
            value[k, :n] = t.value[:, :, 0]
        return cls(feature, threshold, left, right, value, int(max(t.max_depth for t in trees)))

    def predict(self, x: np.ndarray) -> np.ndarray:
        xs = np.asarray(x, np.float32).astype(np.float64).ravel()
        rows = np.arange(self.feature.shape[0])
        node = np.zeros(len(rows), np.int64)
        for _ in range(self.depth):
            lft = self.left[rows, node]
            inner = lft >= 0
            if not inner.any():
                break
            go_left = xs[self.feature[rows, node]] <= self.threshold[rows, node]
            node = np.where(inner, np.where(go_left, lft, self.right[rows, node]), node)
        return self.value[rows, node].mean(axis=0)

    def arrays(self) -> dict[str, Any]:
        return {"feature": self.feature, "threshold": self.threshold, "left": self.left, "right": self.right,
                "value": self.value, "depth": self.depth}


def train_forest(table: QueryTable, seed: int) -> Any:
    from sklearn.ensemble import ExtraTreesRegressor

    forest = ExtraTreesRegressor(**FOREST, random_state=seed, n_jobs=1)
    forest.fit(table.X, table.targets())
    return forest


def choice_report(pred_scores: dict[str, np.ndarray], table: QueryTable, train: QueryTable | None = None
                  ) -> dict[str, dict[str, float]]:
    """Per criterion, the mean score over ``table``'s queries of: the choice (each query's predicted
    best planner, as run), every planner alone, the oracle (each query's best planner), and with
    ``train`` the single planner best on the training queries (HyperPlan's choice)."""
    out = {}
    for c in CRITERIA:
        s = table.score[c]
        pick = np.argmin(pred_scores[c], axis=1)
        row = {"auto": float(np.mean(s[np.arange(len(s)), pick])), "oracle": float(np.mean(s.min(axis=1)))}
        row.update({p: float(np.mean(s[:, j])) for j, p in enumerate(table.planners)})
        if train is not None:
            best = table.planners[int(np.argmin(train.score[c].mean(axis=0)))]
            row["hyperplan"] = row[best]
            row["hyperplan_planner"] = best  # type: ignore[assignment]
        out[c] = row
    return out


# ---------------------------------------------------------------------------------- the saved model
class ChoiceModelError(PlannerConfigError):
    """The model files are missing, unreadable or from another scikit-learn."""


@dataclass
class ChoiceModel:
    forest: Forest
    planners: list[str]
    features: list[str]
    manifest: dict[str, Any]

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(success per planner, {criterion: score per planner}) for one query's features."""
        y = self.forest.predict(x)
        P = len(self.planners)
        return y[:P], {c: y[P * (k + 1): P * (k + 2)] for k, c in enumerate(CRITERIA)}

    def save(self, directory: Path) -> tuple[Path, Path]:
        directory.mkdir(parents=True, exist_ok=True)
        # plain arrays, lists and strings: loading needs NumPy only
        blob = pickle.dumps({"forest": self.forest.arrays(), "planners": self.planners, "features": self.features},
                            protocol=5)
        model = directory / MODEL_FILE
        model.write_bytes(blob)
        manifest = dict(self.manifest, model_sha256=hashlib.sha256(blob).hexdigest())
        mpath = directory / MANIFEST_FILE
        mpath.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        return model, mpath


def library_versions() -> dict[str, str]:
    import importlib.metadata

    import mujoco
    import sklearn

    out = {"scikit-learn": sklearn.__version__, "numpy": np.__version__, "mujoco": mujoco.__version__}
    for dist in ("ompl", "hilsim"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = "?"
    return out


def load_model(directory: str | Path = MODEL_DIR) -> ChoiceModel:
    """The saved model (cached per directory: a service loads it once)."""
    return _load(str(Path(directory).resolve()))


@functools.lru_cache(maxsize=4)
def _load(directory: str) -> ChoiceModel:
    d = Path(directory)
    try:
        manifest = json.loads((d / MANIFEST_FILE).read_text())
        blob = (d / MODEL_FILE).read_bytes()
    except (OSError, ValueError) as e:
        raise ChoiceModelError(f"{d}: no planner-choice model ({e}); build it with `hilsim plan learn`") from None
    constants = (manifest.get("criterion") or {}).get("constants")
    if constants != CONSTANTS:
        raise ChoiceModelError(f"{d / MANIFEST_FILE}: criterion.constants: the model was trained under "
                               f"{constants}, hilsim.planning.scoring says {CONSTANTS}: retrain it "
                               "(`hilsim plan learn --train-only`)")
    if hashlib.sha256(blob).hexdigest() != manifest.get("model_sha256"):
        raise ChoiceModelError(f"{d / MODEL_FILE}: does not match model_sha256 of {MANIFEST_FILE}")
    data = pickle.loads(blob)  # the repository's own file, its hash checked against the manifest
    if list(data["features"]) != list(FEATURES):
        raise ChoiceModelError(f"{d / MODEL_FILE}: trained on other features than hilsim.planning.features "
                               "computes: rebuild it with `hilsim plan learn --train-only`")
    if not isinstance(data.get("forest"), dict):
        raise ChoiceModelError(f"{d / MODEL_FILE}: an older model format: rebuild it with "
                               "`hilsim plan learn --train-only`")
    return ChoiceModel(Forest(**data["forest"]), list(data["planners"]), list(data["features"]), manifest)


# ---------------------------------------------------------------------------------- the decision
@dataclass
class Decision:
    criterion: str
    ranking: list[str]  # best first
    score: dict[str, float]  # predicted score per planner
    success: dict[str, float]  # predicted success per planner
    seconds: float  # what deciding cost: CPU seconds of the deciding thread (features and model)

    def text(self, planned: str | None = None, tried: Sequence[str] = ()) -> str:
        """One line: the choice and why, e.g. ``auto (weighted): predicted score (success) aorrtc 1.08
        (100 %) < bitstar 1.12 (98 %) < …``; with the attempts that failed before ``planned``."""
        parts = [f"{p} {self.score[p]:.2f} ({100 * self.success[p]:.0f} %)" for p in self.ranking]
        # no measured time in it: the text goes into recorded messages, the same in every run of a seed
        head = f"auto ({self.criterion}): predicted score (success) "
        tail = ""
        if tried:
            tail = f"; {', '.join(tried)} failed, {planned or 'none'} {'planned' if planned else 'succeeded'}"
        return head + " < ".join(parts) + tail


def robot_signature(arm: ArmModel) -> dict[str, Any]:
    """What a model is trained for: the arm's joints and a hash of its kinematics (each joint's body place,
    orientation and axis, and the tool site), the same in every scene built around the same arm."""
    m = arm.model
    h = hashlib.sha256()
    for j in arm.joint_ids:
        b = int(m.jnt_bodyid[j])
        for v in (m.body_pos[b], m.body_quat[b], m.jnt_axis[j], m.jnt_pos[j]):
            h.update(np.round(np.asarray(v, float), 6).tobytes())
    tool = mujoco_site(arm, "tool")
    if tool >= 0:
        h.update(np.round(np.asarray(m.site_pos[tool], float), 6).tobytes())
    return {"joints": list(arm.joint_names), "kinematics_sha256": h.hexdigest()[:16]}


def mujoco_site(arm: ArmModel, name: str) -> int:
    import mujoco

    return int(mujoco.mj_name2id(arm.model, mujoco.mjtObj.mjOBJ_SITE, name))


_FEATURES: weakref.WeakKeyDictionary[ArmModel, FeatureModel] = weakref.WeakKeyDictionary()
# collision models decided for at start -> the 99th percentile of those decisions' CPU [ms]
_WARM: weakref.WeakKeyDictionary[ArmModel, float] = weakref.WeakKeyDictionary()


def feature_model(arm: ArmModel) -> FeatureModel:
    """The query features of ``arm``'s world, built once per collision model and kept with it (a model
    belongs to one thread, and so does its feature model: robots planning in threads of one process
    never share one)."""
    fm = _FEATURES.get(arm)
    if fm is None:
        fm = _FEATURES[arm] = FeatureModel(arm.path, arm.clearance, arm.joint_names)
    return fm


class AutoPlanner:
    """``kind: auto``: the model's pick for each query, then the next best while one fails."""

    def __init__(self, name: str, params: dict[str, Any], library: PlannerLibrary, criterion: str | None = None
                 ) -> None:
        unknown = set(params) - {"model", "fallbacks", "criterion", "fallback", "bound_ms"}
        if unknown:
            raise PlannerConfigError(f"planner {name!r}: unknown parameter(s) {sorted(unknown)}; "
                                     "expected model, fallbacks, criterion, fallback, bound_ms")
        self.name = name
        self.library = library
        model = Path(str(params.get("model", MODEL_DIR)))
        self.model_dir = model if model.is_absolute() else (library.path.parent / model).resolve()
        try:
            self.criterion = check_criterion(str(criterion or params.get("criterion", DEFAULT_CRITERION)))
            self.fallbacks = int(params.get("fallbacks", 2))
            self.bound_ms = float(params.get("bound_ms", BOUND_MS))
        except ValueError as e:
            raise PlannerConfigError(f"planner {name!r}: {e}") from None
        self.enforce_bound = False  # the service sets it in realtime mode (solve)
        self.model = load_model(self.model_dir)
        self.candidates = [p for p in self.model.planners if p in library.specs]
        if not self.candidates:
            raise PlannerConfigError(f"planner {name!r}: none of the model's planners {self.model.planners} "
                                     "is in the library")
        # the planner for an arm the model was not trained for (it says so, once per arm, and plans)
        self.fallback = str(params.get("fallback", DEFAULT_FALLBACK))
        if self.fallback not in library.specs or library.specs[self.fallback].get("kind") == "auto":
            raise PlannerConfigError(f"planner {name!r}: fallback {self.fallback!r} is not a planner of the library")
        # arm -> why the model does not fit it ("" = it fits)
        self._foreign: weakref.WeakKeyDictionary[ArmModel, str] = weakref.WeakKeyDictionary()

    def unfit(self, arm: ArmModel) -> str:
        """Why the model cannot choose for ``arm`` (trained for another robot), or "" when it can."""
        key = arm
        if key not in self._foreign:
            want = self.model.manifest.get("robot")
            have = robot_signature(arm)
            why = ""
            if not isinstance(want, dict):
                why = f"{self.model_dir / MANIFEST_FILE} names no robot it was trained for"
            elif want.get("joints") != have["joints"] or want.get("kinematics_sha256") != have["kinematics_sha256"]:
                why = (f"its model ({self.model_dir}) was trained for the arm with joints "
                       f"{', '.join(want.get('joints') or [])} ({want.get('model', '?')}), not "
                       f"{arm.path.name} ({', '.join(have['joints'])})")
            self._foreign[key] = why
        return self._foreign[key]

    def fallback_text(self, arm: ArmModel) -> str:
        return (f"planner auto: {self.unfit(arm)}: planning with {self.fallback}; retrain it for this arm with "
                "`hilsim plan learn --scenario FILE --out DIR` and name DIR in the library's auto params.model")

    def prepare(self, arm: ArmModel) -> None:
        """Before the first goal: build the world's feature model (its scene features take a few ms) and
        decide ``WARM_DECISIONS`` times on random queries (a fixed seed), so that the first real decision is
        as quick as the others (the first call of every code path costs more) and the 99th percentile of
        their CPU says whether the bound holds on this machine (:meth:`too_slow`). Once per collision model."""
        if arm in _WARM or self.unfit(arm):
            return
        rng = np.random.default_rng(0)
        lo, hi = arm.sampling_bounds()
        ms = [1e3 * self.decide(arm, rng.uniform(lo, hi), rng.uniform(lo, hi)).seconds
              for _ in range(WARM_DECISIONS)]
        _WARM[arm] = float(np.percentile(ms[1:], 99))

    def warm_p99_ms(self, arm: ArmModel) -> float | None:
        """The 99th percentile of the start's decisions (CPU ms), None before :meth:`prepare`."""
        return _WARM.get(arm)

    def too_slow(self, arm: ArmModel) -> bool:
        p99 = _WARM.get(arm)
        return p99 is not None and p99 > self.bound_ms

    def decide(self, arm: ArmModel, start: np.ndarray, goal: np.ndarray) -> Decision:
        fm = feature_model(arm)  # built once per collision model (prepare), not part of a decision
        t0 = time.thread_time()  # the CPU the decision costs, whatever else the machine runs
        x = fm.features(start, goal)
        success, score = self.model.predict(x)
        idx = {p: i for i, p in enumerate(self.model.planners)}
        s = {p: float(score[self.criterion][idx[p]]) for p in self.candidates}
        ok = {p: float(np.clip(success[idx[p]], 0.0, 1.0)) for p in self.candidates}
        ranking = sorted(self.candidates, key=lambda p: (s[p], p))
        return Decision(self.criterion, ranking, s, ok, time.thread_time() - t0)

    def solve(self, pb: Problem) -> PlanOutcome:
        """Decide and plan. ``enforce_bound`` (set by the service in realtime mode): when the start's decisions were
        over the bound on this machine, plan with the fallback planner instead (said, and counted). In
        lockstep mode sim time stands still while deciding, and a choice that depended on the machine's
        load would break determinism: a decision over the bound is only counted there
        (``extra['over_bound']``)."""
        slow = self.enforce_bound and self.too_slow(pb.arm)
        if self.unfit(pb.arm) or slow:  # never a choice for a robot the model has not seen: the default, said so
            why = self.fallback_text(pb.arm) if not slow else (
                f"planner auto: its decisions took {self.warm_p99_ms(pb.arm):.1f} ms CPU at the 99th percentile "
                f"at start, over its bound of {self.bound_ms:g} ms: planning with {self.fallback}")
            if pb.report is not None:
                pb.report(self.fallback, why)
            out = self.library.create(self.fallback).solve(pb)
            out.extra = dict(out.extra, planner=self.fallback, choice=why, auto_fallback="bound" if slow else "robot")
            return out
        decision = self.decide(pb.arm, pb.start, pb.goal)
        if pb.report is not None:
            pb.report(decision.ranking[0], decision.text())
        tried: list[str] = []
        iterations, elapsed, cap = 0, decision.seconds, False
        out = PlanOutcome(None, "auto: nothing tried")
        for name in decision.ranking[: 1 + max(0, self.fallbacks)]:
            out = self.library.create(name).solve(pb)
            iterations += out.iterations
            elapsed += out.planning_time
            cap = cap or out.wall_cap_hit
            if out.success or (pb.cancelled is not None and pb.cancelled()):
                break
            tried.append(name)
        planned = None if not out.success else (decision.ranking[len(tried)])
        extra = dict(out.extra, planner=planned or decision.ranking[0], choice=decision.text(planned, tried),
                     decision_s=decision.seconds, ranking=decision.ranking,
                     over_bound=1e3 * decision.seconds > self.bound_ms)
        msg = out.message if out.success else f"auto: {', '.join(tried)} failed ({out.message})"
        return PlanOutcome(out.path, msg, iterations, elapsed, cap, extra)
