"""``hilsim up`` following the run: what its services report, turned into its :class:`Outcome` as it goes.

The :class:`Follower` prints each goal's result, every fault and the lockstep pauses as they happen,
keeps every service's last health, and says when the run has ended (the task result of every robot,
physics done, or a stalled lockstep). Only the services' own samples are believed
(:mod:`hilsim.core.provenance`); the others are counted. What the summary reports comes from the
service that knows it: sim time and counts from each service's *final* health (``final: 1``, sent at
its exit; nothing later replaces it), a goal's result from its first report. That a sample is the
service's own rests on the run's router letting only the run's processes write (docs/security.md):
a gid and a sequence number are public, any writer can copy them. The launcher (:mod:`hilsim.launch.launcher`)
supervises the processes and records their deaths and restarts in the same outcome;
:mod:`hilsim.launch.summary` prints it at the end.

Reads: the ROS 2 graph ``@ros2_lv/<domain>/**`` (liveliness: who writes what), ``/<robot>/task/result``,
``planner/result`` and ``navigator/result``, ``health/*``, ``log/*`` (faults); with ``robots: N``
every robot's (``<domain>/*/…``). Writes nothing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from hilsim.core import fleet, msgs, transport
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys, topic_name
from hilsim.core.provenance import Provenance
from hilsim.core.rights import owners

TASK_END_WAIT_S = 60.0  # lockstep: wall seconds the end of a task waits for physics to stop on its step


@dataclass
class Restart:
    """One restart of a service, for the summary."""

    name: str
    rc: int
    sim_time: str  # physics' sim time when the death was noticed (its last health)
    back_after: float | None = None  # wall seconds from the death to its liveliness token


@dataclass
class Outcome:
    task: msgs.MoveResult | None = None
    tasks: dict[str, msgs.MoveResult] = field(default_factory=dict)  # per robot (robots > 1)
    results: list[msgs.MoveResult] = field(default_factory=list)
    result_robots: list[str] = field(default_factory=list)  # the robot of each of results
    health: dict[str, dict[str, str]] = field(default_factory=dict)
    physics_done: bool = False
    died: list[tuple[str, int]] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    stalled: str = ""  # physics waited longer than clock.ack_timeout for a lockstep participant
    interrupted: bool = False
    signal: int = 0  # the stop signal that interrupted the run (SIGINT, SIGTERM; hilsim.launch.launcher)
    killed: list[str] = field(default_factory=list)  # services killed (SIGKILL) on a second stop signal
    not_started: list[str] = field(default_factory=list)  # services that never announced themselves
    restarts: list[Restart] = field(default_factory=list)


class Follower:
    """The run's results, health and faults, followed into :attr:`outcome` (under ``lock``, shared
    with the launcher; ``changed`` is set at each news)."""

    def __init__(self, sc: Scenario, follow_keys: Keys, robots: list[str], prov: Provenance, *,
                 lock: threading.Lock, changed: threading.Event, say: Callable[[str], None]) -> None:
        self.sc = sc
        self.keys = Keys.of(sc)
        self.follow_keys = follow_keys  # the robot's, or with robots > 1 every robot's (<domain>/*/…)
        self.robots = robots
        self.prov = prov
        self.lock = lock
        self.changed = changed
        self.say = say
        self.outcome = Outcome()
        self.untrusted = 0  # samples on the keys it follows from writers other than the services
        self.paused_for = ""  # lockstep: the services physics waits for to come back (its health)
        self.recording_stopped = ""  # the recorder stopped recording (logger.max_size, min_free): its health
        # lockstep: services silent for clock.ack_timeout that are to be restarted (taken by the launcher)
        self.silent: set[str] = set()
        self._silent_seen: set[str] = set()  # as physics' last health said
        self.stalled_for: set[str] = set()  # lockstep: services physics waited for in vain (the run ends)
        # per service, the writer of its final health (published at its exit): the summary's figures
        self.final: dict[str, bytes] = {}
        self._task_at: float | None = None  # lockstep: when the task ended (wall), physics then stops on its step

    def subscribe(self, session: zenoh.Session) -> list[Any]:
        """Declare its subscribers on ``session`` (the caller undeclares them)."""
        fk = self.follow_keys
        # the results of the services this run has (the key table's writers): a result key no service of
        # the run writes is the tools' to write (hilsim.core.rights), and no result of the run's
        results = [t for t in ("planner/result", "navigator/result", "task/result") if owners(self.sc, t)]
        return [
            # first: who writes what, so that only the services' own samples are believed
            session.liveliness().declare_subscriber(self.keys.all_writers, self.prov.on_token, history=True),
            *(session.declare_subscriber(fk.topic(t), self._on_result) for t in results),
            session.declare_subscriber(fk.health("*"), self._on_health),
            session.declare_subscriber(fk.log("*"), self._on_log),
        ]

    def ended(self) -> bool:
        """The run is over as far as its services say: the task (of every robot) ended, physics is
        done (the duration), or the lockstep stalled (said here)."""
        with self.lock:
            task_over = self.outcome.task is not None or (len(self.robots) > 1
                                                           and len(self.outcome.tasks) == len(self.robots))
            if self.outcome.physics_done:
                return True
            if task_over and self.sc.clock.mode == "lockstep" and "physics" in self.sc.services \
                    and not self.outcome.stalled:
                # physics stops sim time on a step the task sets (hilsim.services.physics): the run ends there,
                # the same in every run with the same seed, not when this process heard of the task's end
                if self._task_at is None:
                    self._task_at = time.monotonic()
                if time.monotonic() - self._task_at < TASK_END_WAIT_S:
                    return False
                self.say(f"warning: physics did not stop within {TASK_END_WAIT_S:g} s of the task's end; stopping")
            if task_over:
                return True
            if self.outcome.stalled:
                self.say(f"error: the simulation stalled: {self.outcome.stalled}; stopping")
                return True
        return False

    def progress(self) -> None:
        """Say where the run is (physics' last health)."""
        ph = self.outcome.health.get("physics", {})
        self.say(f"  … sim time {ph.get('sim_time', '?')} s, real-time factor {ph.get('real_time_factor', '?')}")

    def _trusted(self, sample: zenoh.Sample) -> bool:
        """A sample from the key's announced writer (not a stranger's, nor a duplicate), on a key that has
        one (a result put before anyone announced a writer for its key is nobody's)."""
        key = str(sample.key_expr)
        why, _ = self.prov.check(key, transport.read_attachment(sample), sample.payload.to_bytes())
        if why is None and key not in self.prov.restricted:
            why = "no announced writer"
        if why is not None:
            self.untrusted += 1
        return why is None

    def _on_result(self, sample: zenoh.Sample) -> None:
        """``planner/result``: one goal ended (progress); ``task/result``: the task ended (the run ends)."""
        if not self._trusted(sample):
            return
        try:
            res = msgs.decode(msgs.MoveResult, sample.payload.to_bytes())
        except msgs.BadMessage as e:
            self.say(f"warning: unreadable result on {sample.key_expr}: {e}")
            return
        key = str(sample.key_expr)
        name = topic_name(key)  # /<robot>/task/result, /<robot>/planner/result …
        robot = name.split("/")[1]
        with self.lock:
            if name.endswith("/task/result"):
                self.outcome.tasks[robot] = res
                if len(self.robots) == 1:
                    self.outcome.task = res
            elif res.goal_id != "task":  # the planner repeats the task's result on planner/result
                if any(r.goal_id == res.goal_id and who == robot
                       for r, who in zip(self.outcome.results, self.outcome.result_robots, strict=True)):
                    return  # a goal ends once: its first result stands
                self.outcome.results.append(res)
                self.outcome.result_robots.append(robot)
                err = max((abs(e) for e in res.execution_error), default=float("nan"))
                status = "reached" if res.success else f"FAILED ({res.message})"
                if name.endswith("/navigator/result"):  # a rover goal: [m, rad] (the key ends with its type and hash)
                    pos, yaw = (*res.execution_error, float("nan"), float("nan"))[:2]
                    what = f"position error {pos:.3f} m, yaw error {yaw:.3f} rad (odometry)"
                else:
                    what = f"max joint error {err:.4f} rad"
                who = f"{robot}: " if len(self.robots) > 1 else ""
                self.say(f"  {who}{res.goal_id}: {status} at t={msgs.seconds(res.header.stamp):.2f}s sim, "
                         f"planning {res.planning_time:.2f}s, {what}")
        self.changed.set()

    def _on_log(self, sample: zenoh.Sample) -> None:
        """Faults of any service (a silent joint server, a stalled lockstep) as they happen, and the
        notices a service publishes at INFO (the recorder's: a file of the recording closed)."""
        if not self._trusted(sample):
            return
        try:
            m = msgs.decode(msgs.Log, sample.payload.to_bytes())
        except msgs.BadMessage:
            return
        if m.level >= 40:
            with self.lock:
                self.outcome.faults.append(f"{m.name}: {m.msg}")
            self.say(f"  fault: {m.name}: {m.msg}")
        elif m.level == 20:  # rcl_interfaces/msg/Log INFO: published only as a notice for the run's screen
            self.say(f"  {m.name}: {m.msg}")

    def _on_health(self, sample: zenoh.Sample) -> None:
        if not self._trusted(sample):
            return
        try:
            h = msgs.decode(msgs.DiagnosticArray, sample.payload.to_bytes())
        except msgs.BadMessage:
            return
        # a robot's service (robots > 1) by <service>@<robot>: the robots' health apart
        sid = fleet.service_id(self.sc, str(sample.key_expr), "health")
        att = transport.read_attachment(sample)
        writer = att.gid if att is not None else b""
        for st in h.status:
            vals = {kv.key: kv.value for kv in st.values}
            name = sid if st.name == sid.split("@")[0] else st.name
            with self.lock:
                if self.final.get(name) == writer:
                    continue  # its process's final report is in: nothing that comes later replaces it
                if vals.get("final") == "1":
                    self.final[name] = writer
                else:
                    self.final.pop(name, None)  # a new process of it (restarted): its reports count again
                self.outcome.health[name] = vals
                if st.name == "physics" and vals.get("state") == "done":
                    self.outcome.physics_done = True
                if st.name == "physics" and vals.get("state") == "stalled" and not self.outcome.stalled:
                    self.outcome.stalled = vals.get("last_error", "lockstep stalled")
                    # whom it waited for: silent (stopped or hung), they are killed at the end (hilsim.launch.launcher)
                    self.stalled_for = {s for s in (vals.get("waiting_for", "") + "," + vals.get("paused_for", ""))
                                        .split(",") if s}
                if st.name == "physics":  # silent for clock.ack_timeout, to be restarted (hilsim.launch.launcher)
                    silent = {s for s in vals.get("silent", "").split(",") if s}
                    if silent != self._silent_seen:  # news once per silence (health repeats it each second)
                        self.silent, self._silent_seen = set(silent), silent
                if st.name == "physics":
                    self._paused(vals)
                if st.name == "logger" and vals.get("recording_stopped") and not self.recording_stopped:
                    self.recording_stopped = vals["recording_stopped"]
                    self.say(f"  logger: recording stopped {self.recording_stopped}; the run goes on")
        self.changed.set()

    def _paused(self, vals: dict[str, str]) -> None:
        """Lockstep physics pauses sim time while a service is gone (under self.lock): say so once
        per pause. Physics also says at which sim time each service left: the restarts' time."""
        for r in self.outcome.restarts:
            left = f"left:{r.name.split('+')[0]}"  # a composed process: its first service
            if r.back_after is None and left in vals:
                r.sim_time = vals[left]
        gone = vals.get("paused_for", "")
        if gone and gone != self.paused_for:
            self.say(f"  physics: sim time paused at t={vals.get('sim_time', '?')} s until {gone} is back")
        elif not gone and self.paused_for:
            self.say(f"  physics: sim time runs again from t={vals.get('sim_time', '?')} s")
        self.paused_for = gone
