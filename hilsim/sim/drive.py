"""A servo drive's closed-loop response: what ``hilsim identify`` fits, and what a twin's joint is simulated with.

A drive in position control (ODrive control mode 3, input passthrough: what the controller sends a
``position`` joint) takes a setpoint ``p_in`` with velocity feed-forward ``v_in``, acts on it after a
dead time, and moves as a closed position loop with limits::

    order 2:  a = ω_n²·(p_in − p) + 2ζω_n·(v_in − v)
    order 1:  a = (v_in + (p_in − p)/τ − v) / h           (the velocity follows at once, per substep h)
    a  clipped to ±max_acceleration, then  v ← clip(v + a·h, ±max_velocity),  p ← p + v·h

integrated semi-implicitly in substeps of at most :data:`SUBSTEP`, a setpoint taking effect exactly
at its stamp plus the dead time (inside a substep if need be, so the response depends smoothly on
the dead time: the fit needs that). A velocity drive (control mode 2) has no position loop:
``a = 2ζω_n·(v_in − v)`` (order 2) or ``(v_in − v)/τ`` (order 1), the same limits.

What it reports is what its encoder says: the position rounded to ``resolution`` and the velocity,
every ``period`` seconds (0: at every step), held in between.

Pure Python, no MuJoCo: :class:`DriveModel` is stepped by :class:`hilsim.sim.world.World` for a joint
with ``joints.<name>.drive`` (the twin), and :func:`simulate` runs the same arithmetic over a recorded
command sequence for the fit (:mod:`hilsim.tools.tuning.identify`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from hilsim.core.config import DriveConfig

SUBSTEP = 0.001  # [s] the longest integration substep (the twin and the fit alike)


def law(cfg: DriveConfig, velocity_mode: bool = False) -> tuple[float, float, float, float, float, int, bool]:
    """The constants of the loop, unpacked once: (k_p, k_v, τ, max_velocity, max_acceleration, order, velocity)."""
    if cfg.order == 2:
        wn, z = cfg.natural_frequency, cfg.damping_ratio
        return wn * wn, 2.0 * z * wn, 0.0, cfg.max_velocity, cfg.max_acceleration, 2, velocity_mode
    return 0.0, 0.0, cfg.time_constant, cfg.max_velocity, cfg.max_acceleration, 1, velocity_mode


def integrate(p: float, v: float, p_in: float, v_in: float, span: float,
              k: tuple[float, float, float, float, float, int, bool]) -> tuple[float, float]:
    """The drive's state after ``span`` seconds with a constant input (substeps of at most SUBSTEP)."""
    if span <= 0.0:
        return p, v
    kp, kv, tau, vmax, amax, order, vel_mode = k
    n = max(1, math.ceil(span / SUBSTEP - 1e-9))
    h = span / n
    # one loop per law, the branches out of it: the fit runs this some 10⁷ times
    if order == 2 and not vel_mode:
        for _ in range(n):
            a = kp * (p_in - p) + kv * (v_in - v)
            a = amax if a > amax else -amax if a < -amax else a
            v += a * h
            v = vmax if v > vmax else -vmax if v < -vmax else v
            p += v * h
        return p, v
    for _ in range(n):
        if order == 2:
            a = kv * (v_in - v)
        elif vel_mode:
            a = (v_in - v) / tau
        else:
            a = (v_in + (p_in - p) / tau - v) / h
        a = amax if a > amax else -amax if a < -amax else a
        v += a * h
        v = vmax if v > vmax else -vmax if v < -vmax else v
        p += v * h
    return p, v


def quantise(x: float, q: float) -> float:
    return round(x / q) * q if q > 0.0 else x


class DriveModel:
    """One simulated drive, advanced in time: setpoints in (stamped), the encoder's report out."""

    def __init__(self, cfg: DriveConfig, p0: float, velocity_mode: bool = False) -> None:
        self.cfg = cfg
        self.k = law(cfg, velocity_mode)
        self.t = 0.0  # [s] the state's time
        self.p, self.v = p0, 0.0
        self.p_in, self.v_in = p0, 0.0  # the setpoint in force: hold where it starts
        self.queue: deque[tuple[float, float, float]] = deque()  # (when it acts [s], p_in, v_in)
        self.out_p, self.out_v = quantise(p0, cfg.resolution), 0.0
        self.next_report = 0.0

    def command(self, stamp: float, p_in: float, v_in: float) -> None:
        """A setpoint stamped ``stamp`` [s]: it acts at ``stamp + dead_time`` (at once if that has passed)."""
        self.queue.append((stamp + self.cfg.dead_time, p_in, v_in))

    def advance(self, t_end: float) -> None:
        """Move the drive on to ``t_end`` [s], taking each setpoint at its time; report if one is due."""
        q = self.queue
        while q and q[0][0] <= t_end:
            te, pi, vi = q.popleft()
            if te > self.t:
                self.p, self.v = integrate(self.p, self.v, self.p_in, self.v_in, te - self.t, self.k)
                self.t = te
            self.p_in, self.v_in = pi, vi
        self.p, self.v = integrate(self.p, self.v, self.p_in, self.v_in, t_end - self.t, self.k)
        self.t = t_end
        period = self.cfg.period
        if period <= 0.0 or t_end >= self.next_report - 1e-9:
            self.out_p, self.out_v = quantise(self.p, self.cfg.resolution), self.v
            if period > 0.0:
                self.next_report = (math.floor(t_end / period + 1e-9) + 1) * period


def simulate(cfg: DriveConfig, cmd_t: Sequence[float], cmd_p: Sequence[float], cmd_v: Sequence[float],
             out_t: Sequence[float], p0: float, v0: float = 0.0, velocity_mode: bool = False) -> np.ndarray:
    """The drive's (continuous, unquantised) position at each of ``out_t`` [s] (a velocity drive: its
    velocity), given setpoints ``(cmd_p, cmd_v)`` stamped ``cmd_t`` (both increasing), starting at
    ``p0, v0`` at ``out_t[0]`` holding ``p0``: :class:`DriveModel`'s arithmetic, operation for operation
    (a test holds them to the same bits), without its queue and with the common law's substeps inline:
    the fit runs this hundreds of times."""
    k = law(cfg, velocity_mode)
    kp, kv, _, vmax, amax, order, vel_mode = k
    fast = order == 2 and not vel_mode
    d = cfg.dead_time
    ct = [t + d for t in cmd_t]
    cp, cv = list(cmd_p), list(cmd_v)
    n_cmd = len(ct)
    out = np.empty(len(out_t))
    p, v, p_in, v_in = p0, v0, p0, 0.0
    t = float(out_t[0]) if len(out_t) else 0.0
    i = 0
    while i < n_cmd and ct[i] <= t:  # setpoints that act before the start: the last one is in force
        p_in, v_in = cp[i], cv[i]
        i += 1
    ceil = math.ceil
    for j, te in enumerate(out_t):
        while True:
            nxt = ct[i] if i < n_cmd and ct[i] <= te else te  # the next event: a setpoint acts, or the output
            span = nxt - t
            if span > 0.0:
                if fast:  # integrate(), inline
                    n = max(1, ceil(span / SUBSTEP - 1e-9))
                    h = span / n
                    for _ in range(n):
                        a = kp * (p_in - p) + kv * (v_in - v)
                        a = amax if a > amax else -amax if a < -amax else a
                        v += a * h
                        v = vmax if v > vmax else -vmax if v < -vmax else v
                        p += v * h
                else:
                    p, v = integrate(p, v, p_in, v_in, span, k)
                t = nxt
            if nxt == te and not (i < n_cmd and ct[i] <= te and ct[i] == te):
                break
            p_in, v_in = cp[i], cv[i]
            i += 1
        out[j] = v if velocity_mode else p
    return out
