"""The imported arm's ``home`` pose and task targets, checked as the planner will check them.

- **home**: the SRDF's group state ``home``, else ``ready``, else its first one, when it is collision-free
  with :data:`CLEARANCE` to spare; otherwise the joints' zero (the middle of a range that excludes 0),
  and, if that collides, the nearest collision-free pose found by seeded random search around it.
- **targets**: :data:`N_TARGETS` poses spread apart in the tool's workspace: each collision-free with
  :data:`CLEARANCE`, inside the inner :data:`RANGE_USED` of every joint's range (continuous joints: of one
  turn), the tool above the pedestal and away from it. Each is planned to and from home and every
  other target (both ways) with the scenario's planner: a target any plan misses is replaced.

Deterministic: the same URDF and seed give the same poses.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlannerLibrary
from hilsim.planning.problem import Problem
from hilsim.tools.robot.urdf import ImportFailure, Joint

CLEARANCE = 0.02  # [m] home and targets keep this far from everything (the planner asks for 5 mm)
RANGE_USED = 0.8  # targets keep to this middle part of each joint's range
N_TARGETS = 3
CANDIDATES = 300  # collision-free poses drawn before the spread-out ones are picked
MAX_MOVE = 1.5  # [rad] (or m) a target's joints at most this far from home: runs of seconds, not minutes


def zero_pose(joints: list[Joint]) -> np.ndarray:
    """Each joint at 0, or at the middle of a range that excludes 0."""
    return np.array([0.0 if not j.limited or j.lower <= 0.0 <= j.upper else (j.lower + j.upper) / 2 for j in joints])


def _bounds(joints: list[Joint], used: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([j.lower if j.limited else -np.pi for j in joints])
    hi = np.array([j.upper if j.limited else np.pi for j in joints])
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * used
    return mid - half, mid + half


def choose_home(arm: ArmModel, joints: list[Joint], states: dict[str, dict[str, float]], seed: int,
                say: Callable[[str], None]) -> tuple[np.ndarray, str]:
    """The home pose and where it came from."""
    names = [j.name for j in joints]
    zero = zero_pose(joints)
    order = [n for n in ("home", "ready") if n in states] + [n for n in states if n not in ("home", "ready")]
    for name in order:
        q = np.array([states[name].get(n, zero[i]) for i, n in enumerate(names)])
        if arm.is_valid(q):
            return q, f"the SRDF's group state {name!r}"
        say(f"  the SRDF's group state {name!r} is not collision-free with {CLEARANCE * 1000:.0f} mm to spare: "
            "not used as home")
    if arm.is_valid(zero):
        return zero, "every joint at zero (or the middle of its range)"
    rng = np.random.default_rng(seed)
    lo, hi = _bounds(joints, 1.0)
    for spread in (0.1, 0.2, 0.4, 0.8, 1.6, 3.2):
        for _ in range(200):
            q = np.clip(zero + rng.normal(0.0, spread, len(zero)), lo, hi)
            if arm.is_valid(q):
                return q, f"the nearest collision-free pose to zero found (spread {spread} rad)"
    near = sorted({f"{c.geom1}–{c.geom2} {c.dist * 1000:.0f} mm" for c in arm.contacts(zero)})
    raise ImportFailure(f"{arm.path}: no collision-free home pose found near zero (too near at zero: "
                        f"{', '.join(near[:4]) or 'none'}): does the robot fit its pedestal?")


def _plan_ok(lib: PlannerLibrary, planner: str, arm: ArmModel, a: np.ndarray, b: np.ndarray, seed: int) -> bool:
    pl = lib.create(planner)
    # the budget the planner service has in lockstep: what is planned here is planned there
    out = pl.solve(Problem(arm, a, b, seed=seed, max_iterations=lib.iterations, time_limit=20.0,
                           resolution=lib.resolution))
    return out.success


def choose_targets(arm: ArmModel, joints: list[Joint], home: np.ndarray, library: Path, planner: str, seed: int,
                   say: Callable[[str], None]) -> list[np.ndarray]:
    """:data:`N_TARGETS` targets, each reachable from home and from each other, both ways."""
    rng = np.random.default_rng(seed + 1)
    lo, hi = _bounds(joints, RANGE_USED)
    base, _ = arm.site_pose(home, "tool")
    root = arm.data.xpos[1].copy()  # the arm's root body: the pedestal's top
    reach = max(np.linalg.norm(base - root), 0.2)
    cands: list[tuple[np.ndarray, np.ndarray]] = []
    tries = 0
    while len(cands) < CANDIDATES and tries < CANDIDATES * 60:
        tries += 1
        q = np.clip(home + rng.uniform(-MAX_MOVE, MAX_MOVE, len(lo)), lo, hi)
        if not arm.is_valid(q):
            continue
        p, _ = arm.site_pose(q, "tool")
        horizontal = np.linalg.norm((p - root)[:2])
        # above the pedestal's top and clear of its column, within the reach of home
        if p[2] - root[2] < 0.05 or horizontal < 0.25 * reach or np.linalg.norm(p - root) > 1.2 * reach:
            continue
        cands.append((q, p))
    if len(cands) < N_TARGETS:
        raise ImportFailure(f"{arm.path}: only {len(cands)} collision-free poses with the tool above the pedestal "
                            f"in {tries} tries: no targets")
    lib = PlannerLibrary.load(library)
    chosen: list[np.ndarray] = []
    points: list[np.ndarray] = []
    rejected = 0
    pool = list(cands)
    while len(chosen) < N_TARGETS and pool:
        # farthest from the chosen tool points (and from home's), then the smallest joint motion
        ref = [base, *points]
        pool.sort(key=lambda c: (-min(np.linalg.norm(c[1] - r) for r in ref), float(np.abs(c[0] - home).sum())))
        q, p = pool.pop(0)
        others = [home, *chosen]
        ok = all(_plan_ok(lib, planner, arm, a, b, seed) for o in others for a, b in ((o, q), (q, o)))
        if not ok:
            rejected += 1
            continue
        chosen.append(q)
        points.append(p)
        say(f"  target {len(chosen)}: tool at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m, planned to and from "
            f"home{' and the targets before' if len(chosen) > 1 else ''}")
    if len(chosen) < N_TARGETS:
        raise ImportFailure(f"{arm.path}: only {len(chosen)} of {N_TARGETS} targets could be planned to with "
                            f"{planner!r} ({rejected} tried and missed)")
    return chosen
