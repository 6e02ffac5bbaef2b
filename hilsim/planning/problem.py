"""What every planner shares: the :class:`Problem` it solves, the :class:`PlanOutcome` it returns,
the :class:`Planner` protocol, the iteration / wall-time :class:`Budget`, and the configuration error.

:mod:`hilsim.planning.library` (which builds planners by name) and the planners themselves
(:mod:`hilsim.planning.improved`, plug-ins) import from here, not from each other.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hilsim.planning.collision import ArmModel


class PlannerConfigError(ValueError):
    """A library entry that cannot be built (unknown class, unknown parameter)."""


@dataclass
class Problem:
    arm: ArmModel
    start: np.ndarray
    goal: np.ndarray
    seed: int = 0
    max_iterations: int | None = None  # deterministic budget; None = stop on wall time
    time_limit: float = 1.0  # wall seconds (a safety cap when max_iterations is set)
    resolution: float = 0.01  # rad between collision checks along a motion
    # asked between iterations: True ends the search at once (a goal canceled while planning)
    cancelled: Callable[[], bool] | None = None
    # told (planner, why) by a planner that chooses another (auto) once it has chosen, before it plans
    report: Callable[[str, str], None] | None = None


@dataclass
class PlanOutcome:
    path: np.ndarray | None  # waypoints × joints, start and goal included; None = no solution
    message: str = ""
    iterations: int = 0
    planning_time: float = 0.0
    wall_cap_hit: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.path is not None


class Planner(Protocol):
    name: str

    def solve(self, problem: Problem) -> PlanOutcome: ...


class Budget:
    """Termination shared by all planners: iterations (deterministic) or wall time.

    With an iteration budget, an anytime planner stops at ``max_iterations`` once it has a
    solution, and keeps searching up to ``extend × max_iterations`` while it has none.
    """

    def __init__(self, pb: Problem, extend: int = 4) -> None:
        self.max_it = pb.max_iterations
        self.hard_it = None if pb.max_iterations is None else pb.max_iterations * extend
        self.time_limit = pb.time_limit
        self.cancelled = pb.cancelled or (lambda: False)
        self.t0 = time.perf_counter()
        self.iterations = 0
        self.wall_cap_hit = False

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def done(self, solved: bool) -> bool:
        if self.cancelled():
            return True
        if self.elapsed() >= self.time_limit:
            self.wall_cap_hit = self.max_it is not None
            return True
        if self.max_it is None:
            return False
        return self.iterations >= (self.max_it if solved else self.hard_it)

    def why_failed(self) -> str:
        if self.wall_cap_hit:
            return f"planner hit the wall-clock cap of {self.time_limit:g} s after {self.iterations} iterations"
        if self.max_it is None:
            return f"planner ran out of time ({self.time_limit:g} s) without a solution"
        return f"no solution within {self.iterations} iterations"


def k_nearest_count(n_nodes: int, dim: int, rewire_factor: float) -> int:
    """OMPL's k-nearest RRT* neighbourhood size: k_rrt · log(n), k_rrt = rewire · e · (1 + 1/d)."""
    return max(1, math.ceil(rewire_factor * math.e * (1.0 + 1.0 / dim) * math.log(n_nodes + 1)))
