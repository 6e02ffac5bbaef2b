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
"""

from __future__ import annotations

import gc
import os
import threading
import time
from typing import Any

import numpy as np
import zenoh

from hilsim.core import fleet, msgs
from hilsim.core.keys import Keys, topic_name
from hilsim.core.scenario import array_misfit, fleet_arrays
from hilsim.core.service import LEVEL_ERROR, Publisher, Service
from hilsim.core.transport import Attachment
from hilsim.sim.fleet_world import FleetWorld
from hilsim.sim.tf import UrdfFrames
from hilsim.sim.world import World

SPIN_NS = 80_000  # realtime: busy-wait at most this long before a deadline
REALTIME_PRIORITY = 10
# realtime: without these the joint commands stop coming (the control law, whatever its type, is
# named controller; it acts on the sensors' joint_states) and the last one would be held
COMMAND_PATH = ("controller", "sensors")
# lockstep: sim time stops this long after the task's result stamp (every robot's), so that a run ends on a
# step set by the task, not by when hilsim up stopped it; longer than physics can run past that stamp before
# the result reaches it (the result host's decision period and lockstep lag: 20 steps of the arm)
TASK_END_MARGIN_NS = 100_000_000
STEP_BINS = 200_000  # lockstep: wall time per step, 1 µs bins (last bin: 200 ms or more)
JITTER_BINS = 20_000  # SCHED_FIFO priority of physics in realtime mode (if permitted)


def _percentile(hist: np.ndarray, n: int, q: float) -> float:
    """The q-quantile of ``n`` samples in a histogram of 1 µs bins, in µs."""
    return float(np.searchsorted(np.cumsum(hist), q * n))


class Participant:
    """A lockstep participant as it announced itself."""

    __slots__ = ("gid", "lag", "period", "via")

    def __init__(self, period: int, lag: int, via: str, gid: str) -> None:
        self.period, self.lag, self.via, self.gid = period, lag, via, gid


class Robot:
    """One robot's part of the world and its truth publishers (a fleet has one per robot)."""

    def __init__(self, svc: Service, keys: Keys, world: World, fleet_robot: str | None = None) -> None:
        self.keys, self.world = keys, world
        self.pub_imu = svc.publisher(keys.truth("imu")) if world.imu_site else None
        # a mobile base (free joint) also has truth/odom; its pose in the world goes on /tf every step
        self.pub_odom = svc.publisher(keys.truth("odom")) if world.base else None
        # the URDF's frames (robot_state_publisher's job): fixed joints once on /tf_static, moving ones
        # on /tf at physics.tf_rate_hz, the URDF itself on robot_description (both transient-local)
        urdf = svc.sc.world.urdf
        self.frames = UrdfFrames(urdf, f"{fleet_robot}/" if fleet_robot else "") if urdf is not None else None
        self.pub_tf = svc.publisher(keys.tf) if world.base or self.frames else None
        if self.frames is not None:
            svc.publisher(keys.tf_static, latched=True).put(self.frames.static(world.time_ns))
            svc.publisher(keys.topic("robot_description"), latched=True).put(msgs.String(data=self.frames.urdf_text))
        self.pub_js = svc.publisher(keys.truth("joint_states"))
        # contacts: published when the set of touching geom pairs changes (and once at start), so
        # every contact is in the record without a message per step
        self.pub_contacts: Publisher = svc.publisher(keys.truth("contacts"))
        self.contact_pairs: frozenset[tuple[int, int]] | None = None


class PhysicsService(Service):
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
        self.ended_by = "the scenario duration"
        if sc.clock.mode == "lockstep" and sc.task.targets:
            for r in self.robots:
                self.subscribe(r.keys.topic("task/result"), msgs.MoveResult, self._on_task_result, stream=False)
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

    def _safe_commands(self, svc: str) -> None:
        """Realtime, the controller or the sensors it acts on gone: as a drive's command watchdog
        does, the simulated joints stop obeying the last command (a torque held for seconds would
        throw the arm about): effort joints get no torque, position joints hold where they are,
        velocity joints stop. The controller's next command, once both are back, replaces this."""
        for r in self.robots:
            js = r.world.joint_states()
            n = len(js.name)
            r.world.command(msgs.JointState(name=list(js.name), position=list(js.position),
                                            velocity=[0.0] * n, effort=[0.0] * n))
        self.log.info("%s gone: simulated joints without torque until commands come again", svc)

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

    def _apply(self, commands: list[tuple[World, msgs.JointState]], cmd: msgs.JointState,
               att: Attachment | None) -> None:
        """Apply ``commands`` (robot, its command), all from the sample ``cmd``, at the step they act on."""
        writer = att.gid.hex() if att is not None else None
        acks = [n for n, p in self.participants.items() if p.via == "joint_commands" and p.gid == writer]
        stamp = msgs.ns_of(cmd.header.stamp)
        if self.participants and self.started and not self.done:
            # lockstep: a command belongs to the step it answers and acts from that step + its
            # writer's lag (clock.controller_lag: the one-sample computation delay); one for
            # another step is stale (or not what it claims to be) and must not act on this one
            now = self.world.time_ns
            due = stamp + max((self.participants[n].lag for n in acks), default=0) * self.sc.dt_ns
            if due < now or stamp > now:
                raise msgs.BadMessage(f"command stamped t={stamp / 1e9:.3f}s, but the current step is "
                                      f"t={now / 1e9:.3f}s")
            if due > now:  # arrived before physics reached its step: acts there, whatever the timing
                self.pending.extend((due, w, c) for w, c in commands)
            else:
                for w, c in commands:
                    w.command(c)
        else:
            for w, c in commands:
                w.command(c)
        for name in acks:
            self._ack(name, stamp)

    def _subscribe_robot_commands(self) -> None:
        """Each robot's own joint_commands (the per-robot path: arrays off, or a robot's controller run
        alone, e.g. ``hilsim run controller@arm3``)."""
        self.robot_commands = True
        for r in self.robots:
            def on_command(cmd: msgs.JointState, key: str, att: Attachment | None, r: Robot = r) -> None:
                self._on_command(r.world, cmd, key, att)

            self.subscribe(r.keys.topic("joint_commands"), msgs.JointState, on_command, with_attachment=True)

    def _on_fleet_command(self, cmd: msgs.JointState, key: str, att: Attachment | None) -> None:
        """Every robot's command in one sample (joints ``<robot>/<joint>``): each robot's slice acts as its
        own joint_commands would; in lockstep it acknowledges the fleet driver's step for every robot."""
        if list(cmd.name) != self.fleet_names:
            raise msgs.BadMessage(f"fleet command names {len(cmd.name)} joints, not the fleet's "
                                  f"{len(self.fleet_names)} ({self.fleet_names[0]} …)")
        n = self.fleet_n
        cuts = [(r.world, slice(k * n, (k + 1) * n)) for k, r in enumerate(self.robots)]
        split = [(w, msgs.JointState(header=cmd.header, name=w.joint_names,
                                     position=cmd.position[c] if cmd.position else [],
                                     velocity=cmd.velocity[c] if cmd.velocity else [],
                                     effort=cmd.effort[c] if cmd.effort else []))
                 for w, c in cuts]
        self._apply(split, cmd, att)

    def _on_command(self, world: World, cmd: msgs.JointState, key: str, att: Attachment | None) -> None:
        self._apply([(world, cmd)], cmd, att)

    def _on_sync(self, clk: msgs.Clock, key: str, att: Attachment | None) -> None:
        name = fleet.service_id(self.sc, key, "sync")
        p = self.participants.get(name)
        if p is None or p.via != "sync":
            return
        if att is None or att.gid.hex() != p.gid:
            self.reject(key, f"acknowledgement not from the {name} that announced itself")
            return
        self._ack(name, msgs.ns_of(clk.clock))

    def _on_server_state(self, js: msgs.JointState, key: str) -> None:
        server = topic_name(key).split("/")[-2]  # …/hw/<server>/joint_states
        served = self.servers.get(server)
        if served is None:
            raise msgs.BadMessage(f"{server!r} serves no joint in this scenario")
        stray = [n for n in js.name if n not in served]
        if stray:
            raise msgs.BadMessage(f"{server} reports joints it does not serve: {stray}")
        if len(js.position) != len(js.name):
            raise msgs.BadMessage("joint server state without positions")
        self.robots[0].world.follow(list(js.name), list(js.position), list(js.velocity))
        self.server_seen[server] = time.monotonic()
        if server in self.server_silent:
            self.server_silent.discard(server)
            self.log.info("joint server %s reports again (t=%.3f s)", server, self.sim_ns / 1e9)

    def _check_servers(self) -> None:
        """A joint server silent for physics.server_timeout (wall) is a fault, said once."""
        now = time.monotonic()
        for server, joints in self.servers.items():
            last = self.server_seen.get(server, self.wall_start)
            if now - last > self.sc.physics.server_timeout and server not in self.server_silent:
                self.server_silent.add(server)
                self.robots[0].world.hold(sorted(joints))
                self.fault(f"joint server {server} silent for {now - last:.2f} s at t={self.sim_ns / 1e9:.3f}s: "
                           f"{', '.join(sorted(joints))} held at the last measured position")

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

    # ------------------------------------------------------------------ stepping
    def _publish_step(self) -> None:
        self.sim_ns = self.world.time_ns
        for r in self.robots:  # each robot's truth, its truth/joint_states last (see docs/keys.md)
            w = r.world
            if r.pub_imu is not None:
                imu = w.imu()
                assert imu is not None
                r.pub_imu.put(imu)
            if w.base is not None and r.pub_odom is not None and r.pub_tf is not None:
                # before truth/joint_states: the sensors' step is complete once they handled that one
                r.pub_odom.put(w.base.odometry(w.time_ns))
                r.pub_tf.put(w.base.transforms(w.time_ns))
            if r.frames is not None and self.tf_period and w.step_index % self.tf_period == 0:
                assert r.pub_tf is not None
                q = dict(zip(w.joint_names, w.positions().tolist(), strict=True))
                r.pub_tf.put(msgs.TFMessage(transforms=r.frames.moving_transforms(w.time_ns, q)))
            if w.data.ncon or r.contact_pairs:  # the arm: nothing to look at on almost every step
                pairs = w.contact_pairs()
                self.contact_steps += bool(pairs)
                if pairs != r.contact_pairs:
                    r.contact_pairs = pairs
                    r.pub_contacts.put(w.contacts())
            elif r.contact_pairs is None:
                r.contact_pairs = frozenset()
                r.pub_contacts.put(w.contacts())
            if not self.arrays or r.pub_js.wanted(covered=True):  # arrays: the fleet sample carries it anyway
                r.pub_js.put(w.joint_states())
            else:
                r.pub_js.skip()
        if self.arrays:
            if self.pub_fleet_js.wanted():
                d = self.world.data
                self.pub_fleet_js.put(msgs.JointState(
                    header=msgs.header(self.world.time_ns, "world"), name=self.fleet_names,
                    position=d.qpos[self._fq].tolist(), velocity=d.qvel[self._fv].tolist(),
                    effort=d.actuator_force[self._fa].tolist()))
            else:
                self.pub_fleet_js.skip()
        self.pub_clock.put(msgs.Clock(clock=msgs.stamp(self.world.time_ns)))

    def _advance(self) -> None:
        """Step once and publish; in lockstep also keep going while nothing needs waiting for."""
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

    def _on_task_result(self, msg: msgs.MoveResult, key: str) -> None:
        """Lockstep: a robot's task ended; once every robot's did, sim time stops ``TASK_END_MARGIN_NS`` after
        the latest result's stamp, on that step in every run with the same seed."""
        with self.lock:
            self.task_ends[key] = msgs.ns_of(msg.header.stamp)
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

    def _jitter_figures(self) -> dict[str, str]:
        out = {}
        if self.ticks:
            out["jitter_p50_us"] = f"{_percentile(self.jitter_hist, self.ticks, 0.5):.0f}"
            out["jitter_p99_us"] = f"{_percentile(self.jitter_hist, self.ticks, 0.99):.0f}"
        if self.step_count:
            out["step_p50_us"] = f"{_percentile(self.step_hist, self.step_count, 0.5):.0f}"
            out["step_p99_us"] = f"{_percentile(self.step_hist, self.step_count, 0.99):.0f}"
        return out

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
        """The process (launch unit) a service runs in: itself, or a composed ``a+b`` (hilsim.run.compose)."""
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

    def _raise_priority(self) -> None:
        """Realtime: ask the kernel for a real-time scheduling class, as HIL setups do; the
        other services then cannot delay a tick. Without the privilege, say so and go on."""
        try:
            # every thread of the process: a Zenoh thread preempted while holding the GIL
            # would otherwise stall the stepping thread (priority inversion)
            for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
            self.log.info("realtime: running with SCHED_FIFO priority %d", REALTIME_PRIORITY)
        except (PermissionError, AttributeError, OSError) as e:
            self.log.warning("realtime: could not get a real-time scheduling class (%s); "
                             "tick jitter will depend on the machine's load", e)

    def _realtime_loop(self) -> None:
        self._raise_priority()
        # a full garbage collection can take milliseconds: move what exists now out of its
        # reach and make young-generation collections rarer
        gc.freeze()
        gc.set_threshold(50_000, 50, 100)
        dt_ns = self.sc.dt_ns
        t0 = time.perf_counter_ns()
        k = 0
        while not self.stop_event.is_set() and not self.done:
            k += 1
            deadline = t0 + k * dt_ns
            # sleep most of the way, then spin: time.sleep alone overshoots by ~60 µs. The spin
            # is kept short because on a small machine it takes CPU from the other services.
            while True:
                now = time.perf_counter_ns()
                remaining = deadline - now
                if remaining <= 0:
                    break
                if remaining > SPIN_NS:
                    time.sleep((remaining - SPIN_NS) / 1e9)
            with self.lock:
                self._advance()
                if self.done:
                    break
                if self.servers and k % 50 == 0:
                    self._check_servers()
            self.jitter_hist[min((now - deadline) // 1000, JITTER_BINS)] += 1
            self.ticks += 1
            if time.perf_counter_ns() > deadline + dt_ns:
                self.overruns += 1
        if self.done:
            self.stop_event.wait()

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
