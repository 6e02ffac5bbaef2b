"""Commanding the shown robot: goals and cancels to its planner or navigator (through
:class:`hilsim.planning.client.MoveClient`), and the controller's gains (:mod:`hilsim.tools.inspection.params`),
each checked first against the scenario in force (:class:`hilsim.ui.options.ScenarioOption`).

Queries (``<prefix>/<robot>/…``): ``planner/goal``, ``planner/cancel``, ``navigator/goal``,
``navigator/cancel``, ``controller/set_parameters``. A goal sent is noted in the watcher
(:mod:`hilsim.ui.watch`), which follows it on ``planner|navigator/feedback`` and ``…/result``; the
gains in force are read back there from the controller's health (``gains:<joint>``).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import time
from collections.abc import Callable
from typing import Any

import zenoh

from hilsim.core import msgs, run_finder
from hilsim.sim.control import GAIN_FIELDS, check_gain
from hilsim.ui.jsonio import BadInput, number
from hilsim.ui.options import ScenarioOption
from hilsim.ui.watch import Monitor


class Commands:
    """Goals, cancels and gains for the robot the panel shows (``POST /api/goal``, ``/api/cancel``,
    ``/api/gains``); each blocks until the service answers its query."""

    def __init__(self, session: zenoh.Session, prefix: str, monitor: Monitor, planners: list[str],
                 robot: Callable[[], str], option: Callable[[], ScenarioOption | None]) -> None:
        self.session = session
        self.prefix = prefix
        self.monitor = monitor
        self.planners = planners
        self.robot = robot  # the robot shown (hilsim.ui.panel.Panel.robot)
        self.option = option  # what goals and gains are checked against (hilsim.ui.panel.Panel.option)
        self.clients: dict[tuple[str, str], Any] = {}
        self.goal_seq = 0

    def _client(self, service: str) -> Any:
        from hilsim.planning.client import MoveClient

        key = (self.robot(), service)
        if key not in self.clients:
            keys = run_finder.tool_keys(self.robot(), self.prefix)
            self.clients[key] = MoveClient(self.session, keys, query_timeout=15.0, service=service)
        return self.clients[key]

    def _live_option(self, fld: str) -> ScenarioOption:
        opt = self.option()
        if opt is None:
            raise BadInput(fld, "no run is running: start one first", 409)
        return opt

    def goal(self, body: dict[str, Any]) -> dict[str, Any]:
        """Validate and send a goal (blocking: the planner answers the query)."""
        opt = self._live_option("goal")
        kind = body.get("kind")
        planner = body.get("planner") or ""
        if not isinstance(planner, str) or (planner and planner not in self.planners):
            raise BadInput("goal-planner", f"unknown planner {str(planner)[:40]!r}; one of: {', '.join(self.planners)}")
        self.goal_seq += 1
        gid = f"ui-{int(time.time()) % 100000}-{self.goal_seq}"
        if kind == "joints":
            if opt.mobile:
                raise BadInput("goal", f"scenario {opt.name} takes map goals (x, y), not joint targets")
            pos = body.get("positions")
            if not isinstance(pos, list) or len(pos) != len(opt.joints):
                raise BadInput("goal", f"positions: expected {len(opt.joints)} numbers ({', '.join(opt.joints)})")
            q = []
            for i, (name, lo, hi) in enumerate(zip(opt.joints, opt.lower, opt.upper, strict=True)):
                v = number({name: pos[i]}, name, f"joint-{name}")
                assert v is not None
                if not lo <= v <= hi:
                    raise BadInput(f"joint-{name}", f"{name}: {v:g} rad is outside its limits [{lo:.3f}, {hi:.3f}]")
                q.append(v)
            goal = msgs.MoveGoal(goal_id=gid, target_kind="joints", joint_names=list(opt.joints),
                                 joint_positions=q, planner=planner)
            service = "planner"
        elif kind == "pose":
            if opt.mobile:
                raise BadInput("goal", f"scenario {opt.name} takes map goals (x, y), not a tool pose")
            x, y, z = (number(body, n, f"pose-{n}") for n in ("x", "y", "z"))
            rpy = [number(body, n, f"pose-{n}", required=False) for n in ("roll", "pitch", "yaw")]
            given = [v is not None for v in rpy]
            if any(given) and not all(given):
                raise BadInput("pose-roll", "orientation: give roll, pitch and yaw, or none of them")
            from hilsim.planning.client import goal_from_args

            ns = argparse.Namespace(xy=None, yaw=None, joints=None, planner=planner,
                                    pose=[x, y, z, *(rpy if all(given) else [])])
            goal = goal_from_args(ns)
            goal.goal_id = gid
            service = "planner"
        elif kind == "xy":
            if not opt.mobile:
                raise BadInput("goal", f"scenario {opt.name} takes joint or pose goals, not a map point")
            x, y = number(body, "x", "xy-x"), number(body, "y", "xy-y")
            yaw = number(body, "yaw", "xy-yaw", required=False)
            pose = msgs.Pose(position=msgs.Point(x=x, y=y))
            if yaw is not None:
                pose.orientation = msgs.Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))
            goal = msgs.MoveGoal(goal_id=gid, target_kind="pose", pose=pose, use_orientation=yaw is not None)
            service = "navigator"
        else:
            raise BadInput("goal", f"kind: expected joints, pose or xy, got {str(kind)[:40]!r}")
        self.monitor.note_goal(self.robot(), gid, service)
        resp = self._client(service).send(goal)
        if not resp.accepted:
            with self.monitor.lock:
                g = self.monitor.robot(self.robot()).goals.get(gid)
                if g is not None:
                    g.update(state="rejected", done=True, success=False, message=resp.reason)
            raise BadInput("goal", f"rejected by the {service}: {resp.reason}", 422)
        return {"goal_id": gid, "accepted": True}

    def cancel(self, body: dict[str, Any]) -> dict[str, Any]:
        gid = body.get("goal_id")
        if not isinstance(gid, str) or not gid:
            raise BadInput("cancel", "goal_id: a goal id is required")
        self._live_option("cancel")
        with self.monitor.lock:
            g = self.monitor.robot(self.robot()).goals.get(gid)
        if g is None:
            raise BadInput("cancel", f"no goal {gid[:40]!r} known to the panel", 404)
        resp = self._client(str(g["service"])).cancel(gid)
        if not resp.accepted:
            raise BadInput("cancel", f"not cancelled: {resp.reason}", 422)
        return {"goal_id": gid, "cancelled": True, "reason": resp.reason}

    def gains(self, body: dict[str, Any]) -> dict[str, Any]:
        from hilsim.tools.inspection.params import set_parameters

        joint = body.get("joint")
        if not isinstance(joint, str):
            raise BadInput("gains", f"joint: expected a joint's name, got {str(joint)[:40]!r}")
        # the values first, by the controller's own rule: a bad one is refused with or without a run
        values: dict[str, float] = {}
        shown = joint[:40]  # not yet known to be a joint: said shortly
        for f in GAIN_FIELDS:
            v = number(body, f, f"gain-{shown}-{f}", required=False)
            if v is not None:
                why = check_gain(f"{shown}.{f}", f, v)
                if why is not None:
                    raise BadInput(f"gain-{shown}-{f}", why)
                values[f"{joint}.{f}"] = v
        unknown = [k for k in body if k not in (*GAIN_FIELDS, "joint")]
        if unknown:
            raise BadInput("gains", f"unknown field(s) {', '.join(map(str, unknown))[:80]}; gains are "
                           f"{', '.join(GAIN_FIELDS)}")
        if not values:
            raise BadInput("gains", "no gain given")
        opt = self._live_option("gains")
        if joint not in opt.joints:
            raise BadInput("gains", f"joint: expected one of {', '.join(opt.joints) or 'the joints'}, got "
                           f"{shown!r}")
        res = set_parameters(self.session, run_finder.tool_keys(self.robot(), self.prefix), values, timeout=10.0)
        if not res.successful:
            raise BadInput("gains", f"not set: {res.reason}", 422)
        return {"set": values, "reason": res.reason}

    def close(self) -> None:
        for c in self.clients.values():
            with contextlib.suppress(Exception):
                c.close()
