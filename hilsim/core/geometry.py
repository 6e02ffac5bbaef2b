"""Small rigid-body helpers shared by services (kept in one place, no transport)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def heading(w: float, x: float, y: float, z: float) -> float:
    """Yaw [rad] of the unit quaternion (w, x, y, z): its rotation about z, ZYX convention."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_of(q: Any) -> float:
    """Yaw [rad] of a quaternion message (anything with ``w``, ``x``, ``y``, ``z``)."""
    return heading(q.w, q.x, q.y, q.z)


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix of fixed-axis roll (x), pitch (y), yaw (z), as URDF uses: R = Rz·Ry·Rx."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
