"""Joint control: PID with anti-windup, trajectory sampling, the model's joint table.

Pure Python/numpy (MuJoCo is only used to read the model's joints and actuators); no Zenoh,
so everything here is unit-tested without a network. :mod:`hilsim.services.controller`
wires it to the keys.

PID law of one joint (``e = r - y``)::

    u = kp·e + ki·∫e dt + kd·(v_ref - v_meas) + feedforward·v_ref

The derivative acts on the *measured* velocity (``-kd·v_meas``), so a step of the setpoint
gives no derivative kick; the ``kd·v_ref`` term only adds damping relative to a moving
reference (it is zero for a setpoint step). Anti-windup: the integral is clamped so that
``|ki·∫e| ≤ i_limit``, and it does not grow while the output is saturated in the direction
the error pushes it (conditional integration). The output is clamped to the joint's limits.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import ConfigError, PidGains

GAIN_FIELDS: tuple[str, ...] = tuple(PidGains.model_fields)  # kp ki kd i_limit output_limit feedforward


class TrajectoryError(ValueError):
    """A trajectory the controller cannot follow; the message says why, in one line."""


# ---------------------------------------------------------------- model joint table
@dataclass(frozen=True)
class JointTable:
    """The actuated joints of a MuJoCo model, in actuator order (= command order)."""

    names: tuple[str, ...]
    lower: np.ndarray  # position limits [rad or m]; -inf/inf when unlimited
    upper: np.ndarray
    effort_lower: np.ndarray  # actuator ctrlrange (effort limits in effort mode); -inf/inf when unlimited
    effort_upper: np.ndarray

    @property
    def n(self) -> int:
        return len(self.names)


def joint_table(model_path: str | Path) -> JointTable:
    """Read the actuated joints of an MJCF file; actuators are expected to be named like their joints."""
    import mujoco  # imported here: only services that need the model pay for it

    try:
        m = mujoco.MjModel.from_xml_path(str(model_path))
    except ValueError as e:
        raise ConfigError(f"world.model: cannot load {model_path}: {str(e).splitlines()[0]}") from None
    names, lo, hi, elo, ehi = [], [], [], [], []
    for a in range(m.nu):
        if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            continue
        j = int(m.actuator_trnid[a, 0])
        names.append(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j))
        limited = bool(m.jnt_limited[j])
        lo.append(m.jnt_range[j, 0] if limited else -math.inf)
        hi.append(m.jnt_range[j, 1] if limited else math.inf)
        climited = bool(m.actuator_ctrllimited[a])
        elo.append(m.actuator_ctrlrange[a, 0] if climited else -math.inf)
        ehi.append(m.actuator_ctrlrange[a, 1] if climited else math.inf)
    if not names:
        raise ConfigError(f"world.model: {model_path} has no joint actuators")
    f = np.asarray
    return JointTable(tuple(names), f(lo, float), f(hi, float), f(elo, float), f(ehi, float))


# ---------------------------------------------------------------- PID
class Pid:
    """PID of one joint. Gains may be changed between calls (live tuning)."""

    def __init__(
        self,
        gains: PidGains,
        effort_lower: float = -math.inf,
        effort_upper: float = math.inf,
    ) -> None:
        self.kp = gains.kp
        self.ki = gains.ki
        self.kd = gains.kd
        self.i_limit = gains.i_limit
        self.feedforward = gains.feedforward
        self.output_limit = gains.output_limit  # None: the actuator's limits alone
        self._effort = (effort_lower, effort_upper)
        self.integral = 0.0
        self.lo = self.hi = 0.0
        self._update_limits()

    def set(self, field: str, value: float) -> None:
        """Change one gain (a name of :data:`GAIN_FIELDS`); the caller has validated the value."""
        if field not in GAIN_FIELDS:
            raise KeyError(field)
        setattr(self, field, float(value))
        self._update_limits()
        self._clamp_integral()

    def _update_limits(self) -> None:
        # A configured output_limit can only tighten the actuator's range: beyond it physics
        # clips anyway, and anti-windup must know where the real saturation is.
        lim = math.inf if self.output_limit is None else self.output_limit
        self.lo = max(self._effort[0], -lim)
        self.hi = min(self._effort[1], lim)

    def _clamp_integral(self) -> None:
        if self.ki <= 0.0:
            self.integral = 0.0  # no integral action: nothing may wind up for a later ki
        elif math.isfinite(self.i_limit):
            bound = self.i_limit / self.ki
            self.integral = min(max(self.integral, -bound), bound)

    def reset(self) -> None:
        self.integral = 0.0

    def update(self, pos_ref: float, vel_ref: float, pos: float, vel: float, dt: float) -> float:
        """One control step: the effort for this joint."""
        e = pos_ref - pos
        u_rest = self.kp * e + self.kd * (vel_ref - vel) + self.feedforward * vel_ref
        if self.ki > 0.0:
            old = self.integral
            self.integral += e * dt
            self._clamp_integral()
            u = u_rest + self.ki * self.integral
            # Conditional integration: saturated and the error pushes further -> keep the old integral.
            if (u > self.hi and e > 0.0) or (u < self.lo and e < 0.0):
                self.integral = old
                u = u_rest + self.ki * old
        else:
            u = u_rest
        return min(max(u, self.lo), self.hi)


def gains_for(gains: Mapping[str, PidGains], joints: Sequence[str], where: str = "") -> list[PidGains]:
    """Per-joint gains from ``controller.gains`` (joint name, falling back to ``default``).

    Raises :class:`ConfigError` naming the field for a joint without gains or a name that is
    not a joint of the model (a typo would otherwise be silently replaced by the default).
    """
    prefix = f"{where}: " if where else ""
    for k in gains:
        if k != "default" and k not in joints:
            raise ConfigError(f"{prefix}controller.gains.{k}: not a joint of the model (joints: {', '.join(joints)})")
    out = []
    for j in joints:
        g = gains.get(j, gains.get("default"))
        if g is None:
            raise ConfigError(f"{prefix}controller.gains: no gains for {j} and no 'default' entry")
        out.append(g.model_copy())
    return out


def check_gain(name: str, field: str, value: float) -> str | None:
    """The rule of one gain, for every caller (the controller, the panel, ``hilsim gains``): a known field,
    finite, and within the bounds the scenario's schema gives it (:class:`PidGains`: ``ge``/``gt``). The
    reason it is refused, beginning with ``name`` (how the caller names it), or None when it is good."""
    if field not in GAIN_FIELDS:
        return f"{name}: unknown gain {field!r} (gains: {', '.join(GAIN_FIELDS)})"
    if not math.isfinite(value):
        return f"{name}: value {value} is not finite"
    for bound in PidGains.model_fields[field].metadata:
        ge, gt = getattr(bound, "ge", None), getattr(bound, "gt", None)
        if ge is not None and not value >= ge:
            return f"{name}: value {value} must be >= {ge}"
        if gt is not None and not value > gt:
            return f"{name}: value {value} must be > {gt}"
    return None


def check_parameter(name: str, value: float, joints: Sequence[str]) -> tuple[int, str] | str:
    """Validate one live parameter ``<joint>.<field>``; return (joint index, field) or a reason."""
    joint, _, field = name.rpartition(".")
    if joint not in joints:
        return f"{name}: unknown joint {joint!r} (joints: {', '.join(joints)})"
    why = check_gain(name, field, value)
    return why if why is not None else (list(joints).index(joint), field)


def set_parameters(pids: Sequence[Pid], joints: Sequence[str], params: Sequence[msgs.Parameter]) -> str | None:
    """Live gains, all or nothing: every ``<joint>.<field>`` is checked before any is set.
    Returns the reason of the first bad one (nothing changed), or None when all were set."""
    changes = []
    for p in params:
        r = check_parameter(p.name, p.value, joints)
        if isinstance(r, str):
            return r
        changes.append((r[0], r[1], p.value))
    for j, field, value in changes:
        pids[j].set(field, value)
    return None


# ---------------------------------------------------------------- trajectories
class TrajectorySampler:
    """Samples a JointTrajectory at sim time: cubic Hermite between points, in model joint order.

    - ``start_ns``: sim time of ``time_from_start = 0`` (the header stamp, or the receipt time
      when the stamp is zero — the caller decides).
    - ``base``: the setpoint of every model joint when the trajectory arrives. Joints the
      trajectory does not name keep it; if the first point is later than ``time_from_start = 0``
      the trajectory starts from ``base`` at 0 (as ROS controllers do) instead of jumping.
    - Missing velocities: central finite differences at interior points, zero at the first and
      last point (a path starts and ends at rest).
    - Before the start the first point is held, after the end the last point (velocity 0).
    """

    def __init__(
        self,
        traj: msgs.JointTrajectory,
        joints: Sequence[str],
        start_ns: int,
        base: np.ndarray,
        lower: np.ndarray | None = None,
        upper: np.ndarray | None = None,
        tolerance: float = 1e-3,
    ) -> None:
        if not traj.points:
            raise TrajectoryError("trajectory has no points (an empty trajectory means: hold)")
        names = list(traj.joint_names)
        if len(set(names)) != len(names):
            raise TrajectoryError(f"trajectory names a joint twice: {names}")
        unknown = [n for n in names if n not in joints]
        if unknown:
            raise TrajectoryError(f"unknown joint(s) {', '.join(unknown)} (joints: {', '.join(joints)})")
        cols = [list(joints).index(n) for n in names]
        n = len(joints)
        t = [msgs.ns_of(p.time_from_start) * 1e-9 for p in traj.points]
        npts = len(t)
        pos = np.tile(np.asarray(base, float), (npts, 1))
        vel = np.zeros((npts, n))
        has_vel = np.zeros(npts, bool)
        for i, p in enumerate(traj.points):
            if len(p.positions) != len(names):
                raise TrajectoryError(f"points[{i}] has {len(p.positions)} positions for {len(names)} joints")
            pos[i, cols] = p.positions
            if len(p.velocities) == len(names):
                vel[i, cols] = p.velocities
                has_vel[i] = True
            elif p.velocities:
                raise TrajectoryError(f"points[{i}] has {len(p.velocities)} velocities for {len(names)} joints")
        if any(b <= a for a, b in itertools.pairwise(t)):
            raise TrajectoryError("time_from_start is not strictly increasing")
        if not np.all(np.isfinite(pos)) or not np.all(np.isfinite(vel)):
            raise TrajectoryError("trajectory contains non-finite values")
        if lower is not None and upper is not None:
            bad = np.nonzero((pos < lower - tolerance) | (pos > upper + tolerance))
            if bad[0].size:
                i, j = int(bad[0][0]), int(bad[1][0])
                raise TrajectoryError(
                    f"points[{i}] puts {joints[j]} at {pos[i, j]:.4f}, "
                    f"outside its limits [{lower[j]:.3f}, {upper[j]:.3f}]"
                )
        if t[0] > 0.0:
            t.insert(0, 0.0)
            pos = np.vstack([np.asarray(base, float), pos])
            vel = np.vstack([np.zeros(n), vel])
            has_vel = np.concatenate([[True], has_vel])
        self.t = np.asarray(t)
        # Finite differences where velocities were not given (interior: central; ends: rest).
        for i in np.nonzero(~has_vel)[0]:
            if 0 < i < len(t) - 1:
                vel[i] = (pos[i + 1] - pos[i - 1]) / (self.t[i + 1] - self.t[i - 1])
        self.pos = pos
        self.vel = vel
        # the same as Python floats for sample(), every control step: a few joints cost less as floats
        # than as numpy calls on tiny arrays, and the arithmetic is the same, operation for operation
        self._t, self._p, self._v = self.t.tolist(), pos.tolist(), vel.tolist()
        self.start_ns = int(start_ns)
        self.duration = float(self.t[-1])
        self.end_ns = self.start_ns + round(self.duration * 1e9)
        self._zero = np.zeros(n)

    def progress(self, now_ns: int) -> float:
        if self.duration <= 0.0:
            return 1.0 if now_ns >= self.start_ns else 0.0
        return min(max((now_ns - self.start_ns) * 1e-9 / self.duration, 0.0), 1.0)

    def done(self, now_ns: int) -> bool:
        return now_ns >= self.end_ns

    def sample(self, now_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) in model joint order at sim time ``now_ns``."""
        s = (now_ns - self.start_ns) * 1e-9
        t = self._t
        if s < t[0]:
            return self.pos[0], self._zero
        if s >= t[-1]:
            return self.pos[-1], self._zero
        i = bisect.bisect_right(t, s) - 1
        h = t[i + 1] - t[i]
        u = (s - t[i]) / h
        u2, u3 = u * u, u * u * u
        # Cubic Hermite basis and its derivative (d/ds = d/du / h), joint by joint.
        a0, a1, a2, a3 = 2 * u3 - 3 * u2 + 1, (u3 - 2 * u2 + u) * h, -2 * u3 + 3 * u2, (u3 - u2) * h
        b0, b2, b1, b3 = 6 * u2 - 6 * u, -6 * u2 + 6 * u, 3 * u2 - 4 * u + 1, 3 * u2 - 2 * u
        p0, p1, v0, v1 = self._p[i], self._p[i + 1], self._v[i], self._v[i + 1]
        pos = [a0 * x0 + a1 * w0 + a2 * x1 + a3 * w1 for x0, x1, w0, w1 in zip(p0, p1, v0, v1, strict=True)]
        vel = [(b0 * x0 + b2 * x1) / h + b1 * w0 + b3 * w1 for x0, x1, w0, w1 in zip(p0, p1, v0, v1, strict=True)]
        return np.array(pos), np.array(vel)


# ---------------------------------------------------------------- step response figures
@dataclass(frozen=True)
class StepFigures:
    rise_time: float  # 10 % -> 90 % of the step [s]
    peak_time: float  # time of the largest excursion [s]
    overshoot: float  # beyond the target, fraction of the step
    settling_time: float  # last time the error left the band [s]; inf if never settled
    steady_state_error: float  # |error| at the end [same unit as the step]


def step_figures(t: np.ndarray, y: np.ndarray, y0: float, target: float, band: float) -> StepFigures:
    """Classical figures of a step response sampled at times ``t`` (from the step)."""
    step = target - y0
    frac = (np.asarray(y) - y0) / step
    t = np.asarray(t)

    def first(cond: np.ndarray) -> float:
        idx = np.nonzero(cond)[0]
        return float(t[idx[0]]) if idx.size else math.inf

    rise = first(frac >= 0.9) - first(frac >= 0.1)
    k = int(np.argmax(frac))
    outside = np.nonzero(np.abs(np.asarray(y) - target) > band)[0]
    settle = 0.0 if not outside.size else (float(t[outside[-1] + 1]) if outside[-1] + 1 < len(t) else math.inf)
    return StepFigures(
        rise_time=rise,
        peak_time=float(t[k]),
        overshoot=max(0.0, float(frac[k]) - 1.0),
        settling_time=settle,
        steady_state_error=abs(float(y[-1]) - target),
    )
