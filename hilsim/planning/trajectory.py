"""Time parameterisation of a geometric joint path with ruckig, and conversion to JointTrajectory.

A planner's path is a polyline in joint space whose *segments* were collision-checked. To keep
the timed trajectory on exactly those segments, every segment is timed on its own, from rest to
rest: the motion is ``q(t) = a + u·s(t)`` with ``u`` the unit direction of the segment and
``s(t)`` a jerk-limited one-dimensional ruckig profile from 0 to the segment length. The limits
of ``s`` are the tightest of the joint limits projected on the direction
(``ṡ_max = min_i v_i / |u_i|``, same for acceleration and jerk), so each joint respects its own
velocity, acceleration and jerk limits. Stopping at the waypoints costs some time; in exchange
the executed path never leaves the checked polyline (no blending corner cuts an obstacle).
Fewer, straighter segments (the improved RRT*) therefore also mean a faster trajectory.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from hilsim.core import msgs


class TrajectoryError(ValueError):
    """The path cannot be timed (bad limits, ruckig failure)."""


@dataclass
class TimedTrajectory:
    """Samples of a timed joint trajectory: ``t`` (s, from 0), ``q``, ``qd``, ``qdd`` (rows = samples)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    knots: np.ndarray  # time at which each waypoint of the path is reached (at rest)

    @property
    def duration(self) -> float:
        return float(self.t[-1]) if len(self.t) else 0.0


def _segment_profile(length: float, v: float, a: float, j: float) -> Trajectory:
    otg = Ruckig(1)
    inp = InputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [length]
    inp.max_velocity = [v]
    inp.max_acceleration = [a]
    inp.max_jerk = [j]
    traj = Trajectory(1)
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        raise TrajectoryError(f"ruckig failed on a segment of length {length:.4f}: {res}")
    return traj


def time_parameterize(
    path: np.ndarray,
    vmax: np.ndarray,
    amax: np.ndarray,
    jmax: np.ndarray,
    dt: float = 0.01,
) -> TimedTrajectory:
    """Timed trajectory through every waypoint of ``path`` (rows), at rest at each waypoint.

    Samples every ``dt`` seconds within each segment plus every waypoint exactly.
    """
    path = np.asarray(path, dtype=float)
    if path.ndim != 2 or len(path) < 1:
        raise TrajectoryError("path must be a non-empty 2-D array (waypoints × joints)")
    n = path.shape[1]
    vmax, amax, jmax = (np.broadcast_to(np.asarray(x, dtype=float), (n,)) for x in (vmax, amax, jmax))
    if np.any(vmax <= 0) or np.any(amax <= 0) or np.any(jmax <= 0):
        raise TrajectoryError("velocity, acceleration and jerk limits must be positive")
    ts, qs, qds, qdds = [0.0], [path[0]], [np.zeros(n)], [np.zeros(n)]
    t0 = 0.0
    knots = [0.0]
    for a, b in itertools.pairwise(path):
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 1e-9:
            knots.append(t0)
            continue
        u = d / length
        with np.errstate(divide="ignore"):
            au = np.abs(u)
            v = float(np.min(np.where(au > 1e-12, vmax / au, np.inf)))
            acc = float(np.min(np.where(au > 1e-12, amax / au, np.inf)))
            jerk = float(np.min(np.where(au > 1e-12, jmax / au, np.inf)))
        prof = _segment_profile(length, v, acc, jerk)
        dur = float(prof.duration)
        k = max(1, int(np.ceil(dur / dt - 1e-9)))
        for i in range(1, k + 1):
            tau = dur if i == k else i * dt
            p, vel, ac = prof.at_time(tau)
            s = min(max(p[0], 0.0), length)
            ts.append(t0 + tau)
            qs.append(b.copy() if i == k else a + u * s)
            qds.append(np.zeros(n) if i == k else u * vel[0])
            qdds.append(np.zeros(n) if i == k else u * ac[0])
        t0 += dur
        knots.append(t0)
    return TimedTrajectory(np.array(ts), np.array(qs), np.array(qds), np.array(qdds), np.array(knots))


def truncate(traj: TimedTrajectory, t_end: float) -> TimedTrajectory:
    """The trajectory up to and including time ``t_end`` (a knot, so it ends at rest)."""
    k = int(np.searchsorted(traj.t, t_end + 1e-9))
    return TimedTrajectory(traj.t[:k], traj.q[:k], traj.qd[:k], traj.qdd[:k], traj.knots[traj.knots <= t_end + 1e-9])


def _projected(u: np.ndarray, lim: np.ndarray) -> float:
    """Largest rate along unit direction ``u`` that keeps every joint within ``lim``."""
    au = np.abs(u)
    with np.errstate(divide="ignore"):
        return float(np.min(np.where(au > 1e-12, lim / au, np.inf)))


def stop_on_segment(
    traj: TimedTrajectory, t: float, vmax: np.ndarray, amax: np.ndarray, jmax: np.ndarray, dt: float = 0.01
) -> TimedTrajectory:
    """A jerk-limited stop from the state of ``traj`` at time ``t``, on the segment being travelled.

    Each segment is a 1-D motion ``a + u·s``; braking ``s`` to rest with ruckig's velocity
    interface keeps the arm on the same collision-checked segment. If braking would run past the
    segment's end, the original trajectory already stops sooner: it is cut at that waypoint.
    Times of the result start at 0 = ``t``.
    """
    i = int(np.searchsorted(traj.knots, t, side="right"))
    if i >= len(traj.knots) or t <= 0:
        k = min(int(np.searchsorted(traj.t, t)), len(traj.t) - 1)
        return TimedTrajectory(np.zeros(1), traj.q[k:k + 1], np.zeros_like(traj.q[k:k + 1]),
                               np.zeros_like(traj.q[k:k + 1]), np.zeros(1))
    k0 = int(np.searchsorted(traj.t, traj.knots[i - 1] - 1e-9))
    k1 = int(np.searchsorted(traj.t, traj.knots[i] - 1e-9))
    a, b = traj.q[k0], traj.q[k1]
    length = float(np.linalg.norm(b - a))
    k = min(int(np.searchsorted(traj.t, t)), k1)
    if length < 1e-9:
        return _shift(truncate(traj, traj.knots[i]), k)
    u = (b - a) / length
    inp = InputParameter(1)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position = [float((traj.q[k] - a) @ u)]
    inp.current_velocity = [float(traj.qd[k] @ u)]
    inp.current_acceleration = [float(traj.qdd[k] @ u)]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    inp.max_velocity = [_projected(u, vmax)]
    inp.max_acceleration = [_projected(u, amax)]
    inp.max_jerk = [_projected(u, jmax)]
    prof = Trajectory(1)
    if Ruckig(1).calculate(inp, prof) not in (Result.Working, Result.Finished):
        return _shift(truncate(traj, traj.knots[i]), k)
    dur = float(prof.duration)
    if prof.at_time(dur)[0][0] > length:
        return _shift(truncate(traj, traj.knots[i]), k)
    n = max(1, int(np.ceil(dur / dt - 1e-9)))
    ts = [0.0] + [dur if j == n else j * dt for j in range(1, n + 1)]
    qs, qds, qdds = [], [], []
    for tau in ts:
        p, v, acc = prof.at_time(tau)
        qs.append(a + u * min(max(p[0], 0.0), length))
        qds.append(u * (0.0 if tau == dur else v[0]))
        qdds.append(u * (0.0 if tau == dur else acc[0]))
    return TimedTrajectory(np.array(ts), np.array(qs), np.array(qds), np.array(qdds), np.array([dur]))


def _shift(traj: TimedTrajectory, k: int) -> TimedTrajectory:
    """The part of ``traj`` from sample ``k`` on, with time restarting at 0."""
    t0 = traj.t[k]
    return TimedTrajectory(traj.t[k:] - t0, traj.q[k:], traj.qd[k:], traj.qdd[k:], traj.knots[traj.knots >= t0] - t0)


def to_msg(traj: TimedTrajectory, joint_names: list[str], start_ns: int) -> msgs.JointTrajectory:
    """JointTrajectory whose header.stamp (sim time) is when ``time_from_start = 0`` applies."""
    pts = []
    last = -1
    for t, q, qd, qdd in zip(traj.t, traj.q, traj.qd, traj.qdd, strict=True):
        ns = round(t * 1e9)
        if ns <= last:  # keep time_from_start strictly increasing after rounding
            continue
        last = ns
        pts.append(
            msgs.JointTrajectoryPoint(
                positions=[float(x) for x in q],
                velocities=[float(x) for x in qd],
                accelerations=[float(x) for x in qdd],
                time_from_start=msgs.Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
            )
        )
    return msgs.JointTrajectory(header=msgs.header(start_ns), joint_names=list(joint_names), points=pts)


def path_msg(path: np.ndarray, joint_names: list[str], stamp_ns: int) -> msgs.JointTrajectory:
    """The geometric path as a JointTrajectory (waypoints only, time_from_start = index · 1 s) for the logger."""
    pts = [
        msgs.JointTrajectoryPoint(positions=[float(x) for x in q], time_from_start=msgs.Duration(sec=i))
        for i, q in enumerate(np.asarray(path))
    ]
    return msgs.JointTrajectory(header=msgs.header(stamp_ns), joint_names=list(joint_names), points=pts)


def joint_path_lengths(q: np.ndarray) -> np.ndarray:
    """The arm paper's P_i = Σ_j |q_i^{j+1} − q_i^j| for each joint (columns of q, the timed samples)."""
    q = np.asarray(q, float)
    return np.sum(np.abs(np.diff(q, axis=0)), axis=0) if len(q) > 1 else np.zeros(q.shape[1])


def acceleration_variance(qdd: np.ndarray) -> np.ndarray:
    """The arm paper's A_i = D(a_i): population variance of each joint's acceleration samples."""
    return np.var(np.asarray(qdd, float), axis=0)
