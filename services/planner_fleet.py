"""The planners' fleet feed (``fleet.arrays``): every robot's planner fed from one joint-state sample.

Run in place of each robot's own subscription when robots are arrays (:mod:`hilsim.core.fleet`; the
planner's ``array_driver``). Reads ``<prefix>/<robot>/fleet/joint_states_throttle``; writes no key of its own.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Protocol

from hilsim.core import msgs
from hilsim.core.config import Scenario
from hilsim.core.service import Service


class FedPlanner(Protocol):
    """What the feed uses of a robot's :class:`hilsim.services.planner.PlannerService`."""

    n: int
    lock: Any
    stop_event: threading.Event
    counts_in: Counter[str]

    def on_joint_states(self, js: msgs.JointState, _key: str) -> None: ...

    def fail(self, text: str, exc: BaseException | None = None) -> None: ...


class FleetPlannerFeed(Service):
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): every robot's planner fed from one sample.

    Reads ``<prefix>/<robot>/fleet/joint_states_throttle`` (every robot's encoders of the planners'
    decision steps, joints ``arm<k>/<joint>``) and
    hands each robot's :class:`PlannerService` its slice, the very JointState (names, values, stamp) the
    robot's own ``joint_states`` carries, in robot order; writes nothing of its own. The planners keep
    everything else, their lockstep role included (each acknowledges its ticks on its own ``sync/planner``):
    one sample to decode per step instead of one per robot.
    """

    name = "planner"
    stop_rank = 11  # started before the planners it feeds, stopped after them
    acks_for_robots = False

    def __init__(self, scenario: Scenario, members: list[FedPlanner]) -> None:
        super().__init__(scenario)
        self.members = members
        self.n = members[0].n
        self.names: list[str] | None = None
        self.robot_joints: list[list[str]] = []

    def setup(self) -> None:
        self.subscribe(self.keys.fleet("joint_states_throttle"), msgs.JointState, self.on_joint_states)

    def on_joint_states(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        self.sim_ns = stamp
        n, k_n = self.n, len(self.members)
        if self.names is None:
            self.names = list(msg.name)
            self.robot_joints = [[j.split("/", 1)[-1] for j in self.names[k * n:(k + 1) * n]] for k in range(k_n)]
        if list(msg.name) != self.names or len(msg.name) != n * k_n or len(msg.position) != len(msg.name):
            self.reject(key, f"fleet JointState of {len(msg.name)} joints is not {k_n} robots of {n} joints")
            return
        for k, m in enumerate(self.members):
            c = slice(k * n, (k + 1) * n)
            js = msgs.JointState(header=msg.header, name=self.robot_joints[k], position=msg.position[c],
                                 velocity=msg.velocity[c] if msg.velocity else [],
                                 effort=msg.effort[c] if msg.effort else [])
            with m.lock:
                if m.stop_event.is_set():
                    continue
                try:
                    m.on_joint_states(js, key)
                except Exception as e:  # its decision ticks, as its own subscription is: fatal to it
                    m.fail(f"error handling {key}: {type(e).__name__}: {e}", exc=e)
                    continue
            m.counts_in[key] += 1

    def health_values(self) -> dict[str, Any]:
        return {"robots": len(self.members), "arrays": "yes"}
