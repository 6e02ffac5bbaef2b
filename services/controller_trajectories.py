"""The joint controller's trajectories: which is taken, when it acts, and the planner's hand-over.

A part of :class:`hilsim.services.controller.ControllerService` (one of its bases, not a service of its own).
A trajectory arriving before the first measurement waits (the setpoint to start from is not known yet);
then each is taken or refused under ROS 2's joint_trajectory_controller's rules (:mod:`hilsim.sim.jtc`):
an empty one holds the measured position, a refusal is a rejected payload of its key, said in the log and
the health (``trajectories_refused``, ``last_refused``). The planner's own is taken even if it has ended.
The start stamps of the planner's last ``HANDOFF_KEPT`` trajectories are kept with why each was refused
(or None), for ``controller/has_trajectory``.

Reads ``<prefix>/<robot>/joint_trajectory`` and ``<prefix>/<robot>/planner/joint_trajectory``
(trajectory_msgs/JointTrajectory; the subscriptions are the service's setup). Serves
``controller/has_trajectory`` (builtin_interfaces/Time, a trajectory's start stamp → GoalResponse).
Writes nothing of its own: the reference it sets goes out with the control step.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np

from hilsim.core import msgs
from hilsim.core.keys import NOT_REACHED
from hilsim.core.service import Service
from hilsim.sim import control, jtc

PLANNER, JOINT_TRAJECTORY = "planner", "joint_trajectory"  # who sent a trajectory (health: command_from)
PLANNER_TRAJECTORY = "planner/joint_trajectory"  # the planner's own key (hilsim.core.keys)
HANDOFF_KEPT = 64  # the start stamps of the last trajectories taken, each with why it was rejected (or None)


class ControllerTrajectories(Service):
    """The controller's trajectories (:class:`hilsim.services.controller.ControllerService` sets these attributes)."""

    joints: control.JointTable
    names: list[str]
    pos: np.ndarray  # the latest measured positions (model order)
    rules: jtc.Rules
    timeline: jtc.Timeline | None  # the command over sim time (None until the first measurement)
    _early: list[tuple[msgs.JointTrajectory, str, str]]  # arrived before any measurement
    taken: control.TrajectorySampler | None  # the last trajectory take() took
    command_from: str
    refused: int
    last_refused: str
    max_tracking_error: float
    _taken: OrderedDict[int, str | None]  # the planner's trajectories taken: start stamp -> why rejected, or None
    _took: threading.Condition

    # ------------------------------------------------------------------ trajectories
    def on_trajectory(self, msg: msgs.JointTrajectory, key: str) -> None:
        """``joint_trajectory``: a person's, a tool's or a ROS 2 node's command (anyone the router lets write it)."""
        self._arrived(msg, key, JOINT_TRAJECTORY)

    def on_planner_trajectory(self, msg: msgs.JointTrajectory, key: str) -> None:
        """``planner/joint_trajectory``: the planner's own, a key only the planner's identity may write."""
        self._arrived(msg, key, PLANNER)

    def _arrived(self, msg: msgs.JointTrajectory, key: str, source: str) -> None:
        if self.timeline is None:
            # the setpoint to start from is not known yet: taken, in order, before the first step
            self._early.append((msg, key, source))
            why = None
        else:
            refused = self.take(msg, key, source)
            why = refused[1] if refused is not None else None
        if source == PLANNER:  # controller/has_trajectory answers the planner about its own
            self._taken[msgs.ns_of(msg.header.stamp)] = why
            while len(self._taken) > HANDOFF_KEPT:
                self._taken.popitem(last=False)
            self._took.notify_all()

    def on_has_trajectory(self, start: msgs.Time) -> msgs.GoalResponse:
        """``controller/has_trajectory`` (see the module docstring); runs under self.lock, which the wait
        gives up, so the trajectory's own subscriber thread can take it meanwhile."""
        ns = msgs.ns_of(start)
        # well within physics' patience, so a trajectory lost on the way is a warning, not a stalled run
        wait = self.sc.clock.ack_timeout / 3
        end = time.monotonic() + wait
        while ns not in self._taken and not self.stop_event.is_set() and (left := end - time.monotonic()) > 0:
            self._took.wait(min(left, 0.2))
        if ns not in self._taken:
            return msgs.GoalResponse(accepted=False, reason=f"{NOT_REACHED} starting at {ns * 1e-9:.3f} s "
                                     f"reached the controller within {wait:g} s")
        why = self._taken[ns]
        return msgs.GoalResponse(accepted=why is None, reason=why or "")

    def take(self, msg: msgs.JointTrajectory, key: str, source: str) -> tuple[str, str] | None:
        """Follow ``msg`` (from ``source``) under the rules of :mod:`hilsim.sim.jtc`; None, or (what, why)
        it is refused (a rejected payload of ``key``, said in the log and the health). The planner's own
        is taken even if it has ended: only it may write its key, and it hands a restarted controller
        the trajectory under way again (whose end is then held)."""
        assert self.timeline is not None
        self.taken = None
        refused = jtc.refusal(msg, self.sim_ns, self.names, self.rules, ended_ok=source == PLANNER)
        if refused is None and not msg.points:
            # ROS convention: an empty trajectory stops the motion where the arm is now.
            self.stop_here()
            self.command_from = source
            return None
        if refused is None:
            start = msgs.ns_of(msg.header.stamp) or self.sim_ns
            # from where the command will be when the new one starts (joints it does not name keep it)
            base = self.timeline.reference_at(start)
            try:
                t = control.TrajectorySampler(msg, self.names, start, base, self.joints.lower, self.joints.upper)
            except control.TrajectoryError as e:
                refused = jtc.JOINTS if "joint" in str(e) else "invalid", str(e)
            else:
                self.timeline.replace(jtc.Segment(t, source))
                self.taken = t
                self.max_tracking_error = 0.0
                return None
        self.refused += 1
        self.last_refused = f"{source}: {refused[1]}"
        self.reject(key, refused[1])
        return refused

    def stop_here(self) -> None:
        """Hold the measured position: nothing followed or pending."""
        assert self.timeline is not None
        self.timeline.stop(self.pos.copy())
