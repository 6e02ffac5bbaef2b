"""The planner's ROS 2 action ``hilsim_msgs/action/Move`` at ``/<robot>/move``.

A part of :class:`hilsim.services.planner.PlannerService` (one of its bases, not a service of its own),
served through :mod:`hilsim.services.ros2_action`: a goal (a MoveGoal; its ``goal_id`` string, if empty,
becomes the action goal's UUID) goes through the planner's ``on_goal``, a cancel through the same cancel
as ``planner/cancel`` (:mod:`hilsim.services.planner_goals`); the action's feedback is the MoveFeedback
and its result the MoveResult published on ``planner/feedback`` / ``planner/result``. A goal ``on_goal``
refuses is accepted and aborted at once with its error code, as move_group reports a bad request in its
result.

Serves the action's keys as a node on rmw_zenoh has them (``…/move/_action/send_goal``, ``cancel_goal``,
``get_result``) and writes its ``feedback`` and ``status`` (:class:`~hilsim.services.ros2_action.ActionServer`).
"""

from __future__ import annotations

from hilsim.core import msgs
from hilsim.services.planner_goals import PlannerGoals
from hilsim.services.ros2_action import goal_text

MOVE_ACTION = "move"  # /<robot>/move
MOVE_ACTION_TYPE = "hilsim_msgs/action/Move"


class PlannerAction(PlannerGoals):
    """Move goals as a ROS 2 action."""

    # ------------------------------------------------------------------ the same, as a ROS 2 action
    def on_move_goal(self, action_id: bytes, g: msgs.MoveGoal) -> bool:
        """An action goal: accepted, then run as :meth:`on_goal` runs a goal of ``planner/goal``, or
        aborted at once with the code of the reason it refuses it."""
        assert self.move is not None
        g.goal_id = g.goal_id or goal_text(action_id)
        try:
            msgs.validate(g, n_joints=self.n)  # what decoding checks of a goal on planner/goal
            resp = self.on_goal(g) if g.goal_id not in self.action_goals else self._reject(
                f"INVALID_GOAL: goal id {g.goal_id!r} is running already", g.goal_id)
        except msgs.BadMessage as e:
            resp = self._reject(f"INVALID_GOAL: {e}", g.goal_id)
        if not resp.accepted:
            code = getattr(msgs, resp.reason.split(":", 1)[0], msgs.INVALID_GOAL)
            self.move.finish(action_id, msgs.MoveResult(header=msgs.header(self.sim_ns), goal_id=g.goal_id,
                                                        error_code=code, message=resp.reason), False)
            return True
        self.action_goals[resp.goal_id] = action_id
        return True

    def on_move_cancel(self, action_id: bytes) -> bool:
        gid = next((k for k, v in self.action_goals.items() if v == action_id), None)
        return gid is not None and self.on_cancel(msgs.CancelRequest(goal_id=gid)).accepted
