"""Physics service: MuJoCo owns sim time and the robot's true state.

Reads:
  ``<prefix>/<robot>/joint_commands``        sensor_msgs/JointState: per joint, the field of its
                                             interface (``joints.<name>.interface``); any subset
  ``<prefix>/<robot>/hw/<server>/joint_states`` sensor_msgs/JointState measured by an external
                                             joint server; the joints it serves follow it
  ``<prefix>/<robot>/sync/<service>``        rosgraph_msgs/Clock, lockstep acknowledgements
  ``<prefix>/<robot>/task/result``           lockstep with a task: sim time stops ``TASK_END_MARGIN_NS``
                                             after every robot's result (a run ends on a step the task sets)
  ``<prefix>/<robot>/alive/*``, ``lockstep/**`` liveliness: who is running, who is a lockstep
                                             participant (period, how it acknowledges, its writer id)
Writes (every step, stamped with the step's sim time):
  ``<prefix>/<robot>/truth/imu``          sensor_msgs/Imu at ``physics.truth_imu_site`` (if set)
  ``<prefix>/<robot>/truth/odom``         nav_msgs/Odometry of the chassis, world frame (mobile
                                          robots only: a model whose root body has a free joint)
  ``/tf``                                 tf2_msgs/TFMessage: world → chassis → its sensor sites
                                          (mobile robots, every step); the URDF's moving joints
                                          (``physics.tf_rate_hz``, from the true joint positions)
  ``/tf_static``, ``<ns>/robot_description`` the URDF's fixed joints, the URDF (std_msgs/String);
                                          once, transient-local (kept for late subscribers)
  ``<prefix>/<robot>/truth/joint_states`` sensor_msgs/JointState (position, velocity, applied effort)
  ``<prefix>/clock``                      rosgraph_msgs/Clock
  ``<prefix>/<robot>/truth/contacts``     hilsim_msgs/Contacts: every contact, published at step 0
                                          and whenever the set of touching geom pairs changes

Many robots (``robots: N``, :mod:`hilsim.core.fleet`): one MuJoCo world holding N copies of the
world model; every key above that is under ``<prefix>/<robot>/`` is then read and written once per
robot ``<robot><k>`` (its joints by their single-robot names), the clock stays one, and a
participant is ``<service>@<robot>`` (its tokens and acknowledgements under that robot's keys).

Robots as arrays (``robots: N`` with ``fleet.arrays``, :mod:`hilsim.core.fleet`): physics also writes
``<prefix>/<robot>/fleet/truth/joint_states`` (every robot's truth in one sample, joints
``<robot><k>/<joint>``, after the robots' own truth) and reads ``<prefix>/<robot>/fleet/joint_commands``
(each robot's slice acts as its own ``joint_commands`` would; in lockstep the acknowledgement of the
fleet controller, one participant for every robot) and ``<prefix>/<robot>/sync/*`` (a fleet driver's
acknowledgement); a robot's own ``truth/joint_states`` is then built only while someone subscribes it,
and the robots' own ``joint_commands`` are read only when no fleet controller is alive at the start
(each robot's controller run alone).

Lockstep (default): step k+1 happens only once every participant acknowledged step k (see
docs/keys.md). Participants announce themselves (``lockstep/<service>/<period>/<via>/<gid>``),
so physics needs no list of them; a ``joint_commands`` sample acknowledges a step only when
written by the participant that announced it. The step is taken in the thread that delivers the
last acknowledgement, which avoids a thread hand-off per step. Realtime: steps are paced by the
wall clock, and a step that finishes after its deadline counts as an overrun. An external joint
server silent for ``physics.server_timeout`` is a fault (published; said again on recovery).

The service is this module (its setup, the services' comings and goings, stepping, the start, the
lockstep loop and health) and its bases, one concern each: :mod:`hilsim.services.physics_truth` (each
robot's truth publishers, the step's truth out), :mod:`hilsim.services.physics_lockstep` (the lockstep
barrier: participants, acknowledgements, silence, pauses, the task's end),
:mod:`hilsim.services.physics_commands` (joint commands, each robot's and the fleet's, and the realtime
watchdog), :mod:`hilsim.services.physics_servers` (external joint servers),
:mod:`hilsim.services.physics_realtime` (the realtime loop, tick jitter and step latency).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np
import zenoh

from hilsim.core import fleet, msgs
from hilsim.core.keys import Keys
from hilsim.core.scenario import array_misfit, fleet_arrays
from hilsim.core.service import LEVEL_ERROR
from hilsim.services.physics_commands import PhysicsCommands
from hilsim.services.physics_lockstep import TASK_END_MARGIN_NS, Participant
from hilsim.services.physics_realtime import JITTER_BINS, STEP_BINS, PhysicsRealtime
from hilsim.services.physics_truth import Robot
from hilsim.sim.fleet_world import FleetWorld
from hilsim.sim.world import World

# realtime: without these the joint commands stop coming (the control law, whatever its type, is
# named controller; it acts on the sensors' joint_states) and the last one would be held
COMMAND_PATH = ("controller", "sensors")
__all__ = ["COMMAND_PATH", "TASK_END_MARGIN_NS", "Participant", "PhysicsService", "Robot"]


class PhysicsService(PhysicsRealtime, PhysicsCommands):
    name = "physics"
    stop_rank = 0  # stopped first: sim time ends before its consumers go
    world: World | FleetWorld  # loaded in setup(), inside run()'s error handling

    def __init__(self, scenario: Any) -> None:
        super().__init__(scenario)
        # tick lateness histogram, 1 µs bins (last bin: JITTER_BINS µs or more): O(1) per tick,
        # and percentiles for health cost microseconds instead of sorting every tick so far
        self.jitter_hist = np.zeros(JITTER_BINS + 1, dtype=np.int64)
        self.ticks = 0
        # lockstep: wall time from one step to the next (the whole round: truth out, every
        # acknowledgement back), the per-step latency `hilsim bench scale` reports
        self.step_hist = np.zeros(STEP_BINS + 1, dtype=np.int64)
        self.step_count = 0
        self._last_step_ns = 0

    def setup(self) -> None:
        sc = self.sc
        if sc.robots > 1:
            self.world = FleetWorld(sc)
            views = self.world.views
        else:
            self.world = World(sc)
            views = [self.world]
        self.participants: dict[str, Participant] = {}  # from lockstep tokens, fixed at step 0
        self.announced: dict[str, Participant] = {}
        self.acked: dict[str, int] = {}
        self.present: set[str] = set()
        # lockstep: services of the scenario that left during the run (sim time is paused until
        # every one is back), when the last one came back, how often the run was paused
        self.gone: dict[str, int] = {}
        self.left: dict[str, int] = {}  # sim time each service last left at (for hilsim up's report)
        self.back_at = 0.0
        self.pauses = 0
        self.started = False
        self.done = False
        self.end_ns = round(sc.duration * 1e9) if sc.duration else None
        self.last_progress = time.monotonic()
        self.waiting_reported = False
        self.pending: list[tuple[int, World, msgs.JointState]] = []  # lockstep: (due step [ns], robot, command)
        self.silent: list[str] = []  # lockstep participants silent for clock.ack_timeout, to be restarted
        robot_keys = [Keys.of(sc, r) for r in fleet.robot_names(sc)]
        self.robots = [Robot(self, k, v, k.robot if sc.robots > 1 else None)
                       for k, v in zip(robot_keys, views, strict=True)]
        rate = sc.physics.tf_rate_hz
        self.tf_period = max(1, round(1.0 / (rate * sc.clock.dt))) if rate > 0 else 0
        self.pub_clock = self.publisher(self.keys.clock)
        self.contact_steps = 0
        self.arrays = fleet_arrays(sc)
        if sc.robots > 1 and sc.fleet.arrays and not self.arrays:
            self.log.info("fleet.arrays: %s; every robot runs on its own keys", array_misfit(sc))
        self.robot_commands = False  # whether the robots' own joint_commands are subscribed
        if not self.arrays:
            self._subscribe_robot_commands()
        for r in self.robots:
            self.subscribe(r.keys.sync("*"), msgs.Clock, self._on_sync, with_attachment=True)
        if self.arrays:
            # robots as arrays (hilsim.core.fleet): every robot's truth in one sample, every robot's command
            # in one; a fleet driver's acknowledgement (sync) comes under the scenario's own namespace
            w0 = views[0]
            self.fleet_names = fleet.joint_names(sc, list(w0.joint_names))
            self.fleet_n = len(w0.joint_names)
            self._fq = np.concatenate([np.asarray(v.qpos_adr).ravel() for v in views])
            self._fv = np.concatenate([np.asarray(v.dof_adr).ravel() for v in views])
            self._fa = np.concatenate([np.arange(v._act.start, v._act.stop) for v in views])
            self.pub_fleet_js = self.publisher(self.keys.fleet("truth/joint_states"))
            self.subscribe(self.keys.fleet("joint_commands"), msgs.JointState, self._on_fleet_command,
                           with_attachment=True)
            self.subscribe(self.keys.sync("*"), msgs.Clock, self._on_sync, with_attachment=True)
        # the scenario's own namespace, or (robots > 1) every robot's: whose tokens physics follows
        ns = Keys.of(sc, "*") if sc.robots > 1 else self.keys
        # external joint servers (a single robot only): which joints each serves, when it last reported
        self.servers: dict[str, set[str]] = {}
        w0 = views[0]
        for jn, srv in zip(w0.joint_names, w0.servers, strict=True):
            if w0.external[w0.index[jn]]:
                self.servers.setdefault(srv, set()).add(jn)
        self.server_seen: dict[str, float] = {}
        self.server_silent: set[str] = set()
        if self.servers:
            self.subscribe(self.keys.all_server_states, msgs.JointState, self._on_server_state)
        # lockstep with a task: the run ends on a step set by it (TASK_END_MARGIN_NS after every robot's result)
        self.task_ends: dict[str, int] = {}
        self.task_results: deque[tuple[str, int]] = deque()  # arrived, for the stepping to take (_take_task_results)
        self.ended_by = "the scenario duration"
        if sc.clock.mode == "lockstep" and sc.task.targets:
            for r in self.robots:
                self.subscribe(r.keys.topic("task/result"), msgs.MoveResult, self._on_task_result, stream=False,
                               locked=False)
        live = self.session.liveliness()
        self._declared.append(live.declare_subscriber(ns.all_alive, self._on_alive, history=True))
        if sc.clock.mode == "lockstep":
            self._declared.append(live.declare_subscriber(ns.all_lockstep, self._on_lockstep, history=True))
        self.wall_start = 0.0
        self.steps_done = 0

    # ------------------------------------------------------------------ inputs
    def _on_alive(self, sample: zenoh.Sample) -> None:
        svc = fleet.service_id(self.sc, str(sample.key_expr), "alive")
        with self.lock:
            if self.stop_event.is_set() or svc == self.name:
                return  # stopping: the others leave after us anyway
            if sample.kind == zenoh.SampleKind.PUT:
                if svc not in self.present and svc in self.sc.processes():
                    self.log.info("%s is here", svc)
                self.present.add(svc)
                if svc in self.gone:
                    self.back_at = time.monotonic()
                    self.log.info("%s is back (t=%.3f s)", svc, self.sim_ns / 1e9)
                return
            self.present.discard(svc)
            if not self.started or self.done or svc not in self.sc.processes():
                return
            self.left[svc] = self.world.time_ns
            self.publish_health_async()
            if self.sc.clock.mode != "lockstep":
                # realtime: the wall clock does not wait; a restarted service just joins again
                self.warn(f"{svc} left the simulation at t={self.sim_ns / 1e9:.3f}s")
                if svc in COMMAND_PATH:
                    self._safe_commands(svc)
                return
            # lockstep: whatever the service was doing for the current step is lost with it (a
            # command, the encoders, a plan, the recording); step on only once it is back
            if not self.gone:
                self.pauses += 1
            self.gone[svc] = self.world.time_ns
            self.state = "paused"
            # a warning, not an error of physics: hilsim up reports the death (and any restart)
            self.warn(f"{svc} left the simulation at t={self.world.time_ns / 1e9:.3f}s; "
                      f"sim time is paused until it is back")

    # ------------------------------------------------------------------ stepping
    def _advance(self) -> None:
        """Step once and publish; in lockstep also keep going while nothing needs waiting for."""
        if self.task_results:
            self._take_task_results()
        if self.end_ns is not None and self.world.time_ns >= self.end_ns:
            self._finish()
            return
        if self.pending:  # lagging commands due at this step act on it
            now = self.world.time_ns
            for _, world, cmd in [c for c in self.pending if c[0] <= now]:
                world.command(cmd)
            self.pending = [c for c in self.pending if c[0] > now]
        self.world.step()
        if self.participants:
            now = time.perf_counter_ns()
            if self._last_step_ns:
                self.step_hist[min((now - self._last_step_ns) // 1000, STEP_BINS)] += 1
                self.step_count += 1
            self._last_step_ns = now
        self.steps_done += 1
        self.last_progress = time.monotonic()
        if self.waiting_reported:
            self.waiting_reported = False
            self.silent = []
            if self.state == "stalled":
                self.state = "running"
                self.log.info("lockstep acknowledgements arrive again")
        self._publish_step()

    def _finish(self) -> None:
        if not self.done:
            self.done = True
            self.state = "done"
            self.log.info("reached the end of %s (%.3f s sim)", self.ended_by, self.world.time_ns / 1e9)
            self.publish_health_async()

    def publish_health_async(self) -> None:
        threading.Thread(target=self.publish_health, daemon=True).start()

    def health_values(self) -> dict[str, Any]:
        if not hasattr(self, "world"):
            return {}
        wall = max(time.monotonic() - self.wall_start, 1e-9) if self.wall_start else 0.0
        return {
            "sim_time": f"{self.world.time_ns / 1e9:.3f}",
            "steps": self.steps_done,
            "real_time_factor": f"{self.world.time_ns / 1e9 / wall:.3f}" if wall else "0",
            "clock_mode": self.sc.clock.mode,
            "waiting_for": ",".join(self._missing()),
            "silent": ",".join(self.silent),  # to be restarted by hilsim up (_report_silent)
            "servers_silent": ",".join(sorted(self.server_silent)),
            "clipped_commands": self.world.clipped,
            "contact_steps": self.contact_steps,
            "paused_for": ",".join(sorted(self.gone)),
            **{f"left:{s}": f"{t / 1e9:.3f}" for s, t in self.left.items()},
            "pauses": self.pauses,
            **self._jitter_figures(),
        }

    def _wait_for_services(self) -> bool:
        """Before step 0: every service of the scenario is live, then a short grace.

        A liveliness token proves its owner's subscriptions are known *here*; the other peers
        (e.g. the sensors publishing to the planner) learn of them over their own links a moment
        later, and a step-0 message sent before that would be lost and stall the lockstep.
        """
        deadline = time.monotonic() + self.sc.clock.start_timeout
        others = [s for s in self.sc.processes() if s != self.name]
        if others:
            self.log.info("waiting for %s", ", ".join(others))
        while not self.stop_event.is_set():
            with self.lock:
                missing = [p for p in others if p not in self.present]
            if not missing:
                with self.lock:
                    # arrays: no fleet controller driving every robot (e.g. each robot's controller run
                    # alone): physics listens to the robots' own commands. Before the start delay, so
                    # their publishers learn of the subscription before step 0.
                    if self.arrays and not self.robot_commands and "controller" not in self.present:
                        self._subscribe_robot_commands()
                if self.stop_event.wait(self.sc.clock.start_delay):
                    return False
                self.fix_participants()
                return True
            if time.monotonic() > deadline:
                self.state = "fault"
                self.fault(f"services never appeared: {', '.join(missing)}")
                return False
            self.stop_event.wait(0.01)
        return False

    def loop(self) -> None:
        if not self._wait_for_services():
            return
        self.wall_start = time.monotonic()
        with self.lock:
            self.started = True
            self._publish_step()  # step 0: the state before any command
            if self.participants and self._all_acked():
                self._advance_lockstep()
        if self.sc.clock.mode == "realtime":
            self._realtime_loop()
            return
        if not self.participants:
            # lockstep with nobody to wait for: run free, as fast as the step allows
            while not self.stop_event.is_set() and not self.done:
                with self.lock:
                    self._advance()
        while not self.stop_event.wait(0.05 if self.gone else 0.2):
            with self.lock:
                if self.gone and not self.done:
                    self._resume_when_back()
                stalled = time.monotonic() - self.last_progress
                if not self.done and stalled > self.sc.clock.ack_timeout and not self.waiting_reported:
                    self.waiting_reported = True
                    self._report_silent(stalled)

    def teardown(self) -> None:
        if self.ticks:
            f = self._jitter_figures()
            self.log.info("realtime tick jitter: p50 %s µs, p99 %s µs, overruns %d of %d steps",
                          f["jitter_p50_us"], f["jitter_p99_us"], self.overruns, self.ticks)

    def health(self) -> msgs.DiagnosticArray:
        h = super().health()
        if self.state == "done":
            h.status[0].level = 0
        elif self.state in ("fault", "stalled", "paused"):
            h.status[0].level = LEVEL_ERROR
        return h
