"""The planner's hand-over of a trajectory to the controller, and its resending.

A part of :class:`hilsim.services.planner.PlannerService` (one of its bases, not a service of its own).
Once a trajectory is out, the planner asks the controller whether it holds it
(``controller/has_trajectory``; the controller's docstring says why): lockstep, the tick is acknowledged
only then; realtime, one that never reached it is sent again, up to ``HANDOVER_TRIES`` times in all. A
controller that (re)appears (its liveliness token) knows no trajectory: the one being executed is sent
again, at once and after ``clock.start_delay``.

Reads ``<prefix>/<robot>/alive/controller`` (liveliness); asks ``controller/has_trajectory`` (a query:
the trajectory's start stamp → GoalResponse); writes ``planner/joint_trajectory`` (sent again).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import zenoh

from hilsim.core import msgs
from hilsim.core.keys import NOT_REACHED
from hilsim.services.planner_goals import Goal, PlannerGoals

# realtime: a trajectory that did not reach the controller is sent this many times in all
HANDOVER_TRIES = 3


class PlannerHandover(PlannerGoals):
    """The planner's trajectories handed over to the controller."""

    handovers: int  # trajectories the controller confirmed it holds
    resent: int  # realtime: trajectories sent again, the controller not holding them
    handover_wait_max: float  # [s of wall time] the longest wait for that
    _controller_seen: bool

    # ------------------------------------------------------------------ the controller
    def _on_controller(self, sample: Any) -> None:
        """A controller (re)appeared: a restarted one knows no trajectory, so the one being
        executed is sent again (its start stamp unchanged: it picks up where the arm should be),
        at once and after ``clock.start_delay``: a sample sent before the peers' own links to the
        new process exist can be lost (see physics' start of the run)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        with self.lock:
            first, self._controller_seen = not self._controller_seen, True
        if first:
            return  # the run's own controller, before any goal: nothing to send again (nor any timer)
        self._resend_trajectory()
        t = threading.Timer(self.sc.clock.start_delay, self._resend_trajectory)
        t.daemon = True
        t.start()

    def _resend_trajectory(self) -> None:
        with self.lock:
            if self.stop_event.is_set():
                return
            goal = self.active
            if goal is not None and goal.state in ("executing", "settling") and goal.traj_msg.points:
                self.log.info("a controller appeared: %s's trajectory sent again", goal.goal_id)
                self.pub_traj.put(goal.traj_msg)

    # ------------------------------------------------------------------ hand-over
    def _handed_over(self, goal: Goal, start_ns: int) -> None:
        """Wait until the controller holds the trajectory starting at ``start_ns`` (its
        ``controller/has_trajectory``). Lockstep: the tick is acknowledged only then. Zenoh keeps no
        order between keys: a trajectory the controller took after the joint states of its start step
        would act later than in another run of the seed. Realtime: one that never reached it (lost on
        the way) is sent again, up to ``HANDOVER_TRIES`` times in all, or the arm would not move for the
        rest of the goal's time. No answer (no controller yet, or a control law without the query):
        nothing to wait for; no answer in time: a warning (lockstep: and the tick is acknowledged)."""
        if not self._controller_seen:
            return
        session = self.zenoh_session
        if session is None:
            return  # an in-process bus (benchmarks): delivery is in publication order
        tries = 1 if self.lockstep else HANDOVER_TRIES
        for attempt in range(1, tries + 1):
            got = self._ask_controller(session, start_ns)
            if got is None or got.accepted:
                return  # no controller answers this query, or it holds the trajectory
            with self.lock:
                again = (attempt < tries and got.reason.startswith(NOT_REACHED) and self.active is goal
                         and goal.state in ("executing", "settling"))
                # lockstep: this run may not repeat bit for bit; a refusal: the controller says why too
                self.warn(f"{goal.goal_id}: the controller does not hold the trajectory: {got.reason}"
                          + ("; sent again" if again else ""))
                if not again:
                    return
                self.resent += 1
                self.pub_traj.put(goal.traj_msg)

    def _ask_controller(self, session: zenoh.Session, start_ns: int) -> msgs.GoalResponse | None:
        """The controller's ``controller/has_trajectory`` answer for ``start_ns``; None if none came."""
        w0 = time.perf_counter()
        key, ask = self.keys.topic("controller/has_trajectory"), msgs.encode(msgs.stamp(start_ns))
        got: msgs.GoalResponse | None = None
        # Half of physics' patience (the controller's own wait is a third): a controller that stopped
        # answering (SIGSTOP, hung) is then named silent by physics, not this planner waiting for it
        for reply in session.get(key, payload=ask, timeout=self.sc.clock.ack_timeout / 2):
            try:
                got = (msgs.decode(msgs.GoalResponse, reply.ok.payload.to_bytes()) if reply.ok is not None
                       else msgs.GoalResponse(reason=reply.err.payload.to_string()))
            except msgs.BadMessage as e:
                got = msgs.GoalResponse(reason=f"bad answer: {e}")
            with self.lock:
                self.handover_wait_max = max(self.handover_wait_max, time.perf_counter() - w0)
                self.handovers += got.accepted
        return got
