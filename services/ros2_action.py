"""A ROS 2 action served by a hilsim service, as rcl_action / rclcpp_action serve one over rmw_zenoh.

An action ``<name>`` of type ``<pkg>/action/<A>`` is three services and two topics
(:meth:`hilsim.core.keys.Keys.action`): ``<name>/_action/send_goal`` (``<A>_SendGoal``: a goal id and
the goal → accepted, stamp), ``<name>/_action/cancel_goal`` (``action_msgs/srv/CancelGoal``),
``<name>/_action/get_result`` (``<A>_GetResult``: a goal id → status and result, answered when the goal
has ended: the query is held until then, as rclcpp clients ask right after acceptance), and the topics
``<name>/_action/feedback`` (``<A>_FeedbackMessage``) and ``<name>/_action/status``
(``action_msgs/msg/GoalStatusArray``, transient-local, published whenever a goal's state changes).

The owner (the controller, the planner) decides and executes: ``on_goal(goal_id, goal)`` accepts
(True; the goal is then executing) or rejects it, ``on_cancel(goal_id)`` accepts a cancel request (the
goal is then canceling); it reports with :meth:`ActionServer.feedback` and ends the goal with
:meth:`ActionServer.finish` (succeeded, else canceled if a cancel was accepted, else aborted). Goal
states follow rcl_action's machine (accepted → executing → canceling → succeeded / canceled /
aborted). Everything runs under the service's lock (the queries' handlers do, and so must the owner's
calls), so the table of goals needs no lock of its own.
"""

from __future__ import annotations

import uuid as uuidlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hilsim.core import msgs
from hilsim.core.keys import CANCEL_GOAL_SERVICE
from hilsim.core.msgs.control import (
    CANCEL_ERROR_GOAL_TERMINATED,
    CANCEL_ERROR_NONE,
    CANCEL_ERROR_REJECTED,
    CANCEL_ERROR_UNKNOWN_GOAL_ID,
    STATUS_ABORTED,
    STATUS_ACCEPTED,
    STATUS_CANCELED,
    STATUS_CANCELING,
    STATUS_EXECUTING,
    STATUS_SUCCEEDED,
    STATUS_UNKNOWN,
)
from hilsim.core.service import Service

TERMINAL = frozenset({STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED})
ZERO_ID = bytes(16)
KEEP_ENDED = 32  # ended goals kept (their results answer late get_result calls), the oldest dropped first


def goal_text(goal_id: bytes) -> str:
    """A goal id as people read it (a UUID's canonical form)."""
    return str(uuidlib.UUID(bytes=bytes(goal_id)))


def _classes() -> dict[str, type]:
    return {msgs.type_name(c): c for c in vars(msgs).values()
            if isinstance(c, type) and issubclass(c, msgs.IdlStruct) and c is not msgs.IdlStruct}


@dataclass
class ServerGoal:
    goal_id: bytes
    goal: Any
    stamp: msgs.Time  # when it was accepted (sim time)
    status: int = STATUS_ACCEPTED
    result: Any = None
    waiting: list[Callable[[Any], None]] = field(default_factory=list)  # held get_result queries


class ActionServer:
    """Serves action ``name`` (below the service's namespace, or absolute) of type ``action_type``."""

    def __init__(
        self,
        svc: Service,
        name: str,
        action_type: str,
        on_goal: Callable[[bytes, Any], bool],
        on_cancel: Callable[[bytes], bool],
    ) -> None:
        self.svc = svc
        self.keys = svc.keys.action(name, action_type)
        self.name = self.keys.name
        self.on_goal = on_goal
        self.on_cancel = on_cancel
        cls = _classes()
        try:
            self._send_goal_response = cls[f"{action_type}_SendGoal_Response"]
            self._get_result_response = cls[f"{action_type}_GetResult_Response"]
            self._result = cls[f"{action_type}_Result"]
            self._feedback_message = cls[f"{action_type}_FeedbackMessage"]
            send_goal_request = cls[f"{action_type}_SendGoal_Request"]
            get_result_request = cls[f"{action_type}_GetResult_Request"]
        except KeyError as e:
            raise ValueError(f"no message class of {e} in hilsim.core.msgs: cannot serve {action_type}") from None
        self.goals: dict[bytes, ServerGoal] = {}
        base = f"{self.name}/_action"
        keys = [
            svc.ros2_service(f"{base}/send_goal", f"{action_type}_SendGoal", send_goal_request, self._on_send_goal),
            svc.ros2_service(f"{base}/cancel_goal", CANCEL_GOAL_SERVICE, msgs.CancelGoalRequest, self._on_cancel),
            svc.ros2_service(f"{base}/get_result", f"{action_type}_GetResult", get_result_request,
                             self._on_get_result),
        ]
        assert keys == [self.keys.send_goal, self.keys.cancel_goal, self.keys.get_result], keys
        self.pub_feedback = svc.publisher(self.keys.feedback)
        # rcl_action's status QoS: reliable, transient local, keep last 1 (a client that comes later
        # gets the current array, as from a ROS 2 server)
        self.pub_status = svc.publisher(self.keys.status, latched=True)

    # ------------------------------------------------------------------ the owner's side
    def active(self, goal_id: bytes) -> bool:
        g = self.goals.get(goal_id)
        return g is not None and g.status not in TERMINAL

    def status(self, goal_id: bytes) -> int:
        g = self.goals.get(goal_id)
        return STATUS_UNKNOWN if g is None else g.status

    def feedback(self, goal_id: bytes, feedback: Any) -> None:
        if self.active(goal_id):
            self.pub_feedback.put(self._feedback_message(goal_id=msgs.UUID(uuid=goal_id), feedback=feedback))

    def finish(self, goal_id: bytes, result: Any, success: bool) -> None:
        """End a goal: succeeded, or else canceled (a cancel request was accepted) or aborted. The held
        get_result queries are answered; the status array is published."""
        g = self.goals.get(goal_id)
        if g is None or g.status in TERMINAL:
            return
        g.status = STATUS_SUCCEEDED if success else STATUS_CANCELED if g.status == STATUS_CANCELING else STATUS_ABORTED
        g.result = result
        response = self._get_result_response(status=g.status, result=result)
        waiting, g.waiting = g.waiting, []
        for reply in waiting:
            reply(response)
        self._prune()
        self.publish_status()

    def publish_status(self) -> None:
        self.pub_status.put(msgs.GoalStatusArray(status_list=[
            msgs.GoalStatus(goal_info=msgs.GoalInfo(goal_id=msgs.UUID(uuid=g.goal_id), stamp=g.stamp), status=g.status)
            for g in self.goals.values()
        ]))

    # ------------------------------------------------------------------ the three services
    def _on_send_goal(self, req: Any, _reply: Any) -> Any:
        goal_id = bytes(req.goal_id.uuid)
        stamp = msgs.stamp(self.svc.sim_ns)
        if goal_id in self.goals:  # rcl_action refuses a goal id it knows
            self.svc.warn(f"{self.name}: goal {goal_text(goal_id)} sent twice: rejected")
            return self._send_goal_response(accepted=False, stamp=stamp)
        g = self.goals[goal_id] = ServerGoal(goal_id, req.goal, stamp, STATUS_EXECUTING)
        if not self.on_goal(goal_id, req.goal):
            del self.goals[goal_id]
            return self._send_goal_response(accepted=False, stamp=stamp)
        if g.status not in TERMINAL:  # (ended at once: finish has published)
            self.publish_status()
        return self._send_goal_response(accepted=True, stamp=stamp)

    def _on_get_result(self, req: Any, reply: Callable[[Any], None]) -> Any:
        g = self.goals.get(bytes(req.goal_id.uuid))
        if g is None:
            return self._get_result_response(status=STATUS_UNKNOWN, result=self._result())
        if g.status in TERMINAL:
            return self._get_result_response(status=g.status, result=g.result)
        g.waiting.append(reply)  # answered by finish
        return None

    def _on_cancel(self, req: msgs.CancelGoalRequest, _reply: Any) -> msgs.CancelGoalResponse:
        """action_msgs/srv/CancelGoal: a zero goal id means every goal, a non-zero stamp adds every goal
        accepted at or before it; the goals in that set that are not over are offered to the owner."""
        goal_id = bytes(req.goal_info.goal_id.uuid)
        before = msgs.ns_of(req.goal_info.stamp)
        picked: list[ServerGoal] = []
        if goal_id == ZERO_ID and before == 0:
            picked = list(self.goals.values())
        else:
            if goal_id != ZERO_ID:
                if goal_id not in self.goals and before == 0:
                    return msgs.CancelGoalResponse(return_code=CANCEL_ERROR_UNKNOWN_GOAL_ID)
                if goal_id in self.goals:
                    picked.append(self.goals[goal_id])
            if before:
                picked += [g for g in self.goals.values() if g not in picked and msgs.ns_of(g.stamp) <= before]
        live = [g for g in picked if g.status not in TERMINAL]
        if picked and not live:
            return msgs.CancelGoalResponse(return_code=CANCEL_ERROR_GOAL_TERMINATED)
        canceling = []
        for g in live:
            if g.status != STATUS_CANCELING:
                was, g.status = g.status, STATUS_CANCELING
                if not self.on_cancel(g.goal_id):  # (the owner may also end it here: finish → canceled)
                    g.status = was
                    continue
            canceling.append(msgs.GoalInfo(goal_id=msgs.UUID(uuid=g.goal_id), stamp=g.stamp))
        if live and not canceling:
            return msgs.CancelGoalResponse(return_code=CANCEL_ERROR_REJECTED)
        if canceling:
            self.publish_status()
        return msgs.CancelGoalResponse(return_code=CANCEL_ERROR_NONE, goals_canceling=canceling)

    def _prune(self) -> None:
        ended = [gid for gid, g in self.goals.items() if g.status in TERMINAL and not g.waiting]
        for gid in ended[: max(0, len(ended) - KEEP_ENDED)]:
            del self.goals[gid]
