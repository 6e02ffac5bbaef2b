"""IMU rows (sensor_msgs/Imu of ``truth/imu`` and ``imu``, on every robot).

Entity paths: ``imu/<truth|measured>/<field>/<axis>``, Scalars; field = orientation (x, y, z, w),
angular_velocity, linear_acceleration (x, y, z). The fast path (:mod:`hilsim.record.rows.fast`)
writes the same ones.
"""

from __future__ import annotations

from hilsim.core import msgs
from hilsim.record.rows.common import RowsBase


class ImuRows(RowsBase):
    """The IMU rows' method of :class:`~hilsim.record.rows.writer.RowWriter`."""

    def _imu(self, root: str, source: str, msg: msgs.Imu) -> None:
        ck = (root, source, "imu")
        entities = self._entity_cache.get(ck)
        if entities is None:
            base = f"{root}imu/{source}"
            entities = tuple(f"{base}/orientation/{a}" for a in "xyzw") + tuple(
                f"{base}/{f}/{a}" for f in ("angular_velocity", "linear_acceleration") for a in "xyz"
            )
            self._entity_cache[ck] = entities
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        values = [o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z]
        self._vector(entities, msgs.ns_of(msg.header.stamp), values)
