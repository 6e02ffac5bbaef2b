"""Planning in SE(2) over an occupancy grid: OMPL with Reeds–Shepp curves.

The state space is OMPL's ``ReedsSheppStateSpace`` (x, y, yaw; shortest paths made of arcs of
``turning_radius`` and straight lines, forwards and backwards) bounded by the grid. A state is
valid when every circle of the robot's :class:`Footprint` (centres on the body's x axis) lies in
free space: its centre in a free cell of the grid inflated by the circle radius plus a clearance
(:meth:`hilsim.navigation.grid.Grid.inflate`). A rectangle covered by two or three circles fits
through a doorway that one circle around it would not. Motions are checked every
``check_step`` metres.

The planner (``RRTConnect`` by default with a ``planner_range`` of 3 m, any OMPL geometric planner by
name) stops on an iteration count, which is deterministic, with ``time_limit`` only a wall-clock
safety cap reported when hit; OMPL's random generator is seeded once per process
(:func:`hilsim.planning.library.seed_ompl`), so
a process that plans the same goals in the same order gets the same paths. The solution is
shortened with OMPL's ``PathSimplifier`` and interpolated every ``step`` metres; the shortest of
``attempts`` such plans is kept (a tree planner's first solution depends on its samples, and a
few tries cost less than an asymptotically optimal planner's Python validity checks).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from hilsim.navigation.grid import Grid


@dataclass(frozen=True)
class Footprint:
    """Circles covering the robot: centres at ``centres`` metres along its x axis, each of ``radius``."""

    radius: float
    centres: tuple[float, ...] = (0.0,)

    def points(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(self.centres, float)
        return x + c * math.cos(yaw), y + c * math.sin(yaw)

    @classmethod
    def covering(cls, length: float, width: float, n: int = 2) -> Footprint:
        """``n`` equal circles along the x axis that cover a ``length`` × ``width`` rectangle
        centred on the body origin."""
        seg = length / n
        centres = tuple(-length / 2 + seg * (i + 0.5) for i in range(n))
        return cls(math.hypot(seg / 2, width / 2), centres)


@dataclass
class PlanResult:
    path: np.ndarray | None  # N×3: x, y, yaw, every `step` metres; None: no plan
    message: str
    iterations: int = 0
    planning_time: float = 0.0  # wall seconds
    wall_cap_hit: bool = False

    @property
    def length(self) -> float:
        return path_length(self.path) if self.path is not None else math.nan


def path_length(path: np.ndarray) -> float:
    return float(np.sum(np.hypot(np.diff(path[:, 0]), np.diff(path[:, 1])))) if len(path) > 1 else 0.0


class SE2Planner:
    def __init__(
        self,
        grid: Grid,
        footprint: Footprint,
        *,
        turning_radius: float = 0.8,
        clearance: float = 0.05,
        planner: str = "RRTConnect",
        planner_range: float = 3.0,
        check_step: float | None = None,
    ) -> None:
        from ompl import geometric as og

        if not hasattr(og, planner):
            raise ValueError(f"OMPL has no geometric planner {planner!r}")
        if turning_radius <= 0:
            raise ValueError("turning_radius must be positive")
        self.grid = grid
        self.footprint = footprint
        self.turning_radius = turning_radius
        self.planner_name = planner
        self.planner_range = planner_range
        if grid.inflated.shape != grid.occ.shape or grid.radius != footprint.radius + clearance:
            grid.inflate(footprint.radius + clearance)
        self.check_step = check_step or grid.resolution / 2

    # ------------------------------------------------------------------ validity
    def why_invalid(self, x: float, y: float, yaw: float) -> str | None:
        """None if the robot fits at (x, y, yaw), else why not (one line)."""
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            return "not a finite pose"
        x0, x1, y0, y1 = self.grid.bounds
        px, py = self.footprint.points(x, y, yaw)
        if np.any((px < x0) | (px >= x1) | (py < y0) | (py >= y1)):
            return f"({x:.2f}, {y:.2f}) is outside the map (x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f})"
        if not np.all(self.grid.free(px, py)):
            return f"({x:.2f}, {y:.2f}, yaw {yaw:.2f}) is too close to an obstacle"
        return None

    def nearest_valid(self, pose: tuple[float, float, float], reach: float = 0.25) -> tuple[float, float, float] | None:
        """The valid pose with the same yaw nearest to ``pose`` within ``reach`` metres (rings of
        half a cell), or None."""
        x, y, yaw = pose
        step = self.grid.resolution / 2
        for k in range(1, math.ceil(reach / step) + 1):
            r = k * step
            n = max(8, math.ceil(2 * math.pi * r / step))
            for i in range(n):
                a = 2 * math.pi * i / n
                if self.is_valid(x + r * math.cos(a), y + r * math.sin(a), yaw):
                    return x + r * math.cos(a), y + r * math.sin(a), yaw
        return None

    def is_valid(self, x: float, y: float, yaw: float) -> bool:
        px, py = self.footprint.points(x, y, yaw)
        return bool(np.all(self.grid.free(px, py)))

    # ------------------------------------------------------------------ planning
    def plan(
        self,
        start: tuple[float, float, float],
        goal: tuple[float, float, float],
        *,
        max_iterations: int = 20000,
        time_limit: float = 5.0,
        step: float = 0.05,
        seed: int = 0,
        attempts: int = 1,
    ) -> PlanResult:
        """The shortest of ``attempts`` plans (each with the iteration budget; together within
        ``time_limit``): a tree planner's first solution, even shortened, depends on its samples."""
        w0 = time.perf_counter()
        best: PlanResult | None = None
        iterations = 0
        for _ in range(max(1, attempts)):
            left = time_limit - (time.perf_counter() - w0)
            if best is not None and left <= 0:
                break
            r = self._plan_once(start, goal, max_iterations=max_iterations, time_limit=max(left, 1e-3), step=step,
                                seed=seed)
            iterations += r.iterations
            if r.path is not None and (best is None or best.path is None or r.length < best.length):
                best = r
            elif best is None:
                best = r
            if r.path is None and (r.message.startswith(("start invalid", "goal invalid")) or r.wall_cap_hit):
                break
        assert best is not None
        best.iterations, best.planning_time = iterations, time.perf_counter() - w0
        return best

    def _plan_once(
        self,
        start: tuple[float, float, float],
        goal: tuple[float, float, float],
        *,
        max_iterations: int,
        time_limit: float,
        step: float,
        seed: int,
    ) -> PlanResult:
        from ompl import base as ob
        from ompl import geometric as og

        from hilsim.planning.library import seed_ompl

        w0 = time.perf_counter()
        # SE(2) yaw lives in [-π, π]: a goal's 3.1416 is the same heading
        start = (start[0], start[1], math.remainder(start[2], 2 * math.pi))
        goal = (goal[0], goal[1], math.remainder(goal[2], 2 * math.pi))
        measured = start
        if self.why_invalid(*start) is not None and (near := self.nearest_valid(start)) is not None:
            # the estimate put the rover a little inside the inflated obstacles (it stopped a few cm
            # off a goal near a wall): plan from the nearest free pose, the first waypoint stays here
            start = near
        for what, s in (("start", start), ("goal", goal)):
            why = self.why_invalid(*s)
            if why is not None:
                return PlanResult(None, f"{what} invalid: {why}")
        seed_ompl(seed)
        space = ob.ReedsSheppStateSpace(self.turning_radius)
        x0, x1, y0, y1 = self.grid.bounds
        b = ob.RealVectorBounds(2)
        b.setLow(0, x0)
        b.setHigh(0, x1)
        b.setLow(1, y0)
        b.setHigh(1, y1)
        space.setBounds(b)
        si = ob.SpaceInformation(space)
        si.setStateValidityChecker(lambda s: self.is_valid(s.getX(), s.getY(), s.getYaw()))
        si.setStateValidityCheckingResolution(self.check_step / space.getMaximumExtent())
        si.setup()
        s0, s1 = space.allocState(), space.allocState()
        s0.setXY(float(start[0]), float(start[1]))
        s0.setYaw(float(start[2]))
        s1.setXY(float(goal[0]), float(goal[1]))
        s1.setYaw(float(goal[2]))
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(s0, s1, 1e-3)
        pdef.setOptimizationObjective(ob.PathLengthOptimizationObjective(si))
        planner = getattr(og, self.planner_name)(si)
        if hasattr(planner, "setRange"):
            planner.setRange(self.planner_range)  # short edges: a tree that follows the free space
        planner.setProblemDefinition(pdef)
        planner.setup()
        count = [0]
        cap = [False]

        def stop() -> bool:
            # OMPL calls this once per iteration: a count is a deterministic termination condition
            count[0] += 1
            if time.perf_counter() - w0 >= time_limit:
                cap[0] = True
                return True
            return count[0] >= max_iterations

        planner.solve(ob.PlannerTerminationCondition(stop))
        if not pdef.hasExactSolution():
            why = "wall-clock cap" if cap[0] else f"{max_iterations} iterations"
            return PlanResult(None, f"no path found within {why}", count[0], time.perf_counter() - w0, cap[0])
        path = pdef.getSolutionPath()
        og.PathSimplifier(si).simplifyMax(path)
        path.interpolate(max(2, math.ceil(path.length() / step) + 1))
        pts = np.array([[path.getState(k).getX(), path.getState(k).getY(), path.getState(k).getYaw()]
                        for k in range(path.getStateCount())])
        pts[0], pts[-1] = start, goal
        if measured != start:
            pts = np.vstack([measured, pts])
        return PlanResult(pts, "ok", count[0], time.perf_counter() - w0, cap[0])


def directions(path: np.ndarray) -> np.ndarray:
    """+1 where the robot drives forwards from point i to i+1, −1 backwards (length N−1)."""
    d = np.diff(path[:, :2], axis=0)
    along = d[:, 0] * np.cos(path[:-1, 2]) + d[:, 1] * np.sin(path[:-1, 2])
    return np.where(along >= 0, 1, -1)


def smoothness(path: np.ndarray) -> float:
    """Mean absolute heading change per metre of path [rad/m] (0 for a straight line)."""
    if len(path) < 3:
        return 0.0
    dyaw = np.abs(np.angle(np.exp(1j * np.diff(path[:, 2]))))
    return float(np.sum(dyaw) / max(path_length(path), 1e-9))
