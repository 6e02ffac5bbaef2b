"""Status rows: diagnostics (``health/<service>``, diagnostic_msgs/DiagnosticArray) and the log
levels of ``log/<service>`` (rcl_interfaces/Log, whose text row ``RowWriter.message`` writes).

Entity paths:

- ``health/<service>/level`` and ``health/<service>/<value>``: Scalars (numeric values of the status)
- ``health/<service>/status``: TextLog, the state and all values
- ``log/<service>``: TextLog, at the level :func:`log_level` names
"""

from __future__ import annotations

import math

from hilsim.core import msgs
from hilsim.record.rows.common import RowsBase, part

LOG_LEVELS = ((50, "CRITICAL"), (40, "ERROR"), (30, "WARN"), (20, "INFO"), (10, "DEBUG"))
DIAG_LEVELS = {0: "INFO", 1: "WARN", 2: "ERROR", 3: "WARN"}


def log_level(level: int) -> str:
    for threshold, name in LOG_LEVELS:
        if level >= threshold:
            return name
    return "TRACE"


class StatusRows(RowsBase):
    """The diagnostics rows' method of :class:`~hilsim.record.rows.writer.RowWriter`."""

    def _health(self, root: str, msg: msgs.DiagnosticArray) -> None:
        t = msgs.ns_of(msg.header.stamp)
        for st in msg.status:
            base = f"{root}health/{part(st.name or 'unnamed')}"
            self._scalar(f"{base}/level", t, float(st.level))
            for kv in st.values:
                try:
                    v = float(kv.value)
                except ValueError:
                    continue
                if math.isfinite(v):
                    self._scalar(f"{base}/{part(kv.key)}", t, v)
            values = ", ".join(f"{kv.key}={kv.value}" for kv in st.values)
            self._text(f"{base}/status", t, f"{st.message}: {values}", DIAG_LEVELS.get(st.level, "WARN"))
