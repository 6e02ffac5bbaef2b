"""Task rows: the results of planner and navigator goals (MoveResult); their feedback
(MoveFeedback) is two rows ``RowWriter.message`` writes itself.

Entity paths: ``<planner|navigator>/result``: TextLog (success or failure, code, planner,
planning time, points, execution error; ``planner: auto``'s choice and why), ``…/result/planning_time``: Scalars; from
``RowWriter.message``: ``<planner|navigator>/feedback`` TextLog and ``…/feedback/progress`` Scalars.
"""

from __future__ import annotations

from hilsim.core import msgs
from hilsim.record.rows.common import RowsBase


class TaskRows(RowsBase):
    """The task rows' method of :class:`~hilsim.record.rows.writer.RowWriter`."""

    def _result(self, root: str, topic: str, msg: msgs.MoveResult) -> None:
        t = msgs.ns_of(msg.header.stamp)
        err = max((abs(e) for e in msg.execution_error), default=0.0)
        text = (
            f"{msg.goal_id}: {'success' if msg.success else 'failure'} (code {msg.error_code}) {msg.message}; "
            f"planner {msg.planner}, planning {msg.planning_time:.3f} s, "
            f"{len(msg.trajectory.points)} points, max execution error {err:.4f}"
            + (f"; {msg.choice}" if msg.choice else "")
        )
        self._text(f"{root}{topic}", t, text, "INFO" if msg.success else "WARN")
        self._scalar(f"{root}{topic}/planning_time", t, msg.planning_time)
