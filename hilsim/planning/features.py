"""What a planning query looks like to the planner choice (:mod:`hilsim.planning.choice`): its features.

A query is a start and a goal joint vector in a scene (a MuJoCo world with the arm). Its features,
in :data:`FEATURES` order:

- the joint-space distance (Euclidean, max-norm) and the joints' moves in six groups along the chain
  (an arm of six joints: each joint's own move; of seven or nine: the largest move of each group, so
  the features are the same whatever the joint count);
- the straight joint line start → goal, checked at ``LINE_SAMPLES`` evenly spaced states: the
  fraction of them in collision (closer than the clearance), and the arm's smallest and mean
  distance to the world's static geoms (table, obstacles) along it, capped at ``FAR`` (a second copy
  of the model whose geoms report contacts up to ``FAR`` away);
- that distance at the start and at the goal;
- where the tool is at the start and at the goal, from the arm's base (its root body), how far apart (m),
  and the lower of its two heights;
- the scene: how many obstacles stand on the table, their volume, the highest one's top, and the
  fraction of ``CSPACE_SAMPLES`` random configurations (a fixed seed) that collide — computed once
  per world model and kept.

Everything is collision checking and forward kinematics on MuJoCo (about 50 checks a query, about
a millisecond; the scene's 256 checks once), and deterministic.
"""

from __future__ import annotations

import functools
from pathlib import Path

import mujoco
import numpy as np

from hilsim.planning.collision import ArmModel

LINE_SAMPLES = 16
JOINT_GROUPS = 6  # the joints' moves, in this many groups along the chain
FAR = 0.25  # m: distances beyond this count as far
CSPACE_SAMPLES = 256
_FIXED = ("table", "floor")  # static geoms that are not obstacles

FEATURES: tuple[str, ...] = (
    "dist_l2", "dist_max", "dq1", "dq2", "dq3", "dq4", "dq5", "dq6",
    "line_blocked", "line_min_clear", "line_mean_clear", "start_clear", "goal_clear",
    "tool_start_x", "tool_start_y", "tool_start_z", "tool_goal_x", "tool_goal_y", "tool_goal_z",
    "tool_dist", "tool_min_z",
    "scene_obstacles", "scene_volume", "scene_top", "scene_cspace_blocked",
)


class FeatureModel:
    """Computes :data:`FEATURES` of queries in one world. Holds two MuJoCo models: not thread-safe."""

    def __init__(self, model_path: str | Path, clearance: float = 0.005, joint_names: list[str] | None = None) -> None:
        self.arm = ArmModel(model_path, clearance, joint_names)
        self.far = ArmModel(model_path, FAR, self.arm.joint_names)
        m = self.far.model
        self._static = np.array([m.geom_bodyid[g] == 0 for g in range(m.ngeom)])
        # the far copy reports arm-to-world pairs only (no link-to-link ones): half the pairs to test
        m.geom_contype[:] = np.where(self._static, 0, 2)
        m.geom_conaffinity[:] = np.where(self._static, 2, 0)
        self.scene = scene_features(str(Path(model_path).resolve()), clearance, tuple(self.arm.joint_names))
        # the arm's root body (the child of the world its first joint hangs from): where the tool is measured from
        am = self.arm.model
        b = int(am.jnt_bodyid[self.arm.joint_ids[0]])
        while int(am.body_parentid[b]) != 0:
            b = int(am.body_parentid[b])
        self._root = b
        n = self.arm.n  # each joint's group of the six (the identity for six joints)
        self._group = np.minimum((np.arange(n) * JOINT_GROUPS) // max(n, 1), JOINT_GROUPS - 1)

    def clearance(self, q: np.ndarray) -> float:
        """The arm's distance to the nearest static geom at ``q`` (FAR when none is nearer)."""
        far = self.far
        far.set_q(q)
        mujoco.mj_collision(far.model, far.data)
        n = far.data.ncon  # arm-to-world pairs only (the far copy's contype/conaffinity)
        d = float(far.data.contact.dist[:n].min()) if n else FAR
        return min(max(d, -FAR), FAR)

    def features(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        start, goal = np.asarray(start, float), np.asarray(goal, float)
        dq = np.abs(goal - start)
        moves = np.zeros(JOINT_GROUPS)
        np.maximum.at(moves, self._group, dq)
        line = start + np.outer(np.linspace(0.0, 1.0, LINE_SAMPLES), goal - start)
        blocked = sum(not self.arm.is_valid(q) for q in line[1:-1]) / (LINE_SAMPLES - 2)
        clear = np.array([self.clearance(q) for q in line])
        ps, _ = self.arm.site_pose(start)
        ps = ps - self.arm.data.xpos[self._root]
        pg, _ = self.arm.site_pose(goal)
        pg = pg - self.arm.data.xpos[self._root]
        return np.array([
            float(np.linalg.norm(goal - start)), float(dq.max()), *moves,
            blocked, float(clear.min()), float(clear.mean()), float(clear[0]), float(clear[-1]),
            *ps, *pg, float(np.linalg.norm(pg - ps)), float(min(ps[2], pg[2])),
            *self.scene,
        ])


@functools.lru_cache(maxsize=64)
def scene_features(model_path: str, clearance: float, joint_names: tuple[str, ...]) -> tuple[float, ...]:
    """(obstacles, their volume [m³], the highest top [m], fraction of random configurations that
    collide) of a world: computed once per model (the random draws from a fixed seed)."""
    arm = ArmModel(model_path, clearance, list(joint_names))
    m = arm.model
    count, volume, top = 0, 0.0, 0.0
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != 0 or m.geom(g).name in _FIXED or m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        count += 1
        s = m.geom_size[g]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            volume += 8 * s[0] * s[1] * s[2]
            top = max(top, float(m.geom_pos[g][2] + s[2]))
        else:  # other primitives: their bounding sphere
            volume += 4 / 3 * np.pi * m.geom_rbound[g] ** 3
            top = max(top, float(m.geom_pos[g][2] + m.geom_rbound[g]))
    rng = np.random.default_rng(12345)
    qs = rng.uniform(arm.lower, arm.upper, size=(CSPACE_SAMPLES, arm.n))
    blocked = sum(not arm.is_valid(q) for q in qs) / CSPACE_SAMPLES
    return float(count), float(volume), float(top), float(blocked)
