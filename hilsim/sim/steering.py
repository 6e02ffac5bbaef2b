"""Four-wheel-steer kinematics and wheel odometry: pure functions, no transport, no MuJoCo.

A body twist ``(vx, vy, wz)`` (base_link frame: x forward, y left, z up) moves wheel ``i``, whose
steering axis stands at ``(x_i, y_i)``, with the velocity ``(vx − wz·y_i, vy + wz·x_i)``. Its
steering angle is the direction of that velocity and its traction speed the magnitude over the
wheel radius. The three drive modes of the thesis' robot are cases of this one rule:

- **Ackermann-like** (``vy = 0``, ``wz ≠ 0``, ``vx ≠ 0``): both axles steer in opposite phase about a
  centre of rotation on the rear-front midline, ``R = vx / wz`` to the left;
- **crab** (``wz = 0``): every wheel parallel, at ``atan2(vy, vx)``;
- **turn in place** (``vx = vy = 0``): every wheel tangent to the circle through it.

A steering angle outside ``[lower, upper]`` is not reached by turning further: the wheel is
turned by π the other way and its speed reversed (the same ground velocity). Among the angles
that give the commanded velocity the one nearest the wheel's current angle is chosen, so a wheel
never swings through half a turn to change direction. A wheel asked not to move keeps its angle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

EPS = 1e-9


@dataclass(frozen=True)
class Geometry:
    """Where the wheels are: steering axes ``(x, y)`` in base_link, in wheel order; radius; limits."""

    positions: tuple[tuple[float, float], ...]
    radius: float
    lower: float = -math.pi / 2
    upper: float = math.pi / 2

    @property
    def n(self) -> int:
        return len(self.positions)


def mode(vx: float, vy: float, wz: float, eps: float = 1e-6) -> str:
    """What a twist asks for: ``stop``, ``turn_in_place``, ``crab`` (incl. straight), ``ackermann``
    (vx and wz, no vy) or ``general`` (translation and rotation with a sideways part)."""
    moving = abs(vx) > eps or abs(vy) > eps
    if not moving:
        return "turn_in_place" if abs(wz) > eps else "stop"
    if abs(wz) <= eps:
        return "crab"
    return "ackermann" if abs(vy) <= eps else "general"


def wrap(a: float) -> float:
    """Angle to (−π, π]."""
    a = math.fmod(a + math.pi, 2 * math.pi)
    if a <= 0.0:
        a += 2 * math.pi
    return a - math.pi


def wheel_command(vel_x: float, vel_y: float, current: float, g: Geometry) -> tuple[float, float]:
    """Steering angle and ground speed [m/s] (signed) for one wheel's velocity ``(vel_x, vel_y)``."""
    speed = math.hypot(vel_x, vel_y)
    if speed < EPS:
        return min(max(current, g.lower), g.upper), 0.0
    a = math.atan2(vel_y, vel_x)
    best: tuple[float, float] | None = None
    for cand, sign in ((a, 1.0), (a - math.pi, -1.0), (a + math.pi, -1.0)):
        if g.lower - 1e-12 <= cand <= g.upper + 1e-12:
            cand = min(max(cand, g.lower), g.upper)
            if best is None or abs(cand - current) < abs(best[0] - current):
                best = (cand, sign * speed)
    if best is None:
        # the limits leave this direction out (a range narrower than π): nearest limit, the
        # speed projected onto it
        lim = min((g.lower, g.upper), key=lambda x: abs(wrap(a - x)))
        return lim, speed * math.cos(a - lim)
    return best


def inverse(vx: float, vy: float, wz: float, g: Geometry, current: Sequence[float] | None = None,
            max_wheel_speed: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Steering angles [rad] and traction speeds [rad/s] of every wheel for a body twist.

    ``current``: the wheels' present steering angles (default 0), to choose the nearer of two
    equivalent angles and to keep the angle of a wheel that stands still. When a wheel would
    exceed ``max_wheel_speed`` [rad/s] every wheel is slowed by the same factor (the path stays).
    """
    cur = [0.0] * g.n if current is None else list(current)
    angles = np.zeros(g.n)
    speeds = np.zeros(g.n)
    for i, (x, y) in enumerate(g.positions):
        a, s = wheel_command(vx - wz * y, vy + wz * x, cur[i], g)
        angles[i], speeds[i] = a, s / g.radius
    peak = float(np.max(np.abs(speeds))) if g.n else 0.0
    if peak > max_wheel_speed:
        speeds *= max_wheel_speed / peak
    return angles, speeds


def forward(angles: Sequence[float], speeds: Sequence[float], g: Geometry,
            yaw_rate: float | None = None) -> tuple[float, float, float]:
    """Body twist ``(vx, vy, wz)`` that best explains the wheels' angles and speeds [rad/s]
    (least squares over the 2·n wheel velocity components): wheel odometry. With ``yaw_rate``
    (e.g. an IMU's, which a slipping wheel does not fool) only ``vx, vy`` are fitted."""
    if yaw_rate is not None:
        vxs, vys = [], []
        for (x, y), a, w in zip(g.positions, angles, speeds, strict=True):
            v = w * g.radius
            vxs.append(v * math.cos(a) + yaw_rate * y)
            vys.append(v * math.sin(a) - yaw_rate * x)
        return float(np.mean(vxs)), float(np.mean(vys)), float(yaw_rate)
    rows, rhs = [], []
    for (x, y), a, w in zip(g.positions, angles, speeds, strict=True):
        v = w * g.radius
        rows.append((1.0, 0.0, -y))
        rhs.append(v * math.cos(a))
        rows.append((0.0, 1.0, x))
        rhs.append(v * math.sin(a))
    sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    return float(sol[0]), float(sol[1]), float(sol[2])


def integrate(pose: tuple[float, float, float], twist: tuple[float, float, float], dt: float) -> tuple[
        float, float, float]:
    """Planar pose ``(x, y, yaw)`` after moving with a body twist for ``dt`` (exact for a constant twist)."""
    x, y, th = pose
    vx, vy, wz = twist
    dth = wz * dt
    if abs(dth) < 1e-9:
        dx, dy = vx * dt, vy * dt
    else:  # the arc: body-frame displacement of a constant twist
        s, c = math.sin(dth), math.cos(dth)
        dx = (vx * s - vy * (1.0 - c)) / wz
        dy = (vx * (1.0 - c) + vy * s) / wz
    ct, st = math.cos(th), math.sin(th)
    return x + ct * dx - st * dy, y + st * dx + ct * dy, wrap(th + dth)


def traction_scale(angle_error: float) -> float:
    """How much of the traction speed to apply while a wheel is still steering: ``cos`` of the
    steering error, none beyond 90° (a wheel that points the wrong way must not drive)."""
    return max(0.0, math.cos(angle_error))
