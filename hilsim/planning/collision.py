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

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

VELOCITY_LIMIT_NUMERIC = "arm_joint_velocity_limit"


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
        self.lower = np.where(limited, m.jnt_range[self.joint_ids, 0], -np.pi)
        self.upper = np.where(limited, m.jnt_range[self.joint_ids, 1], np.pi)
        self.n = len(self.joint_names)
        self.clearance = float(clearance)
        m.geom_margin[:] = self.clearance
        self.checks = 0  # number of configurations checked (for benchmarks)
        self._qpos0 = m.qpos0.copy()

    # ------------------------------------------------------------------ limits
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
        return bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    def limit_violation(self, q: np.ndarray) -> str | None:
        for i, name in enumerate(self.joint_names):
            if not self.lower[i] - 1e-9 <= q[i] <= self.upper[i] + 1e-9:
                return f"{name} = {q[i]:.4f} outside its limits [{self.lower[i]:.3f}, {self.upper[i]:.3f}]"
        return None

    # ------------------------------------------------------------------ kinematics / collision
    def set_q(self, q: np.ndarray) -> None:
        d = self.data
        d.qpos[:] = self._qpos0
        d.qpos[self.qpos_adr] = q
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
        m = self.model
        out = []
        for c in self.data.contact[:n]:
            out.append(Contact(m.geom(int(c.geom1)).name, m.geom(int(c.geom2)).name, float(c.dist)))
        return out

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
        """Straight joint-space segment a→b valid at every step of at most ``resolution`` rad (max-norm)."""
        steps = max(1, int(np.ceil(np.max(np.abs(b - a)) / resolution)))
        for k in range(1, steps + 1):
            if not self.is_valid(a + (b - a) * (k / steps)):
                return False
        return True

    def site_pose(self, q: np.ndarray, site: str = "tool") -> tuple[np.ndarray, np.ndarray]:
        """World position and rotation matrix of a site at configuration q."""
        self.set_q(q)
        sid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
        if sid < 0:
            raise ValueError(f"{self.path}: no site named {site!r}")
        return self.data.site_xpos[sid].copy(), self.data.site_xmat[sid].reshape(3, 3).copy()
