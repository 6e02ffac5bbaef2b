"""Collision checking of arm configurations against the MuJoCo world (the model physics runs).

:class:`ArmModel` loads the scenario's MJCF world (e.g. ``models/arm/tabletop.xml``), finds the
arm's hinge joints in actuator order and answers, for a joint vector ``q``:

- is it inside the joint limits?
- does any moving link come closer than ``clearance`` to another geom (obstacles, table, the
  static base, non-adjacent links)?

Only forward kinematics and the collision pipeline run (``mj_kinematics`` + ``mj_collision``,
a few microseconds), with every geom's margin set to the clearance so that MuJoCo reports pairs
that are *nearly* touching too. Pairs excluded in the model (adjacent links) and pairs of two
static geoms (table and obstacle) are never reported, so they need no filtering here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

VELOCITY_LIMIT_NUMERIC = "arm_joint_velocity_limit"
UNLIMITED = 2 * np.pi  # the planning bounds of a continuous joint [rad]


@dataclass
class Contact:
    geom1: str
    geom2: str
    dist: float


class ArmModel:
    """MuJoCo model of the world with the arm, for planning queries. Not thread-safe: one per thread."""

    def __init__(self, model_path: str | Path, clearance: float = 0.005, joint_names: list[str] | None = None) -> None:
        self.path = Path(model_path)
        try:
            self.model = mujoco.MjModel.from_xml_path(str(self.path))
        except ValueError as e:
            raise ValueError(f"cannot load MuJoCo model {self.path}: {str(e).splitlines()[0]}") from None
        self.data = mujoco.MjData(self.model)
        m = self.model
        if joint_names is None:
            # actuator order = joint order of the commands; fall back to all hinge joints
            names = [m.joint(int(m.actuator_trnid[a, 0])).name for a in range(m.nu) if m.actuator_trntype[a] == 0]
            hinge = mujoco.mjtJoint.mjJNT_HINGE
            joint_names = names or [m.joint(j).name for j in range(m.njnt) if m.jnt_type[j] == hinge]
        self.joint_names = list(joint_names)
        ids = []
        for n in self.joint_names:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)
            if j < 0:
                raise ValueError(f"{self.path}: no joint named {n!r}")
            ids.append(j)
        self.joint_ids = np.array(ids)
        self.qpos_adr = m.jnt_qposadr[self.joint_ids]
        self.dof_adr = m.jnt_dofadr[self.joint_ids]
        limited = m.jnt_limited[self.joint_ids].astype(bool)
        # a continuous (unlimited) joint plans within one turn either way of zero: any angle and the
        # way to it the short way round from any start within a turn
        self.continuous = ~limited
        self.lower = np.where(limited, m.jnt_range[self.joint_ids, 0], -UNLIMITED)
        self.upper = np.where(limited, m.jnt_range[self.joint_ids, 1], UNLIMITED)
        self.n = len(self.joint_names)
        self.clearance = float(clearance)
        m.geom_margin[:] = self.clearance
        self.checks = 0  # number of configurations checked (for benchmarks)
        self._qpos0 = m.qpos0.copy()
        self._lo, self._hi = self.lower - 1e-9, self.upper + 1e-9
        # the arm's joints usually sit together in qpos: one slice instead of an index array
        a = self.qpos_adr
        contiguous = len(a) > 0 and bool(np.all(np.diff(a) == 1))
        self._q_at: slice | np.ndarray = slice(int(a[0]), int(a[0]) + len(a)) if contiguous else a
        # nothing but the arm moves in a planning world: then no other coordinate needs resetting
        self._reset = m.nq != len(a)

    # ------------------------------------------------------------------ limits
    def home(self) -> np.ndarray:
        """The arm's start pose: the model's ``home`` keyframe if it has one, else its ``qpos0``, within
        the limits."""
        m = self.model
        k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
        q = (m.key_qpos[k] if k >= 0 else m.qpos0)[self.qpos_adr]
        return np.clip(np.asarray(q, float), self.lower, self.upper)

    def sampling_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Where random configurations of this arm are drawn: within the limits, and for a joint that turns
        more than once (±2π, continuous) one turn centred on the home pose. Each physical pose once: a
        joint range of two turns holds every pose twice, and the copies are often cut off from each
        other (the UR5's shoulder would have to swing its arm through the table from one to the other)."""
        home = self.home()
        wide = (self.upper - self.lower) > 2 * np.pi + 1e-9
        lo = np.where(wide, np.maximum(self.lower, home - np.pi), self.lower)
        hi = np.where(wide, np.minimum(self.upper, home + np.pi), self.upper)
        return lo, hi

    def velocity_limits(self) -> np.ndarray | None:
        """Per-joint velocity limits from the model's custom numeric, if it has one."""
        m = self.model
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, VELOCITY_LIMIT_NUMERIC)
        if i < 0:
            return None
        adr, size = m.numeric_adr[i], m.numeric_size[i]
        v = np.array(m.numeric_data[adr : adr + size])
        return v if len(v) == self.n else None

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> bool:
        if tol == 1e-9:  # the planners' hot path: bounds precomputed, ndarray methods (no np.all dispatch)
            return bool((q >= self._lo).all() and (q <= self._hi).all())
        return bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    def limit_violation(self, q: np.ndarray) -> str | None:
        for i, name in enumerate(self.joint_names):
            if not self.lower[i] - 1e-9 <= q[i] <= self.upper[i] + 1e-9:
                return f"{name} = {q[i]:.4f} outside its limits [{self.lower[i]:.3f}, {self.upper[i]:.3f}]"
        return None

    # ------------------------------------------------------------------ kinematics / collision
    def set_q(self, q: np.ndarray) -> None:
        d = self.data
        if self._reset:
            d.qpos[:] = self._qpos0
        d.qpos[self._q_at] = q
        mujoco.mj_kinematics(self.model, d)

    def _collide(self, q: np.ndarray) -> int:
        self.set_q(q)
        mujoco.mj_collision(self.model, self.data)
        self.checks += 1
        return int(self.data.ncon)

    def is_valid(self, q: np.ndarray) -> bool:
        """Inside the limits and no geom pair closer than the clearance."""
        return self.within_limits(q) and self._collide(q) == 0

    def contacts(self, q: np.ndarray) -> list[Contact]:
        n = self._collide(q)
        out = []
        for c in self.data.contact[:n]:
            out.append(Contact(self.geom_label(int(c.geom1)), self.geom_label(int(c.geom2)), float(c.dist)))
        return out

    def geom_label(self, g: int) -> str:
        """How a collision message names a geom: its name, else its body's (a URDF's link: MuJoCo's
        URDF reader leaves geoms unnamed), with the geom's index when the body has several."""
        m = self.model
        name = m.geom(g).name
        if name:
            return name
        b = int(m.geom_bodyid[g])
        body = m.body(b).name or ("world" if b == 0 else f"body {b}")
        return body if m.body_geomnum[b] <= 1 else f"{body} (geom {g})"

    def why_invalid(self, q: np.ndarray) -> tuple[str, str] | None:
        """``None`` if valid, else (``limits`` | ``collision``, one-line reason)."""
        if (r := self.limit_violation(q)) is not None:
            return "limits", r
        cs = self.contacts(q)
        if cs:
            c = min(cs, key=lambda c: c.dist)
            what = "penetrates" if c.dist < 0 else "is closer than the clearance to"
            return "collision", (
                f"{c.geom1} {what} {c.geom2} (distance {c.dist * 1000:.1f} mm, "
                f"clearance {self.clearance * 1000:.1f} mm)"
            )
        return None

    def motion_valid(self, a: np.ndarray, b: np.ndarray, resolution: float) -> bool:
        """Straight joint-space segment a→b valid at every step of at most ``resolution`` rad (max-norm).

        The limits are a box, so a segment between two points inside them stays inside: only
        the end is checked against them. The states are checked end first, then halving the
        remaining gaps (as OMPL's DiscreteMotionValidator does), so a blocked segment is
        usually found blocked after a few checks instead of after half of them.
        """
        d = b - a
        steps = max(1, int(np.ceil(np.max(np.abs(d)) / resolution)))
        if not self.within_limits(b):
            return False
        if not self.within_limits(a):  # a itself is not checked (a measured start may be a hair out)
            return all(self.within_limits(q) and not self._collide(q) for q in _states(a, d, steps))
        # the hot loop of every planner: _collide inlined, the states computed in one go
        m, data, at, reset, q0 = self.model, self.data, self._q_at, self._reset, self._qpos0
        qpos = data.qpos
        kin, col = mujoco.mj_kinematics, mujoco.mj_collision
        for i, q in enumerate(_states(a, d, steps)):
            if reset:
                qpos[:] = q0
            qpos[at] = q
            kin(m, data)
            col(m, data)
            if data.ncon:
                self.checks += i + 1
                return False
        self.checks += steps
        return True

    def site_pose(self, q: np.ndarray, site: str = "tool") -> tuple[np.ndarray, np.ndarray]:
        """World position and rotation matrix of a site at configuration q."""
        self.set_q(q)
        sid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
        if sid < 0:
            raise ValueError(f"{self.path}: no site named {site!r}")
        return self.data.site_xpos[sid].copy(), self.data.site_xmat[sid].reshape(3, 3).copy()


def _states(a: np.ndarray, d: np.ndarray, steps: int) -> np.ndarray:
    """The states of segment a → a + d to check, in :func:`_bisection_order`, one per row."""
    return a + np.outer(_fractions(steps), d)


@functools.lru_cache(maxsize=1024)
def _fractions(steps: int) -> np.ndarray:
    f = np.array(_bisection_order(steps), dtype=float) / steps
    f.flags.writeable = False
    return f


@functools.lru_cache(maxsize=1024)
def _bisection_order(steps: int) -> tuple[int, ...]:
    """1 … steps, the last first, then the midpoints of the remaining gaps, coarse to fine."""
    out, seen = [steps], {0, steps}
    queue = [(0, steps)]
    while queue:
        nxt = []
        for lo, hi in queue:
            if hi - lo < 2:
                continue
            mid = (lo + hi) // 2
            if mid not in seen:
                seen.add(mid)
                out.append(mid)
            nxt += [(lo, mid), (mid, hi)]
        queue = nxt
    out += [k for k in range(1, steps) if k not in seen]
    return tuple(out)
