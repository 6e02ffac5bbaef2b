"""Action client of the planner (like MoveIt's move_group action), and ``hilsim goal``.

Usage::

    client = MoveClient(session, Keys(prefix, robot))
    resp = client.send(msgs.MoveGoal(goal_id="g1", joint_positions=[...]))   # accepted / rejected + reason
    result = client.wait("g1", timeout=60, on_feedback=print)                # MoveResult or None
    client.cancel("g1")                                                      # stop smoothly
    client.close()

Goals go to the queryable ``planner/goal`` (MoveGoal → GoalResponse), cancels to
``planner/cancel``; feedback (``planner/feedback``) and results (``planner/result``) are
subscribed from construction on, so nothing published after ``send`` is missed. A mobile robot's
goals go to its navigator the same way: ``MoveClient(session, keys, service="navigator")`` uses
``navigator/goal``, ``navigator/cancel``, ``navigator/feedback`` and ``navigator/result``.
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import zenoh

from hilsim.core import msgs, run_finder, transport
from hilsim.core.keys import Keys


class MoveClient:
    def __init__(self, session: zenoh.Session, keys: Keys, *, query_timeout: float = 30.0,
                 service: str = "planner") -> None:
        self.session = session
        self.keys = keys
        self.service = service  # who serves the action: the planner (arm) or the navigator (rover)
        self.query_timeout = query_timeout
        self._lock = threading.Lock()
        self._results: dict[str, msgs.MoveResult] = {}
        self._feedback: defaultdict[str, queue.Queue[msgs.MoveFeedback]] = defaultdict(queue.Queue)
        self._cond = threading.Condition(self._lock)
        self._planner_seen = False
        self._subs = [
            session.declare_subscriber(keys.topic(f"{service}/feedback"), self._on_feedback),
            session.declare_subscriber(keys.topic(f"{service}/result"), self._on_result),
        ]

    def _on_feedback(self, s: zenoh.Sample) -> None:
        try:
            fb = msgs.decode(msgs.MoveFeedback, s.payload.to_bytes())
        except msgs.BadMessage:
            return
        with self._lock:
            self._feedback[fb.goal_id].put(fb)
            self._cond.notify_all()

    def _on_result(self, s: zenoh.Sample) -> None:
        try:
            r = msgs.decode(msgs.MoveResult, s.payload.to_bytes())
        except msgs.BadMessage:
            return
        with self._lock:
            self._results[r.goal_id] = r
            self._cond.notify_all()

    def wait_for_planner(self, timeout: float) -> bool:
        """Wait until the planner's liveliness token is seen. A session that has just opened
        does not yet know the planner's queryable: a query sent then reaches nobody. The token
        is declared after the queryable, so seeing it means the query will be routed."""
        return transport.wait_for_service(self.session, self.keys, self.service, timeout)

    def _query(self, topic: str, payload: bytes, goal_id: str) -> msgs.GoalResponse:
        if not self._planner_seen:
            self._planner_seen = self.wait_for_planner(min(self.query_timeout, 10.0))
        replies = self.session.get(self.keys.topic(topic), payload=payload, timeout=self.query_timeout)
        for reply in replies:
            if reply.ok is not None:
                return msgs.decode(msgs.GoalResponse, reply.ok.payload.to_bytes())
            return msgs.GoalResponse(goal_id=goal_id, accepted=False, reason=reply.err.payload.to_string())
        return msgs.GoalResponse(goal_id=goal_id, accepted=False,
                                 reason=f"no {self.service} answered (is it running?)")

    def send(self, goal: msgs.MoveGoal) -> msgs.GoalResponse:
        return self.send_raw(msgs.encode(goal), goal.goal_id)

    def send_raw(self, payload: bytes, goal_id: str = "") -> msgs.GoalResponse:
        """Send a goal payload as it is (tests use it for malformed goals)."""
        return self._query(f"{self.service}/goal", payload, goal_id)

    def cancel(self, goal_id: str) -> msgs.GoalResponse:
        return self._query(f"{self.service}/cancel", msgs.encode(msgs.CancelRequest(goal_id=goal_id)), goal_id)

    def result(self, goal_id: str) -> msgs.MoveResult | None:
        with self._lock:
            return self._results.get(goal_id)

    def wait(
        self,
        goal_id: str,
        timeout: float,
        on_feedback: Callable[[msgs.MoveFeedback], Any] | None = None,
    ) -> msgs.MoveResult | None:
        """Block until the result of ``goal_id`` arrives (None after ``timeout`` s), passing feedback on."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                fq = self._feedback[goal_id]
                while on_feedback is not None and not fq.empty():
                    on_feedback(fq.get_nowait())
                if goal_id in self._results:
                    return self._results[goal_id]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(min(left, 0.1))

    def wait_for_state(self, goal_id: str, state: str, timeout: float) -> bool:
        """Block until feedback of ``goal_id`` reports ``state`` (e.g. ``executing``); False on
        timeout or if the goal ended first. Feedback seen here is not passed to :meth:`wait`."""
        deadline = time.monotonic() + timeout
        with self._lock:
            fq = self._feedback[goal_id]
            while True:
                while not fq.empty():
                    if fq.get_nowait().state == state:
                        return True
                if goal_id in self._results:
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.1))

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def goal_from_args(args: argparse.Namespace) -> msgs.MoveGoal:
    gid = f"cli-{int(time.time() * 1000) % 10_000_000}"
    if getattr(args, "xy", None) is not None:  # a mobile robot: x, y in the world, optional yaw
        yaw = getattr(args, "yaw", None)
        pose = msgs.Pose(position=msgs.Point(x=args.xy[0], y=args.xy[1]))
        if yaw is not None:
            pose.orientation = msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))
        return msgs.MoveGoal(goal_id=gid, target_kind="pose", pose=pose, use_orientation=yaw is not None)
    if getattr(args, "yaw", None) is not None:
        raise ValueError("--yaw goes with --xy")
    if args.joints is not None:
        return msgs.MoveGoal(goal_id=gid, target_kind="joints", joint_positions=list(args.joints), planner=args.planner)
    p = list(args.pose)
    if len(p) not in (3, 6):
        raise ValueError("--pose takes x y z or x y z roll pitch yaw")
    pose = msgs.Pose(position=msgs.Point(x=p[0], y=p[1], z=p[2]))
    if len(p) == 6:
        r, pi, y = (v / 2 for v in p[3:])
        cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(pi), math.sin(pi), math.cos(y), math.sin(y)
        pose.orientation = msgs.Quaternion(
            w=cr * cp * cy + sr * sp * sy,
            x=sr * cp * cy - cr * sp * sy,
            y=cr * sp * cy + sr * cp * sy,
            z=cr * cp * sy - sr * sp * cy,
        )
    return msgs.MoveGoal(goal_id=gid, target_kind="pose", pose=pose, use_orientation=len(p) == 6, planner=args.planner)


def cmd_goal(args: argparse.Namespace) -> int:
    """``hilsim goal ROBOT --joints … | --pose x y z [r p y]``: send, print feedback, print the result."""
    try:
        goal = goal_from_args(args)
    except ValueError as e:
        print(f"hilsim goal: {e}", file=sys.stderr)
        return 2
    keys = run_finder.tool_keys(args.robot, args.prefix)
    target = run_finder.tool_target(args.connect, getattr(args, "run", None), "hilsim goal")
    joints = run_finder.run_joints(target.run) if target.run is not None and args.joints is not None else []
    if joints and len(args.joints) != len(joints):  # the run is known: the mistake is said before connecting
        print(f"hilsim goal: --joints: {len(args.joints)} values, but {args.robot} has {len(joints)} joints "
              f"({', '.join(joints)})", file=sys.stderr)
        return 2
    try:
        session = run_finder.open_tool_session(args.connect, run=target.run.run_dir if target.run else None,
                                         tool="hilsim goal")
    except ConnectionError as e:
        print(f"hilsim goal: {e}", file=sys.stderr)
        return 2
    rover = getattr(args, "xy", None) is not None
    client = MoveClient(session, keys, service="navigator" if rover else "planner")
    try:
        resp = client.send(goal)
        if not resp.accepted:
            print(f"rejected: {resp.reason}")
            return 1
        print(f"accepted: goal {resp.goal_id}")

        shown: set[str] = set()

        def show(fb: msgs.MoveFeedback) -> None:
            print(f"  [{msgs.seconds(fb.header.stamp):8.3f} s] {fb.state:<10} {100 * fb.progress:5.1f} %", flush=True)
            if fb.choice and fb.choice not in shown:  # planner: auto said what it picked and why
                shown.add(fb.choice)
                print(f"  choice: {fb.choice}", flush=True)

        try:
            res = client.wait(resp.goal_id, args.timeout, on_feedback=show)
        except KeyboardInterrupt:
            c = client.cancel(resp.goal_id)
            print(f"cancel: {c.reason}")
            res = client.wait(resp.goal_id, 5.0)
        if res is None:
            print(f"no result within {args.timeout:g} s")
            return 1
        err = ", ".join(f"{e:.4f}" for e in res.execution_error)
        # a failure names its code (MoveIt-like, hilsim.core.msgs.action); success is code 1, said by the word
        how = "succeeded" if res.success else f"failed (code {res.error_code})"
        if rover:
            pos, yaw_err = (*res.execution_error, float("nan"), float("nan"))[:2]
            print(f"{how}: {res.message}; planner {res.planner}, planning {res.planning_time:.3f} s, "
                  f"position error {pos:.3f} m, yaw error {yaw_err:.3f} rad (odometry)")
            return 0 if res.success else 1
        print(
            f"{how}: {res.message}; "
            f"planner {res.planner}, "
            f"planning {res.planning_time:.3f} s, {len(res.trajectory.points)} trajectory points, "
            f"joint error [{err}] rad" + (f"\nchoice: {res.choice}" if res.choice else "")
        )
        return 0 if res.success else 1
    finally:
        client.close()
        session.close()
