"""The planner library: planners chosen by name from ``config/planners.yaml`` or plug-ins.

Every planner implements :class:`Planner`: ``solve(problem) -> PlanOutcome`` on a
:class:`Problem` (arm model with collision checking, start, goal, budget). Four kinds exist:

- ``kind: ompl`` — an OMPL geometric planner by class name (``RRTstar``, ``InformedRRTstar``,
  ``RRTConnect``, ``BITstar``, ``SORRTstar``, ``AORRTC``, …); each YAML parameter ``foo_bar``
  is applied through the planner's ``setFooBar`` method;
- ``kind: improved_rrtstar`` — the paper's improved RRT* (:mod:`hilsim.planning.improved`);
- ``kind: auto`` — the learned planner choice (:mod:`hilsim.planning.choice`): per goal, the library
  planner its model predicts best for the criterion, the next best when that one fails;
- ``kind: plugin`` / any name not in the YAML — a factory registered in the Python entry-point
  group ``hilsim.planners``: ``factory(name: str, params: dict) -> Planner``. A package adds
  a planner with e.g. ``[project.entry-points."hilsim.planners"] my_rrt = "pkg.mod:make"``,
  without touching the service.

Budgets: with ``max_iterations`` set (lockstep mode), planners stop on an iteration count,
which is deterministic; ``time_limit`` is then only a wall-clock safety cap, reported when hit.
Without it they stop on wall time.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hilsim.core.config import CONFIG_DIR
from hilsim.planning.improved import ImprovedRRTStar
from hilsim.planning.problem import Budget, Planner, PlannerConfigError, PlanOutcome, Problem

ENTRY_POINT_GROUP = "hilsim.planners"
DEFAULT_LIBRARY = CONFIG_DIR / "planners.yaml"


class UnknownPlanner(LookupError):
    """A planner name that neither the library file nor an entry point provides."""


# ---------------------------------------------------------------------------------- OMPL
_ompl_seeded: int | None = None


def seed_ompl(seed: int) -> None:
    """Seed OMPL's global RNG once per process (OMPL cannot re-seed after sampling started),
    before any planner exists; the RNG of every planner created later derives from it."""
    global _ompl_seeded
    from ompl import util as ou

    if _ompl_seeded is None:
        ou.setLogLevel(ou.LOG_WARN)
        ou.RNG.setSeed(int(seed) & 0x7FFFFFFF or 1)
        _ompl_seeded = int(seed)


def reseed_ompl(seed: int) -> None:
    """Seed OMPL's global RNG for a run of its own in a forked child, even when the parent seeded it (and
    sampled) before: the planners created after this draw their seeds from ``seed``. Without it a child
    of such a parent would keep the parent's stream, and every seed would be one run."""
    global _ompl_seeded
    from ompl import util as ou

    level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)  # OMPL says that sampling had started: in the parent, not in this child
    ou.RNG.setSeed(int(seed) & 0x7FFFFFFF or 1)
    ou.setLogLevel(level)
    _ompl_seeded = int(seed)


def _setter_name(param: str) -> str:
    return "set" + "".join(p[:1].upper() + p[1:] for p in param.split("_"))


class OmplPlanner:
    """An OMPL geometric planner minimising path length, with the MuJoCo validity checker."""

    def __init__(self, name: str, cls_name: str, params: dict[str, Any] | None = None) -> None:
        from ompl import geometric as og

        if not hasattr(og, cls_name):
            avail = sorted(n for n in dir(og) if n[0].isupper() and n not in ("PathGeometric", "PathSimplifier"))
            raise PlannerConfigError(
                f"planner {name!r}: OMPL has no geometric planner {cls_name!r}; available: {avail}"
            )
        self.name = name
        self.cls_name = cls_name
        self.params = dict(params or {})
        self._cls = getattr(og, cls_name)
        for p in self.params:
            if not hasattr(self._cls, _setter_name(p)):
                raise PlannerConfigError(f"planner {name!r}: {cls_name} has no parameter {p!r} (no {_setter_name(p)})")

    def solve(self, pb: Problem) -> PlanOutcome:
        from ompl import base as ob

        seed_ompl(pb.seed)
        arm, n = pb.arm, pb.arm.n
        space = ob.RealVectorStateSpace(n)
        bounds = ob.RealVectorBounds(n)
        for i in range(n):
            bounds.setLow(i, float(arm.lower[i]))
            bounds.setHigh(i, float(arm.upper[i]))
        space.setBounds(bounds)
        si = ob.SpaceInformation(space)
        si.setStateValidityChecker(lambda s: arm.is_valid(np.fromiter((s[i] for i in range(n)), float, n)))
        si.setStateValidityCheckingResolution(pb.resolution / space.getMaximumExtent())
        si.setup()
        start, goal = space.allocState(), space.allocState()
        for i in range(n):
            start[i] = float(pb.start[i])
            goal[i] = float(pb.goal[i])
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(start, goal, 1e-4)
        pdef.setOptimizationObjective(ob.PathLengthOptimizationObjective(si))
        planner = self._cls(si)
        for p, v in self.params.items():
            getattr(planner, _setter_name(p))(v)
        planner.setProblemDefinition(pdef)
        planner.setup()
        budget = Budget(pb)
        chunk_end = [0]

        def stop() -> bool:
            # OMPL calls this once per iteration of its main loop: counting calls is a
            # deterministic termination condition.
            budget.iterations += 1
            if budget.cancelled():
                return True
            if budget.elapsed() >= budget.time_limit:
                budget.wall_cap_hit = budget.max_it is not None
                return True
            return budget.max_it is not None and budget.iterations >= chunk_end[0]

        # OMPL's RRT* reports its solution only when solve() returns, so with an iteration budget
        # we solve in chunks of max_iterations (the tree is kept) until a solution exists.
        status = None
        for _ in range(1 if budget.max_it is None else 4):
            chunk_end[0] = budget.iterations + (budget.max_it or 0)
            status = planner.solve(ob.PlannerTerminationCondition(stop))
            if pdef.hasExactSolution() or budget.elapsed() >= budget.time_limit or budget.cancelled():
                break
        elapsed = budget.elapsed()
        if not pdef.hasExactSolution():
            return PlanOutcome(None, f"{self.name}: {budget.why_failed()} ({status})", budget.iterations, elapsed,
                               budget.wall_cap_hit)
        path = pdef.getSolutionPath()
        pts = np.array([[path.getState(k)[i] for i in range(n)] for k in range(path.getStateCount())])
        if np.max(np.abs(pts[-1] - pb.goal)) > 0:
            pts = np.vstack([pts, pb.goal])  # within the 1e-4 goal threshold: end exactly on the goal
        pts[0] = pb.start
        return PlanOutcome(pts, "ok", budget.iterations, elapsed, budget.wall_cap_hit)


# ---------------------------------------------------------------------------------- library
Factory = Callable[[str, dict[str, Any]], Planner]


def plugin_factories() -> dict[str, importlib.metadata.EntryPoint]:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


class PlannerLibrary:
    """Planner specs from a YAML file (``planners:`` mapping) plus entry-point plug-ins."""

    def __init__(self, specs: dict[str, dict[str, Any]], settings: dict[str, Any] | None = None,
                 path: Path | None = None) -> None:
        self.specs = specs
        self.path = path or DEFAULT_LIBRARY  # paths in params (auto's model) are relative to it
        settings = settings or {}
        self.limits: dict[str, Any] = settings.get("limits") or {}
        try:
            self.iterations = int(settings.get("iterations", 1000))
            self.wall_cap_factor = float(settings.get("wall_cap_factor", 10.0))
            self.resolution = float(settings.get("resolution", 0.01))
        except (TypeError, ValueError) as e:
            raise PlannerConfigError(f"planner library: iterations / wall_cap_factor / resolution: {e}") from None
        if self.iterations < 1 or self.wall_cap_factor <= 0 or self.resolution <= 0:
            raise PlannerConfigError("planner library: iterations, wall_cap_factor and resolution must be positive")

    @classmethod
    def load(cls, path: str | Path | None = None) -> PlannerLibrary:
        p = Path(path) if path else DEFAULT_LIBRARY
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except (OSError, yaml.YAMLError) as e:
            raise PlannerConfigError(f"{p}: cannot read the planner library: {e}") from None
        specs = data.get("planners")
        if not isinstance(specs, dict) or not all(isinstance(v, dict) for v in specs.values()):
            raise PlannerConfigError(f"{p}: 'planners' must map names to {{kind, class, params}} entries")
        return cls(specs, data, p)

    def names(self) -> list[str]:
        return sorted(set(self.specs) | set(plugin_factories()))

    def create(self, name: str, overrides: dict[str, Any] | None = None, *, criterion: str | None = None) -> Planner:
        """The planner ``name``; ``criterion`` (length | smoothness | weighted, the scenario's
        ``planner.criterion``) is what ``auto`` chooses for (the others minimise their own cost)."""
        spec = self.specs.get(name)
        plugins = plugin_factories()
        if spec is None and name not in plugins:
            raise UnknownPlanner(f"unknown planner {name!r}; available: {', '.join(self.names())}")
        params = dict((spec or {}).get("params") or {})
        params.update(overrides or {})
        kind = (spec or {}).get("kind", "plugin")
        if kind == "ompl":
            return OmplPlanner(name, str(spec["class"]), params)
        if kind == "improved_rrtstar":
            first = params.get("first_path")
            if first is not None and (first == name or first not in self.specs):
                raise PlannerConfigError(f"{self.path}: planners.{name}.params.first_path: expected another "
                                         f"planner of the library, got {first!r}")
            return ImprovedRRTStar(name, params, self.create(str(first)).solve if first else None)
        if kind == "auto":
            from hilsim.planning.choice import AutoPlanner

            return AutoPlanner(name, params, self, criterion)
        if kind == "plugin":
            ep = plugins.get(str((spec or {}).get("entry_point", name)))
            if ep is None:
                raise UnknownPlanner(f"planner {name!r}: no entry point in group {ENTRY_POINT_GROUP!r}")
            try:
                factory = ep.load()
            except (ImportError, AttributeError) as e:
                raise PlannerConfigError(f"planner {name!r}: cannot load entry point {ep.value}: {e}") from None
            return factory(name, params)
        raise PlannerConfigError(f"planner {name!r}: unknown kind {kind!r} (ompl, improved_rrtstar, auto, plugin)")

    def joint_limits(self, n: int, model_velocity: np.ndarray | None = None,
                     joint_names: list[str] | None = None) -> tuple[np.ndarray, ...]:
        """Per-joint (velocity, acceleration, jerk) limits for trajectories, sized to the arm's ``n`` joints.

        Each of ``limits.velocity|acceleration|jerk`` in the library is a number (every joint), a list of
        ``n`` numbers, or a mapping from joint names to numbers (``default:`` for the joints it does not
        name; names of other robots' joints are ignored, so one library serves several arms). A joint
        the entry does not cover gets its default: the velocity from the model's own limit
        (``arm_joint_velocity_limit``, from the URDF) or 1 rad/s, the acceleration 2x and the jerk 10x
        the velocity (per second). The velocity is always capped by the model's own limit."""
        names = list(joint_names) if joint_names is not None else [f"joint_{i + 1}" for i in range(n)]
        base_v = np.array(model_velocity, float) if model_velocity is not None else np.ones(n)
        factors = {"velocity": 1.0, "acceleration": 2.0, "jerk": 10.0}

        def vec(key: str) -> np.ndarray:
            v = self.limits.get(key)
            default = base_v * factors[key]
            what = f"{self.path}: limits.{key}"
            if v is None:
                a = default
            elif isinstance(v, dict):
                d = v.get("default")
                a = np.array([float(v.get(j, d)) if v.get(j, d) is not None else default[i]
                              for i, j in enumerate(names)], dtype=float)
            elif isinstance(v, list):
                if len(v) != n:
                    raise PlannerConfigError(f"{what}: expected a number, {n} numbers (one per joint of "
                                             f"{', '.join(names)}) or a mapping joint: number, got {len(v)}")
                a = np.array(v, dtype=float)
            else:
                a = np.full(n, float(v))
            if a.shape != (n,) or not np.all(np.isfinite(a)) or np.any(a <= 0):
                raise PlannerConfigError(f"{what}: expected positive numbers, got {a.tolist()}")
            return a

        try:
            v, acc, jerk = vec("velocity"), vec("acceleration"), vec("jerk")
        except (TypeError, ValueError) as e:
            if isinstance(e, PlannerConfigError):
                raise
            raise PlannerConfigError(f"{self.path}: limits: expected numbers ({e})") from None
        if model_velocity is not None:
            v = np.minimum(v, model_velocity)
        return v, acc, jerk
