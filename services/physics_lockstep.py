"""Physics' lockstep barrier: who takes part, who acknowledged which step, when the next step may come.

A part of :class:`hilsim.services.physics.PhysicsService` (one of its bases, not a service of its own).
Step k+1 happens only once every participant acknowledged step k (see docs/keys.md). Participants
announce themselves (``lockstep/<service>/<period>/<lag>/<via>/<gid>``, fixed at step 0), so physics needs
no list of them; an acknowledgement counts only when written by the participant that announced it. The
step is taken in the thread that delivers the last acknowledgement. A participant silent for
``clock.ack_timeout`` is named for ``hilsim up`` to restart (restart policy on-failure) or ends the run
("stalled"); sim time paused for services that left goes on once they are back.

Reads ``<prefix>/<robot>/lockstep/**`` (liveliness: the participants), ``<prefix>/<robot>/sync/<service>``
(rosgraph_msgs/Clock, acknowledgements; a ``joint_commands`` sample acknowledges through
:mod:`hilsim.services.physics_commands`) and ``<prefix>/<robot>/task/result`` (hilsim_msgs/MoveResult:
with a task, sim time stops ``TASK_END_MARGIN_NS`` after every robot's result). Writes nothing of its own:
the steps it lets go are published by :mod:`hilsim.services.physics_truth`; its figures (``waiting_for``,
``silent``, ``paused_for``, ``pauses``) are in physics' health.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import zenoh

from hilsim.core import fleet, msgs
from hilsim.core.transport import Attachment
from hilsim.services.physics_truth import PhysicsTruth

# lockstep: sim time stops this long after the task's result stamp (every robot's), so that a run ends on a
# step set by the task, not by when hilsim up stopped it; longer than physics can run past that stamp before
# the result reaches it: the result host's decision period and lockstep lag (20 steps of the arm), and the
# planner's worker thread, which publishes it on its own (a loaded CI runner's was heard 0.175 s after its
# stamp with a margin of 0.1 s, and that run ended 75 ms later than its twin)
TASK_END_MARGIN_NS = 500_000_000


class Participant:
    """A lockstep participant as it announced itself."""

    __slots__ = ("gid", "lag", "period", "via")

    def __init__(self, period: int, lag: int, via: str, gid: str) -> None:
        self.period, self.lag, self.via, self.gid = period, lag, via, gid


class PhysicsLockstep(PhysicsTruth):
    """Physics' lockstep barrier (:class:`hilsim.services.physics.PhysicsService` sets these attributes)."""

    participants: dict[str, Participant]  # from lockstep tokens, fixed at step 0
    announced: dict[str, Participant]
    acked: dict[str, int]  # [ns] the latest step each participant acknowledged
    present: set[str]
    gone: dict[str, int]  # services of the scenario that left during the run, and when
    back_at: float
    started: bool
    done: bool
    end_ns: int | None
    ended_by: str
    task_ends: dict[str, int]
    task_results: deque[tuple[str, int]]
    last_progress: float
    waiting_reported: bool
    silent: list[str]
    _advance: Callable[[], None]  # one step (PhysicsService)
    publish_health_async: Callable[[], None]

    # ------------------------------------------------------------------ participants and acknowledgements
    def _on_lockstep(self, sample: zenoh.Sample) -> None:
        # <prefix>/<robot>/lockstep/<service>/<period>/<lag>/<via>/<gid>
        key = str(sample.key_expr)
        period, lag, via, gid = key.split("/")[-4:]
        svc = fleet.service_id(self.sc, key, "lockstep")
        with self.lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self.announced.pop(svc, None)
                return
            if (via not in ("sync", "joint_commands") or not period.isdigit() or int(period) < 1
                    or not lag.isdigit()):
                self.fault(f"lockstep token of {svc} not understood: period {period!r}, lag {lag!r}, via {via!r}")
                return
            p = Participant(int(period), int(lag), via, gid)
            self.announced[svc] = p
            if svc in self.participants:  # a participant that came back (e.g. restarted): new writer id
                self.participants[svc] = p

    def _on_sync(self, clk: msgs.Clock, key: str, att: Attachment | None) -> None:
        name = fleet.service_id(self.sc, key, "sync")
        p = self.participants.get(name)
        if p is None or p.via != "sync":
            return
        if att is None or att.gid.hex() != p.gid:
            self.reject(key, f"acknowledgement not from the {name} that announced itself")
            return
        self._ack(name, msgs.ns_of(clk.clock))

    def _ack(self, who: str, ns: int) -> None:
        if who not in self.acked:
            return
        self.acked[who] = max(self.acked[who], ns)
        if self.started and not self.done and not self.gone and self._all_acked():
            self._advance_lockstep()

    def _advance_lockstep(self) -> None:
        """Step, then keep stepping through the steps at which no participant is due (e.g. a
        100 Hz controller over 500 Hz physics acknowledges every 5th step only)."""
        self._advance()
        while not self.done and self._all_acked():
            self._advance()

    def _all_acked(self) -> bool:
        return not self._missing()

    def _missing(self) -> list[str]:
        """Participants that still owe an acknowledgement physics must have before stepping on:
        for step k - lag, where that step is one of theirs (the controller answers at control
        steps, the planner at its decision ticks, and is waited for ``lag`` steps later)."""
        t, k, dt = self.world.time_ns, self.world.step_index, self.sc.dt_ns
        missing = []
        for name, ns in self.acked.items():
            p = self.participants[name]
            due = k - p.lag
            if due >= 0 and due % p.period == 0 and ns < t - p.lag * dt:
                missing.append(name)
        return missing

    def fix_participants(self) -> None:
        """Before step 0: the lockstep participants are those that announced themselves by now."""
        with self.lock:
            self.participants = dict(self.announced) if self.sc.clock.mode == "lockstep" else {}
            self.acked = {p: -1 for p in self.participants}
        if self.participants:
            self.log.info("lockstep participants: %s", ", ".join(
                f"{n} (every {p.period} steps, via {p.via}" + (f", waited for {p.lag} steps later)" if p.lag else ")")
                for n, p in self.participants.items()))

    def _on_task_result(self, msg: msgs.MoveResult, key: str) -> None:
        """Lockstep: a robot's task ended (Zenoh's thread, without the lock): handed to the stepping, which
        takes it before its next step. Waiting here for the lock that the acknowledgements' handler holds
        while it steps, a result once reached physics 200 steps late, past the end it sets."""
        self.task_results.append((key, msgs.ns_of(msg.header.stamp)))

    def _take_task_results(self) -> None:
        """Under the lock, before a step: once every robot's task ended, sim time stops ``TASK_END_MARGIN_NS``
        after the latest result's stamp, on that step in every run with the same seed."""
        while self.task_results:
            key, stamp = self.task_results.popleft()
            self.task_ends[key] = stamp
        if len(self.task_ends) < len(self.robots) or self.done:
            return
        dt = self.sc.dt_ns
        end = -(-(max(self.task_ends.values()) + TASK_END_MARGIN_NS) // dt) * dt  # on a step
        if self.end_ns is not None and self.end_ns <= end:
            return  # the duration comes first
        now = self.world.time_ns
        self.end_ns, self.ended_by = end, "the task"
        if now > end:  # the result came later than the margin allows: this end depends on the machine
            self.warn(f"the task's result (t={max(self.task_ends.values()) / 1e9:.3f} s) reached physics at "
                      f"t={now / 1e9:.3f} s, past the end it sets (t={end / 1e9:.3f} s): this run's end is "
                      "not the same as another's with the same seed")
        else:
            self.log.info("the task ended: sim time stops at t=%.3f s", end / 1e9)

    def _report_silent(self, stalled: float) -> None:
        """Lockstep, no step for ``clock.ack_timeout`` (under self.lock): the participants that owe an
        acknowledgement, and the services that left and are not back (a process stopped or hung: its
        session's lease ran out, yet it never exited), are silent. Those ``hilsim up`` restarts
        (restart policy on-failure) are named in health (``silent``): it kills such a process, which
        cannot restart itself, and starts it again, while sim time waits. Any other is a fault, and
        "stalled" in health ends the run instead of waiting forever."""
        silent = sorted({*self._missing(), *(s for s in self.gone if s not in self.present)})
        if not silent:
            return
        t = self.world.time_ns / 1e9
        restartable = [s for s in silent if self.sc.restart.policy(self._unit(s)) == "on-failure"]
        if restartable == silent:
            self.silent = silent
            self.warn(f"{', '.join(silent)} silent for {stalled:.1f} s at step t={t:.3f}s (no lockstep "
                      f"acknowledgement, or gone and not back): restart policy on-failure, hilsim up restarts it")
        else:
            # "stalled" in health: hilsim up ends the run on it instead of waiting forever
            self.state = "stalled"
            gone = [s for s in silent if s in self.gone]
            why = f"; {', '.join(gone)} left at t={t:.3f}s and did not come back" if gone else ""
            self.fault(f"no lockstep acknowledgement from {', '.join(silent)} for step t={t:.3f}s "
                       f"after {stalled:.1f}s{why}")
        self.publish_health_async()

    def _unit(self, svc: str) -> str:
        """The process (launch unit) a service runs in: itself, or a composed ``a+b`` (hilsim.launch.compose)."""
        base = svc.split("@")[0]
        return next((u for u in self.sc.launch_units() if base in u.split("@")[0].split("+")), svc)

    def _resume_when_back(self) -> None:
        """Lockstep, paused (under self.lock): once every service that left is back, and its peers
        had ``clock.start_delay`` to learn of its subscriptions (as before step 0), go on from the
        step where sim time stopped. A step some participant still owes is published again: a
        restarted process never saw it, and without it nobody would acknowledge it."""
        if any(s not in self.present for s in self.gone):
            return
        if time.monotonic() - self.back_at < self.sc.clock.start_delay:
            return
        back = ", ".join(sorted(self.gone))
        # a fleet driver (robots as arrays) restarts with its robots' services: controller@arm0 -> controller
        for s in {*self.gone, *(fleet.split_id(g)[0] for g in self.gone)}:
            if s in self.acked:
                # a step before this one that a lagging participant owed died with it: the new
                # process starts from this step and never saw that one
                self.acked[s] = max(self.acked[s], self.world.time_ns - 1)
        self.gone.clear()
        self.state = "running"
        self.silent, self.waiting_reported = [], False
        self.last_progress = time.monotonic()
        self.log.info("%s back: lockstep resumes at t=%.3f s", back, self.world.time_ns / 1e9)
        self.publish_health_async()
        if self._all_acked():
            self._advance_lockstep()
        else:
            self._publish_step()
