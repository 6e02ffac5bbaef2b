"""Step experiments on the real services: physics, sensors and controller as separate processes, in lockstep.

The tools (``hilsim report step``, ``hilsim tune``) start the scenario's physics, sensors and
controller with :class:`hilsim.launch.launcher.Launcher` (no planner: the rig writes
``joint_trajectory`` itself, and a key with an announced writer accepts no other) and join the run
as one more lockstep participant, :class:`StepRig`, acknowledging on ``sync/step-rig`` every
``PERIOD`` control steps. Because physics waits for its acknowledgement, the rig acts at exact
sim times, so an experiment is as reproducible as the run itself (same seed, same figures):

- at a rig step ``k`` it waits for the controller's ``joint_commands`` of ``k`` (the controller is
  done with that step), then sets the joint's gains for the experiment (its integral emptied
  first, so a trial starts like a fresh controller) through
  ``controller/set_parameters`` (effective from the next control step; the reply comes before the
  rig acknowledges ``k``, so physics cannot step on before), and publishes a one-point
  ``JointTrajectory`` (``time_from_start`` 0) stamped ``k + LEAD`` periods: a step of the reference
  at that sim time. The trajectory and the sensors' ``joint_states`` reach the controller over
  different links, with no order between them, so the stamp lies ``LEAD`` rig periods ahead;
- it records the physics truth (``truth/joint_states``) and the controller's reference
  (``controller/reference``), which proves the step started at the stamped step (a step that
  reached the controller late anyway makes :func:`hilsim.tools.tuning.rig_run.run_experiments` run the batch once more);
- after the measurement window it puts the scenario's own gains back and commands the joint
  home, and lets it settle before the next experiment.

The response measured is the joint's TRUE position, not the encoders'. An experiment may also
command a trajectory (``Experiment.points``) instead of a step: what ``hilsim identify`` excites a
drive with and proves its twin on.

**Hardware in the loop** (a scenario with a joint served by an external server, e.g. a drive on
the CAN bus): the run is realtime, as any run with hardware; the scenario's external servers and
the services that stand in for hardware (the drive emulator) run too. The rig is then not waited
for: it acts on the first control step at or after each of its steps (a trajectory still stamped
``REALTIME_LEAD`` ahead, so the step is exact in sim time; a step the controller took later anyway,
by less than that, is measured from when it took it), never drops a sample as stale, and a response
with samples missing (at most ``REALTIME_LOSS`` of them) is interpolated onto the steps.
A joint served by hardware is measured on its encoder: its server's reports
(``hw/<server>/joint_states``, each stamped with the sim time it came from the drive), the latest
report at each step. (Physics follows the same reports, once they have reached it: its truth of
that joint is the encoder's too, later by the way from the server to physics.)

**The rover** (``controller.type: four_wheel_steer``) has no per-joint reference input: its
controller turns a body twist into each wheel's steering angle and traction speed (its
kinematic layer, :mod:`hilsim.sim.steering`) and closes one PID per loop on them. Its loops are
stepped through that layer, at exact sim times, by the controller's own ``script``
(``controller.params.script``: the twist from a sim time on), which the rig writes into the
scenario before the run; the rig itself only sets the gains at its steps, as for the arm:

- home is a crawl straight ahead (``CRAWL`` = 1 mm/s): every wheel's angle held at 0 (a wheel
  asked not to move at all keeps whatever angle it has, so standing still would hold nothing);
- a **steering** step of ``a`` rad is a crab twist of direction ``a`` at the same crawl: every
  steering loop's reference steps to ``a`` while the wheels stay (nearly) still;
- a **traction** step of ``w`` rad/s is a straight twist ``CRAWL + w·r``: every traction loop's
  speed reference steps by ``w`` (``r`` the wheel radius); the rover drives off and comes back to
  the crawl after the window. An experiment on ``steering`` or ``traction`` measures all four
  wheels' loops of that kind at once; one on a single joint measures that one.

The steering response is the joint's TRUE angle, the traction response its TRUE speed
(``truth/joint_states`` position, velocity); the controller's ``joint_commands`` (its references:
``position`` of a steering joint, ``velocity`` of a traction joint) prove the step started at
the stamped step, as ``controller/reference`` does for the arm.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import SIM, ConfigError, PidGains, Scenario
from hilsim.core.service import Service
from hilsim.sim import control
from hilsim.tools.tuning.rig_types import Experiment, LateStep, Response, RigError, rig_command

__all__ = ["Experiment", "LateStep", "Response", "RigError", "StepRig", "rig_command"]

RIG = "step-rig"
LOOP_SERVICES = ["physics", "sensors", "controller"]
# services standing in for hardware: a HIL loop keeps them (its external servers run anyway)
HARDWARE_STAND_INS = ("drive-emulator", "gps-emulator", "motor-model")
REALTIME_LOSS = 0.02  # realtime: the share of a window's truth samples that may be missing (interpolated)
REPORT_GAP = 0.5  # [s] realtime: a joint served by hardware whose reports stop this long in a window: no measurement
REALTIME_START = 0.5  # [s] realtime: sim time before the first experiment (the services' first steps are slow)
REALTIME_LEAD = 0.2  # [s] realtime: how far ahead of its stamp a trajectory is sent (lockstep: LEAD periods)
TRAJECTORY_LEAD = 1.0  # [s] realtime: the same for a trajectory experiment (the controller holds it until then)
LOOP_SENSORS = ("encoder", "imu")  # what the loops read (the rover's odometry waits for its imu)
CONTROLLERS = ("joint_trajectory", "four_wheel_steer")
CRAWL = 0.001  # [m/s] the rover's home: a crawl straight ahead holds every wheel's angle at 0
GROUPS = ("steering", "traction")  # the rover's loops, by kind


@dataclass
class _Action:
    k: int  # rig step at which it is done (the step of the reference is LEAD periods later)
    gains: dict[str, float]  # live parameters "<joint>.<field>"
    joints: list[str]  # the joints it concerns
    # the arm: the joint's new reference, a trajectory of (time_from_start, position, velocity); None: the
    # rover's script
    points: tuple[tuple[float, float, float], ...] | None
    fresh: bool = False  # empty the joints' integrals before setting the gains (a trial's start)
    lead: int = 0  # physics steps from k to the reference's step (the trajectory's stamp)


@dataclass
class _Loops:
    """What one experiment steps and measures: joints, the quantity, each joint's target."""

    joints: list[str]
    quantity: str  # "position" or "velocity"
    targets: list[float]
    twist: tuple[float, float, float] | None = None  # the rover: the step's body twist


class StepRig(Service):
    """The tool's side of the run: a lockstep participant that steps references at exact sim times."""

    name: ClassVar[str] = RIG
    ack_via: ClassVar[str] = "sync"
    PERIOD: ClassVar[int] = 10  # control steps between acknowledgements (10 ms at 1 kHz)
    LEAD: ClassVar[int] = 10  # rig periods between publishing a trajectory and its stamp

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        return cls.PERIOD * sc.control_decimation

    def __init__(self, sc: Scenario, experiments: Sequence[Experiment],
                 progress: Callable[[int, int], None] | None = None) -> None:
        super().__init__(sc)
        self.period = self.PERIOD * sc.control_decimation
        self.realtime = sc.clock.mode == "realtime"  # hardware in the loop: the rig is not waited for
        # realtime: a trajectory needs only its way to the controller ahead of its stamp (REALTIME_LEAD)
        lead = max(1, math.ceil(REALTIME_LEAD / (self.period * sc.clock.dt))) if self.realtime else self.LEAD
        self.lead = lead * self.period
        self.dt_ns = round(sc.clock.dt * 1e9)
        self.experiments = list(experiments)
        self.progress = progress
        table = control.joint_table(sc.world.model)
        self.table = table
        self.names = list(table.names)
        self.home = _home(sc, self.names)
        self.rover = sc.controller.type == "four_wheel_steer"
        if self.rover:
            from hilsim.core.registry import service_class

            # the rover controller's own geometry, loops and gains (the class that runs it; nothing is opened)
            ctl = service_class("controller", sc)(sc)
            self.geom = ctl.geom
            self.groups = {"steering": list(ctl.steer), "traction": list(ctl.drive)}
            self.max_speed = float(ctl.p.max_speed)
            self.max_wheel_speed = float(ctl.max_wheel_speed)
            base = [PidGains(kp=p.kp, ki=p.ki, kd=p.kd, i_limit=p.i_limit, feedforward=p.feedforward,
                             output_limit=p.output_limit) for p in ctl.pids]
        else:
            base = control.gains_for(sc.controller.gains, self.names, str(sc.source or ""))
        self.loops = [self._loops(e) for e in self.experiments]
        self.actions: dict[int, _Action] = {}
        self.windows: list[tuple[int, int]] = []  # (step index of the step, of the window's end)
        self._done_at: dict[int, int] = {}  # rig step -> experiments finished by then
        # the rover's script: home from the start, each step at its stamp, home again after its window
        self.script: list[tuple[float, float, float, float]] = [(0.0, CRAWL, 0.0, 0.0)]
        # the first step: the first rig step; realtime, once the services had REALTIME_START to get going
        k = self.period * max(1, math.ceil(REALTIME_START / (self.period * sc.clock.dt))) if self.realtime \
            else self.period
        for i, (e, lp) in enumerate(zip(self.experiments, self.loops, strict=True)):
            js = [self.names.index(n) for n in lp.joints]
            own = {f"{n}.{f}": float(v) for n in lp.joints for f, v in e.gains.items()}
            restore = {}
            for n, j in zip(lp.joints, js, strict=True):
                g = base[j]
                limit = g.output_limit if g.output_limit is not None else float(table.effort_upper[j])
                # back to the scenario's gains for the way home (a trial's may be unstable)
                restore.update({f"{n}.{f}": _live(getattr(g, f) if f != "output_limit" else limit) for f in e.gains})
            n_meas = self._steps(e.measure)
            n_settle = self._steps(e.settle)
            # realtime, a trajectory (that cannot be measured from a late start) is sent well ahead
            lead = max(self.lead, self._steps(TRAJECTORY_LEAD)) if self.realtime and e.points else self.lead
            s = k + lead
            kb = s + n_meas
            if self.rover:
                assert lp.twist is not None
                self.actions[k] = _Action(k, own, lp.joints, None, fresh=True)
                self.actions[kb] = _Action(kb, restore, lp.joints, None)
                self.script += [(s * self.dt_ns / 1e9, *lp.twist), (kb * self.dt_ns / 1e9, CRAWL, 0.0, 0.0)]
            else:
                pts = e.points or ((0.0, lp.targets[0], 0.0),)
                self.actions[k] = _Action(k, own, lp.joints, pts, fresh=True, lead=lead)
                self.actions[kb] = _Action(kb, restore, lp.joints, ((0.0, float(self.home[js[0]]), 0.0),),
                                           lead=self.lead)
            self.windows.append((s, s + n_meas))
            self._done_at[kb] = i + 1
            k = kb + self.lead + n_settle
        self.end = k  # the last rig step; the scenario's duration ends the run there
        self.truth_t: list[int] = []
        self.truth_q: list[list[float]] = []
        self.truth_v: list[list[float]] = []
        self.ref_t: list[int] = []
        self.ref_q: list[list[float]] = []
        self.ref_v: list[list[float]] = []
        # realtime: joints served by hardware, measured on their server's reports: joint -> [(stamp, p, v)]
        self.served = [n for n in self.names if sc.joint(n).server != SIM] if self.realtime else []
        self.reports: dict[str, list[tuple[int, float, float]]] = {n: [] for n in self.served}
        # the truth: of the joints measured on it (realtime, with every joint measured served by hardware, none:
        # 500 samples a second fewer for this process to take in, on a machine already busy)
        self.watch_truth = not self.served or any(n not in self.reports for lp in self.loops for n in lp.joints)
        self.queue: queue.Queue[int] = queue.Queue()
        self.done = threading.Event()
        self.error = ""
        self._next_action = 0  # realtime: actions done so far, in order
        self._reported: set[int] = set()  # realtime: the experiments whose progress was said

    def _loops(self, e: Experiment) -> _Loops:
        """The joints an experiment measures and their targets (one-line ConfigError for a bad one)."""
        if not self.rover:
            if e.joint not in self.names:
                raise ConfigError(f"{e.joint}: not a joint of {self.sc.world.model.name} "
                                  f"(joints: {', '.join(self.names)})")
            j = self.names.index(e.joint)
            lo, hi = self.table.lower[j], self.table.upper[j]
            if e.points:
                bad = [p for _, p, _ in e.points if not lo <= p <= hi]
                if bad:
                    raise ConfigError(f"trajectory of {e.joint}: {bad[0]:.3f} is outside its limits "
                                      f"[{lo:.3f}, {hi:.3f}]")
                return _Loops([e.joint], "position", [float(e.points[-1][1])])
            target = self.home[j] + e.step
            if not lo <= target <= hi:
                raise ConfigError(f"step of {e.step:+g} on {e.joint}: {target:.3f} is outside its limits "
                                  f"[{lo:.3f}, {hi:.3f}]")
            return _Loops([e.joint], "position", [float(target)])
        kind = e.joint if e.joint in GROUPS else next((g for g in GROUPS if e.joint in self.groups[g]), None)
        if kind is None:
            loops = [n for g in GROUPS for n in self.groups[g]]
            raise ConfigError(f"{e.joint}: not a loop of the rover (steering, traction or one of {', '.join(loops)})")
        joints = self.groups[kind] if e.joint in GROUPS else [e.joint]
        if kind == "steering":
            # a crab twist of direction a: every wheel's angle reference is a (a in the steering range,
            # strictly inside ±π/2, where a - π and a + π are out of it: no other choice of angle)
            lo, hi = max(self.geom.lower, -math.pi / 2), min(self.geom.upper, math.pi / 2)
            if not lo < e.step < hi or e.step == 0.0:
                raise ConfigError(f"steering step {e.step:+g} rad: expected a non-zero angle strictly inside "
                                  f"({lo:.3f}, {hi:.3f})")
            twist = (CRAWL * math.cos(e.step), CRAWL * math.sin(e.step), 0.0)
            return _Loops(joints, "position", [float(e.step)] * len(joints), twist)
        v = CRAWL + e.step * self.geom.radius
        w = v / self.geom.radius
        if e.step == 0.0 or abs(v) > self.max_speed or abs(w) > self.max_wheel_speed:
            raise ConfigError(f"traction step {e.step:+g} rad/s: expected a non-zero wheel speed the rover may drive "
                              f"(|speed| <= {min(self.max_speed / self.geom.radius, self.max_wheel_speed):.3g} rad/s: "
                              f"controller.params.max_speed {self.max_speed:g} m/s, wheel radius "
                              f"{self.geom.radius:g} m)")
        return _Loops(joints, "velocity", [float(w)] * len(joints), (v, 0.0, 0.0))

    def _steps(self, seconds: float) -> int:
        """Whole rig periods covering ``seconds`` of sim time, in physics steps."""
        per = self.period * self.sc.clock.dt
        return self.period * max(1, math.ceil(seconds / per - 1e-9))

    # ------------------------------------------------------------------ wiring
    def setup(self) -> None:
        self.traj_pub = None if self.rover else self.publisher(self.keys.topic("joint_trajectory"))
        # realtime: every sample is a measurement, none is dropped as stale (stream=False)
        live = not self.realtime
        if not self.rover:  # the rover's references are in its joint_commands
            self.subscribe(self.keys.topic("controller/reference"), msgs.JointState, self._on_reference, stream=live)
        self.subscribe(self.keys.topic("joint_commands"), msgs.JointState, self._on_command, stream=live)
        if self.served:
            self.subscribe(self.keys.all_server_states, msgs.JointState, self._on_report, stream=False)
        if self.watch_truth:
            self.subscribe(self.keys.truth("joint_states"), msgs.JointState, self._on_truth, stream=live)

    def _ordered(self, m: msgs.JointState, values: Sequence[float]) -> list[float]:
        if list(m.name) == self.names:
            return list(values)
        v = dict(zip(m.name, values, strict=True))
        return [v[n] for n in self.names]

    def _on_truth(self, m: msgs.JointState, key: str) -> None:
        ns = msgs.ns_of(m.header.stamp)
        self.truth_t.append(ns)
        self.truth_q.append(self._ordered(m, m.position))
        self.truth_v.append(self._ordered(m, m.velocity) if m.velocity else [math.nan] * len(self.names))
        if self.realtime and ns >= self.end * self.dt_ns:
            self.queue.put(self.end)  # realtime: physics' last step ends the rig, whatever the controller answered

    def _on_report(self, m: msgs.JointState, key: str) -> None:
        ns = msgs.ns_of(m.header.stamp)
        if not self.watch_truth and ns >= self.end * self.dt_ns:
            self.queue.put(self.end)  # the drive's last reports end the rig, whatever the controller answered
        for k, n in enumerate(m.name):
            if n in self.reports and ns > 0:
                self.reports[n].append((ns, m.position[k], m.velocity[k] if m.velocity else math.nan))

    def _on_reference(self, m: msgs.JointState, key: str) -> None:
        self.ref_t.append(msgs.ns_of(m.header.stamp))
        self.ref_q.append(self._ordered(m, m.position))
        self.ref_v.append([math.nan] * len(self.names))

    def _on_command(self, m: msgs.JointState, key: str) -> None:
        ns = msgs.ns_of(m.header.stamp)
        if self.rover:
            self._on_reference(m, key)
            self.ref_v[-1] = self._ordered(m, m.velocity)
        k, rest = divmod(ns, self.dt_ns)
        if rest == 0 and k % self.period == 0:
            self.sim_ns = ns
            self.queue.put(k)  # acted on (and acknowledged) in loop(), not in Zenoh's thread

    # ------------------------------------------------------------------ the rig's steps
    def loop(self) -> None:
        while not self.stop_event.is_set():
            try:
                k = self.queue.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                for a in self._due(k):
                    self._act(a)
            except RigError as e:
                self.error = str(e)
                self.done.set()
                return
            self.ack(k * self.dt_ns)
            if k in self._done_at and self.progress is not None and not self.realtime:
                self.progress(self._done_at[k], len(self.experiments))
            if k >= self.end:
                self.done.set()

    def _due(self, k: int) -> list[_Action]:
        """The actions of rig step ``k``; realtime: every action not done yet at or before ``k`` (the
        controller may skip a step on a loaded machine; the trajectory's stamp keeps the step exact)."""
        if not self.realtime:
            a = self.actions.get(k)
            return [] if a is None else [a]
        keys = sorted(self.actions)
        out = []
        while self._next_action < len(keys) and keys[self._next_action] <= k:
            out.append(self.actions[keys[self._next_action]])
            self._next_action += 1
        if self.progress is not None:
            for kd, n in self._done_at.items():
                if kd < k and kd not in self._reported:
                    self._reported.add(kd)
                    self.progress(n, len(self.experiments))
        return out

    def _act(self, a: _Action) -> None:
        if a.gains:
            if a.fresh:
                # a trial starts like a fresh controller: ki = 0 empties the integral (hilsim.sim.control.Pid)
                self._set_gains({f"{n}.ki": 0.0 for n in a.joints})
            self._set_gains(a.gains)
        if a.points is None or self.traj_pub is None:
            return  # the rover: its script steps the twist at the stamp
        stamp = (a.k + a.lead) * self.dt_ns
        traj = msgs.JointTrajectory(
            header=msgs.header(stamp),
            joint_names=a.joints,
            points=[msgs.JointTrajectoryPoint(positions=[p], velocities=[v], time_from_start=msgs.duration(t))
                    for t, p, v in a.points],
        )
        self.traj_pub.put(traj)

    def _set_gains(self, values: dict[str, float]) -> None:
        assert self.session is not None
        req = msgs.SetParameters(parameters=[msgs.Parameter(name=n, value=v) for n, v in values.items()])
        for reply in self.session.get(self.keys.topic("controller/set_parameters"), payload=msgs.encode(req),
                                      timeout=10.0):
            if reply.ok is None:
                raise RigError(f"controller/set_parameters failed: {reply.err.payload.to_string()}")
            res = msgs.decode(msgs.SetParametersResult, reply.ok.payload.to_bytes())
            if not res.successful:
                raise RigError(f"the controller refused the gains {values}: {res.reason}")
            return
        raise RigError("the controller did not answer controller/set_parameters")

    # ------------------------------------------------------------------ results
    def responses(self) -> list[Response]:
        """One response per joint measured, in the experiments' order."""
        tt = np.asarray(self.truth_t, dtype=np.int64)
        tq = np.asarray(self.truth_q, float)
        tv = np.asarray(self.truth_v, float)
        rt = np.asarray(self.ref_t, dtype=np.int64)
        rq = np.asarray(self.ref_q, float)
        rv = np.asarray(self.ref_v, float)
        out = []
        for e, lp, (s, end) in zip(self.experiments, self.loops, self.windows, strict=True):
            s_ns, end_ns = s * self.dt_ns, end * self.dt_ns
            velocity = lp.quantity == "velocity"
            refs = rv if velocity else rq
            if self.realtime and not e.points:  # a step the controller took late: measured from when it did
                late = self._late_start(e, lp, s_ns, rt, refs)
                s_ns, end_ns = s_ns + late, end_ns + late
            sel = (tt >= s_ns) & (tt <= end_ns)
            t_ns, first = np.unique(tt[sel], return_index=True)
            rows = np.nonzero(sel)[0][first]
            expected = (end - s) + 1
            grid = s_ns + np.arange(expected, dtype=np.int64) * self.dt_ns
            on_truth = any(n not in self.reports for n in lp.joints)
            lost = expected - t_ns.size if on_truth else 0
            if lost and not (self.realtime and lost <= REALTIME_LOSS * expected and t_ns.size > 1):
                raise RigError(f"{e.joint}: {t_ns.size} truth samples in the window of the step, expected "
                               f"{expected} (samples were lost)")
            # the controller's reference proves the step was taken at the stamped step, not later
            if self.realtime:  # the controller may have skipped a step: the nearest on either side
                before, at = np.nonzero(rt < s_ns)[0], np.nonzero(rt >= s_ns)[0]
                before = before[np.argmax(rt[before])] if before.size else None
                at = at[np.argmin(rt[at])] if at.size else None
            else:
                b, a = np.nonzero(rt == s_ns - self.dt_ns * self.sc.control_decimation)[0], np.nonzero(rt == s_ns)[0]
                before, at = (int(b[0]) if b.size else None), (int(a[0]) if a.size else None)
            for n, target in zip(lp.joints, lp.targets, strict=True):
                j = self.names.index(n)
                if e.points:
                    self._check_trajectory(e, j, s_ns, end_ns, rt, rq)
                else:
                    # the rover's speed reference is the twist's scaled by cos(steering error)
                    # (hilsim.sim.steering.traction_scale): a wheel's angle that has not quite come home (a few
                    # 0.01 rad) makes it a few 1e-4 smaller; a step is a step within 0.1 % of its size
                    tol = 1e-3 * abs(e.step) if self.rover else 1e-12
                    if at is None or before is None or abs(refs[at, j] - target) > tol \
                            or abs(refs[before, j] - target) <= tol:
                        why = (f"{n}: the step of {e.step:+g} {'rad/s' if velocity else 'rad'} did not start at "
                               f"t={s_ns / 1e9:.3f} s in the controller (the reference reached it late)")
                        if self.realtime and e.spare:
                            out.append(Response(e, np.zeros(0), np.zeros(0), math.nan, float(target), n,
                                                lp.quantity, s_ns / 1e9, why))
                            continue
                        raise LateStep(why)
                if n in self.reports:  # served by hardware: its encoder's latest report at each step
                    y = self._encoder(n, grid, velocity)
                else:
                    y = (tv if velocity else tq)[rows, j]
                    if lost:  # realtime, a few samples missing: the response on every step, interpolated
                        y = np.interp(grid, t_ns, y)
                if not np.all(np.isfinite(y)):
                    raise RigError(f"{n}: truth/joint_states carries no {lp.quantity} to measure")
                out.append(Response(e, (grid - s_ns) / 1e9, y, float(y[0]), float(target), n, lp.quantity, s_ns / 1e9))
        return out

    def _late_start(self, e: Experiment, lp: _Loops, s_ns: int, rt: np.ndarray, refs: np.ndarray) -> int:
        """Realtime: [ns] by which the controller took a step after its stamp (its reference reached it
        late: the rig heard of its step late on a busy machine), if less than the rig's lead, so the
        window ends before the way home; 0 if on time, or later than that (then :class:`LateStep`)."""
        j = self.names.index(lp.joints[0])
        tol = 1e-3 * abs(e.step) if self.rover else 1e-12
        after = np.nonzero(rt >= s_ns)[0]
        if not after.size:
            return 0
        order = after[np.argsort(rt[after])]
        took = order[np.abs(refs[order, j] - lp.targets[0]) <= tol]
        if not took.size or took[0] == order[0]:
            return 0
        late = int(rt[took[0]] - s_ns)
        return late if late <= self.lead * self.dt_ns else 0

    def _encoder(self, n: str, grid: np.ndarray, velocity: bool) -> np.ndarray:
        """Joint ``n``'s server's latest report at each of ``grid`` [ns] (a sample and hold, as an encoder is read)."""
        r = np.array(sorted(self.reports[n])) if self.reports[n] else np.zeros((0, 3))
        if not r.size or r[0, 0] > grid[0]:
            raise RigError(f"{n}: no report of its server before t={grid[0] / 1e9:.3f} s: nothing to measure")
        gaps = np.diff(r[:, 0])
        if r[-1, 0] < grid[-1] - REPORT_GAP * 1e9 or (gaps.size and gaps.max() > REPORT_GAP * 1e9):
            raise RigError(f"{n}: its server's reports stop for more than {REPORT_GAP:g} s in the window of the step")
        i = np.searchsorted(r[:, 0], grid, side="right") - 1
        return r[i, 2 if velocity else 1]

    def _check_trajectory(self, e: Experiment, j: int, s_ns: int, end_ns: int, rt: np.ndarray,
                          rq: np.ndarray) -> None:
        """The controller's reference in the window is the experiment's trajectory started at ``s_ns``."""
        traj = msgs.JointTrajectory(joint_names=[e.joint], points=[
            msgs.JointTrajectoryPoint(positions=[p], velocities=[v], time_from_start=msgs.duration(t))
            for t, p, v in e.points])
        sampler = control.TrajectorySampler(traj, [e.joint], s_ns, np.zeros(1))
        inside = np.nonzero((rt >= s_ns) & (rt <= end_ns))[0]
        if not inside.size:
            raise LateStep(f"{e.joint}: no reference in the window of the trajectory")
        want = np.array([sampler.sample(int(t))[0][0] for t in rt[inside]])
        if np.max(np.abs(rq[inside, j] - want)) > 1e-9:
            raise LateStep(f"{e.joint}: the trajectory did not start at t={s_ns / 1e9:.3f} s in the controller "
                           f"(the reference reached it late)")


def _live(v: float) -> float:
    """A gain as a live parameter: an unlimited i_limit is sent as a bound no integral reaches."""
    return float(v) if math.isfinite(v) else 1e12


def _home(sc: Scenario, names: list[str]) -> np.ndarray:
    """The joints' positions where physics starts them (hilsim.sim.world: ``world.home``, else the model's
    keyframe ``home``, else its zero pose): where the controller starts holding, and what steps are taken from
    (an imported Panda's joint 4 cannot be at zero)."""
    import mujoco

    if sc.world.home is not None and len(sc.world.home) == len(names):
        return np.array(sc.world.home, dtype=float)
    m = mujoco.MjModel.from_xml_path(str(sc.world.model))
    k = next((i for i in range(m.nkey) if m.key(i).name == "home"), None)
    q = m.key_qpos[k] if k is not None else m.qpos0
    return np.array([q[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]] for n in names])
