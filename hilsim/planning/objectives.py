"""Path costs: length, turning angle, and the weighted cost of the improved RRT*.

The improved RRT* (see :mod:`hilsim.planning.improved`) minimises, over a path ``x_0 … x_m``,

    J = w_length · Σ_k |x_{k+1} − x_k|  +  w_turn · Σ_k θ_k,

where ``θ_k`` is the angle between consecutive segments at waypoint ``x_k`` (0 = straight on,
π = reversing). The turn term makes a path with sudden turns more expensive than a slightly
longer but straighter one: the paper's "included angle between two adjacent points".
The same functions measure every planner's output in the benchmark.

OMPL's optimisation objectives cost one motion ``(a, b)`` at a time, without the predecessor of
``a`` that the turn angle needs, and RRT*'s rewiring changes that predecessor; so this cost is
optimised by our own RRT* loop (built on OMPL's state space, sampler and validity checking),
which knows each node's parent when it costs an edge.
"""

from __future__ import annotations

import math

import numpy as np


def segment_lengths(path: np.ndarray) -> np.ndarray:
    p = np.asarray(path, dtype=float)
    return np.linalg.norm(np.diff(p, axis=0), axis=1) if len(p) > 1 else np.zeros(0)


def path_length(path: np.ndarray) -> float:
    """Euclidean length in joint space (rad)."""
    return float(np.sum(segment_lengths(path)))


def turn_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Angle (rad) between segments a→b and b→c; 0 when either is degenerate."""
    u, v = b - a, c - b
    nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    if nu < 1e-12 or nv < 1e-12:
        return 0.0
    return math.acos(max(-1.0, min(1.0, float(np.dot(u, v)) / (nu * nv))))


def turning_angles(path: np.ndarray) -> np.ndarray:
    """Turn angle at every interior waypoint (zero-length segments dropped first)."""
    p = np.asarray(path, dtype=float)
    if len(p) > 1:
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-12])
        p = p[keep]
    return np.array([turn_angle(p[k - 1], p[k], p[k + 1]) for k in range(1, len(p) - 1)])


def summed_turning_angle(path: np.ndarray) -> float:
    return float(np.sum(turning_angles(path)))


def weighted_cost(path: np.ndarray, w_length: float, w_turn: float) -> float:
    return w_length * path_length(path) + w_turn * summed_turning_angle(path)
