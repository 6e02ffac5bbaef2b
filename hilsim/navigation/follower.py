"""Path following: a planned SE(2) path and the robot's pose in, a body twist (vx, vy, wz) out.

Pure pursuit adapted to a four-wheel-steer base, which can move sideways as well as turn: the
path is cut at its cusps (where a Reeds–Shepp path changes between forwards and backwards) into
segments followed one after the other. On a segment the robot heads for the *lookahead point*,
``lookahead`` metres of path beyond the point of the segment nearest to it: the velocity points
there (expressed in the body frame, so a sideways error is corrected by crabbing, not only by
turning), and the yaw rate turns the heading towards the path's own heading at the nearest
point (``k_yaw`` · error). The speed is limited by ``max_speed`` and by a braking profile
``√(2·accel·d)`` to the end of the segment (a cusp is passed at rest), never below ``min_speed``
while moving. Within ``cusp_tolerance`` of a cusp the next segment starts.

At the goal: within ``xy_tolerance`` of the final point translation stops; with a final yaw,
the robot then turns in place until within ``yaw_tolerance``; then :attr:`Follower.done`.
Everything is a pure function of the path and the poses given, so a lockstep run repeats exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hilsim.navigation.planner import directions


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class FollowerParams:
    max_speed: float = 0.6  # m/s
    min_speed: float = 0.06  # m/s while still moving
    max_yaw_rate: float = 1.0  # rad/s
    accel: float = 0.4  # m/s², braking profile
    lookahead: float = 0.4  # m
    k_yaw: float = 2.0  # 1/s
    k_final: float = 1.0  # 1/s: speed per metre to the goal in the last stretch
    xy_tolerance: float = 0.06  # m
    yaw_tolerance: float = 0.05  # rad
    cusp_tolerance: float = 0.1  # m


def split_at_cusps(path: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """Segments of constant direction, each with its sign (+1 forwards, −1 backwards); a cusp
    point ends one segment and starts the next."""
    if len(path) < 2:
        return [(path, 1)]
    d = directions(path)
    out, start = [], 0
    for i in range(1, len(d)):
        if d[i] != d[i - 1]:
            out.append((path[start:i + 1], int(d[i - 1])))
            start = i
    out.append((path[start:], int(d[-1])))
    return out


class Follower:
    def __init__(self, path: np.ndarray, params: FollowerParams, *, final_yaw: float | None = None) -> None:
        if len(path) < 1:
            raise ValueError("empty path")
        self.p = params
        self.path = np.asarray(path, float)
        self.goal = self.path[-1, :2].copy()
        self.final_yaw = final_yaw
        self.segments = split_at_cusps(self.path)
        self.k = 0  # current segment
        self.i = 0  # nearest index on it
        self.arc = [np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(s[:, :2], axis=0).T))])
                    for s, _ in self.segments]
        self.total = float(sum(a[-1] for a in self.arc))
        self.done = False
        self.off_path = 0.0  # distance to the nearest point of the current segment at the last step
        self.at_goal = False  # position reached (the final yaw may still be turning)

    @property
    def progress(self) -> float:
        """Fraction of the path's length behind the robot (by its nearest point)."""
        if self.total <= 0:
            return 1.0
        behind = sum(a[-1] for a in self.arc[:self.k]) + self.arc[self.k][self.i]
        return float(min(1.0, behind / self.total))

    def _nearest(self, x: float, y: float) -> None:
        seg = self.segments[self.k][0]
        # search forwards only (a path may pass near itself), a few lookaheads at most
        j1 = min(len(seg), self.i + 1 + max(8, int(3 * self.p.lookahead / max(self._spacing(), 1e-3))))
        d = np.hypot(seg[self.i:j1, 0] - x, seg[self.i:j1, 1] - y)
        self.i += int(np.argmin(d))

    def _spacing(self) -> float:
        a = self.arc[self.k]
        return float(a[-1] / max(len(a) - 1, 1))

    def step(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """The body twist (vx, vy, wz) for the robot at (x, y, yaw)."""
        p = self.p
        if self.done:
            return 0.0, 0.0, 0.0
        last = self.k == len(self.segments) - 1
        seg, sign = self.segments[self.k]
        if not last and math.hypot(seg[-1, 0] - x, seg[-1, 1] - y) < p.cusp_tolerance:
            self.k, self.i = self.k + 1, 0
            seg, sign = self.segments[self.k]
            last = self.k == len(self.segments) - 1
        to_goal = math.hypot(self.goal[0] - x, self.goal[1] - y)
        if last and (self.at_goal or to_goal < p.xy_tolerance):
            self.at_goal = True
            if self.final_yaw is None:
                self.done = True
                return 0.0, 0.0, 0.0
            err = wrap(self.final_yaw - yaw)
            if abs(err) < p.yaw_tolerance:
                self.done = True
                return 0.0, 0.0, 0.0
            wz = max(-p.max_yaw_rate, min(p.max_yaw_rate, p.k_yaw * err))
            return 0.0, 0.0, math.copysign(max(abs(wz), 0.1), wz)
        self._nearest(x, y)
        self.off_path = math.hypot(seg[self.i, 0] - x, seg[self.i, 1] - y)
        arc = self.arc[self.k]
        s_ahead = arc[self.i] + p.lookahead
        j = min(int(np.searchsorted(arc, s_ahead)), len(seg) - 1)
        tx, ty = seg[j, 0], seg[j, 1]
        remaining = float(arc[-1] - arc[self.i])
        dist_end = math.hypot(seg[-1, 0] - x, seg[-1, 1] - y)
        if j == len(seg) - 1:
            remaining = dist_end  # the end is within the lookahead: aim at it
        v = min(p.max_speed, math.sqrt(2 * p.accel * max(remaining, 0.0)))
        if last:
            v = min(v, p.k_final * to_goal)
        v = max(v, p.min_speed)
        ex, ey = tx - x, ty - y
        n = math.hypot(ex, ey)
        if n < 1e-9:
            ex, ey, n = math.cos(yaw) * sign, math.sin(yaw) * sign, 1.0
        c, s = math.cos(yaw), math.sin(yaw)
        vx = v * (c * ex + s * ey) / n
        vy = v * (-s * ex + c * ey) / n
        yaw_ref = seg[min(self.i + 1, len(seg) - 1), 2] if len(seg) > 1 else seg[0, 2]
        wz = max(-p.max_yaw_rate, min(p.max_yaw_rate, p.k_yaw * wrap(yaw_ref - yaw)))
        return vx, vy, wz
