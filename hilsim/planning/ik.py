"""Inverse kinematics of the ``tool`` site on the MuJoCo model: damped least squares with restarts.

From a seed configuration, iterate ``Δq = Jᵀ (J Jᵀ + λ² I)⁻¹ e`` (``e`` = position error, plus
the orientation error as a rotation vector when the orientation counts), clamp to the joint
limits, until the error is below tolerance. The first seed is the current configuration (so the
answer is close to where the arm is); further seeds are uniform within the limits from a seeded
generator. A solution must also be collision-free (:meth:`ArmModel.is_valid`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilsim.core.geometry import rpy_to_matrix
from hilsim.planning.collision import ArmModel

__all__ = ["IKError", "rpy_to_matrix", "solve_ik"]


class IKError(ValueError):
    """No collision-free configuration reaches the pose."""


def _rot_error(r_target: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Rotation vector taking r to r_target (world frame)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, (r_target @ r.T).flatten())
    v = np.empty(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


def solve_ik(
    arm: ArmModel,
    position: np.ndarray,
    rotation: np.ndarray | None = None,
    q_seed: np.ndarray | None = None,
    *,
    site: str = "tool",
    restarts: int = 20,
    iterations: int = 150,
    tol: float = 1e-4,
    seed: int = 0,
) -> np.ndarray:
    m, d = arm.model, arm.data
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid < 0:
        raise IKError(f"the model has no site {site!r}")
    rng = np.random.default_rng(seed)
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    target = np.asarray(position, float)
    best_err = np.inf
    seeds = [np.clip(q_seed, arm.lower, arm.upper)] if q_seed is not None else []
    seeds += [rng.uniform(arm.lower, arm.upper) for _ in range(restarts)]
    lam2 = 1e-4
    for q0 in seeds:
        q = q0.copy()
        for _ in range(iterations):
            arm.set_q(q)
            e = target - d.site_xpos[sid]
            mujoco.mj_comPos(m, d)  # the Jacobian needs cdof
            mujoco.mj_jacSite(m, d, jacp, jacr, sid)
            jac = jacp[:, arm.dof_adr]
            if rotation is not None:
                e = np.concatenate([e, 0.5 * _rot_error(rotation, d.site_xmat[sid].reshape(3, 3))])
                jac = np.vstack([jac, 0.5 * jacr[:, arm.dof_adr]])
            err = float(np.linalg.norm(e))
            if err < tol:
                break
            dq = jac.T @ np.linalg.solve(jac @ jac.T + lam2 * np.eye(len(e)), e)
            step = float(np.max(np.abs(dq)))
            if step > 0.3:  # keep steps small so the linearisation holds
                dq *= 0.3 / step
            q = np.clip(q + dq, arm.lower, arm.upper)
        best_err = min(best_err, err)
        if err < tol and arm.is_valid(q):
            return q
    raise IKError(
        f"no collision-free joint configuration reaches the pose (best position/orientation error {best_err:.4f})"
    )
