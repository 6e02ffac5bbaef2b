"""Step experiments on the real services: physics, sensors and controller as separate processes, in lockstep.

The tools (``hilsim report step``, ``hilsim tune``) start the scenario's physics, sensors and
controller with :class:`hilsim.launcher.Launcher` (no planner: the rig writes
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
  reached the controller late anyway makes :func:`run_experiments` run the batch once more);
- after the measurement window it puts the scenario's own gains back and commands the joint
  home, and lets it settle before the next experiment.

The response measured is the joint's TRUE position, not the encoders'.
"""

from __future__ import annotations

import logging
import math
import queue
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from hilsim import control, msgs, transport
from hilsim.config import ConfigError, Scenario, load_scenario
from hilsim.service import Service

RIG = "step-rig"
LOOP_SERVICES = ["physics", "sensors", "controller"]


class RigError(RuntimeError):
    """A step experiment that could not be run or measured; the message says why, in one line."""


class LateStep(RigError):
    """A trajectory reached the controller after its stamp: that experiment's timing is not exact."""


@dataclass
class Experiment:
    """One step of one joint's reference, with the gains it is measured with."""

    joint: str
    step: float  # [rad] (or m), from the joint's home position
    gains: dict[str, float] = field(default_factory=dict)  # e.g. {"kp": 50.0, "kd": 2.0}; {}: the scenario's
    measure: float = 1.5  # sim seconds recorded after the step
    settle: float = 1.0  # sim seconds back home (scenario gains) before the next experiment


@dataclass
class Response:
    """What an experiment measured: the truth of its joint from the step on."""

    experiment: Experiment
    t: np.ndarray  # [s] from the step
    y: np.ndarray  # true position of the joint
    y0: float  # true position when the step was commanded
    target: float  # the commanded position


@dataclass
class _Action:
    k: int  # rig step at which it is done (the step of the reference is LEAD periods later)
    gains: dict[str, float]  # live parameters "<joint>.<field>"
    joint: str
    position: float
    fresh: bool = False  # empty the joint's integral before setting the gains (a trial's start)


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
        self.lead = self.LEAD * self.period
        self.dt_ns = round(sc.clock.dt * 1e9)
        self.experiments = list(experiments)
        self.progress = progress
        table = control.joint_table(sc.world.model)
        self.names = list(table.names)
        self.home = _home(sc, self.names)
        base = control.gains_for(sc.controller.gains, self.names, str(sc.source or ""))
        self.actions: dict[int, _Action] = {}
        self.windows: list[tuple[int, int]] = []  # (step index of the step, of the window's end)
        self._done_at: dict[int, int] = {}  # rig step -> experiments finished by then
        k = self.period
        for i, e in enumerate(self.experiments):
            if e.joint not in self.names:
                raise ConfigError(f"{e.joint}: not a joint of {sc.world.model.name} (joints: {', '.join(self.names)})")
            j = self.names.index(e.joint)
            lo, hi = table.lower[j], table.upper[j]
            target = self.home[j] + e.step
            if not lo <= target <= hi:
                raise ConfigError(f"step of {e.step:+g} on {e.joint}: {target:.3f} is outside its limits "
                                  f"[{lo:.3f}, {hi:.3f}]")
            own = {f"{e.joint}.{f}": float(v) for f, v in e.gains.items()}
            g = base[j]
            limit = g.output_limit if g.output_limit is not None else float(table.effort_upper[j])
            # back to the scenario's gains for the way home (a trial's may be unstable)
            restore = {f"{e.joint}.{f}": _live(getattr(g, f) if f != "output_limit" else limit) for f in e.gains}
            n_meas = self._steps(e.measure)
            n_settle = self._steps(e.settle)
            self.actions[k] = _Action(k, own, e.joint, float(target), fresh=True)
            s = k + self.lead
            self.windows.append((s, s + n_meas))
            kb = s + n_meas
            self.actions[kb] = _Action(kb, restore, e.joint, float(self.home[j]))
            self._done_at[kb] = i + 1
            k = kb + self.lead + n_settle
        self.end = k  # the last rig step; the scenario's duration ends the run there
        self.truth_t: list[int] = []
        self.truth_q: list[list[float]] = []
        self.ref_t: list[int] = []
        self.ref_q: list[list[float]] = []
        self.queue: queue.Queue[int] = queue.Queue()
        self.done = threading.Event()
        self.error = ""

    def _steps(self, seconds: float) -> int:
        """Whole rig periods covering ``seconds`` of sim time, in physics steps."""
        per = self.period * self.sc.clock.dt
        return self.period * max(1, math.ceil(seconds / per - 1e-9))

    # ------------------------------------------------------------------ wiring
    def setup(self) -> None:
        self.traj_pub = self.publisher(self.keys.topic("joint_trajectory"))
        self.subscribe(self.keys.truth("joint_states"), msgs.JointState, self._on_truth)
        self.subscribe(self.keys.topic("controller/reference"), msgs.JointState, self._on_reference)
        self.subscribe(self.keys.topic("joint_commands"), msgs.JointState, self._on_command)

    def _ordered(self, m: msgs.JointState) -> list[float]:
        if list(m.name) == self.names:
            return list(m.position)
        pos = dict(zip(m.name, m.position, strict=True))
        return [pos[n] for n in self.names]

    def _on_truth(self, m: msgs.JointState, key: str) -> None:
        self.truth_t.append(msgs.ns_of(m.header.stamp))
        self.truth_q.append(self._ordered(m))

    def _on_reference(self, m: msgs.JointState, key: str) -> None:
        self.ref_t.append(msgs.ns_of(m.header.stamp))
        self.ref_q.append(self._ordered(m))

    def _on_command(self, m: msgs.JointState, key: str) -> None:
        ns = msgs.ns_of(m.header.stamp)
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
            a = self.actions.get(k)
            if a is not None:
                try:
                    self._act(a)
                except RigError as e:
                    self.error = str(e)
                    self.done.set()
                    return
            self.ack(k * self.dt_ns)
            if k in self._done_at and self.progress is not None:
                self.progress(self._done_at[k], len(self.experiments))
            if k >= self.end:
                self.done.set()

    def _act(self, a: _Action) -> None:
        if a.gains:
            if a.fresh:
                # a trial starts like a fresh controller: ki = 0 empties the integral (hilsim.control.Pid)
                self._set_gains({f"{a.joint}.ki": 0.0})
            self._set_gains(a.gains)
        stamp = (a.k + self.lead) * self.dt_ns
        traj = msgs.JointTrajectory(
            header=msgs.header(stamp),
            joint_names=[a.joint],
            points=[msgs.JointTrajectoryPoint(positions=[a.position], velocities=[0.0],
                                              time_from_start=msgs.duration(0))],
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
        tt = np.asarray(self.truth_t, dtype=np.int64)
        tq = np.asarray(self.truth_q, float)
        rt = np.asarray(self.ref_t, dtype=np.int64)
        rq = np.asarray(self.ref_q, float)
        out = []
        for e, (s, end) in zip(self.experiments, self.windows, strict=True):
            j = self.names.index(e.joint)
            s_ns, end_ns = s * self.dt_ns, end * self.dt_ns
            sel = (tt >= s_ns) & (tt <= end_ns)
            order = np.argsort(tt[sel])
            t_ns = tt[sel][order]
            expected = (end - s) + 1
            if t_ns.size != expected or t_ns[0] != s_ns:
                raise RigError(f"{e.joint}: {t_ns.size} truth samples in the window of the step, expected "
                               f"{expected} (samples were lost)")
            target = self.home[j] + e.step
            # the controller's reference proves the step was taken at the stamped step, not later
            before = np.nonzero(rt == s_ns - self.dt_ns * self.sc.control_decimation)[0]
            at = np.nonzero(rt == s_ns)[0]
            if not at.size or not before.size or abs(rq[at[0], j] - target) > 1e-12 \
                    or abs(rq[before[0], j] - target) < 1e-12:
                raise LateStep(f"{e.joint}: the step did not start at t={s_ns / 1e9:.3f} s in the controller "
                               f"(the trajectory reached it late)")
            y = tq[sel][order][:, j]
            out.append(Response(e, (t_ns - s_ns) / 1e9, y, float(y[0]), float(target)))
        return out


def _live(v: float) -> float:
    """A gain as a live parameter: an unlimited i_limit is sent as a bound no integral reaches."""
    return float(v) if math.isfinite(v) else 1e12


def _home(sc: Scenario, names: list[str]) -> np.ndarray:
    """The joints' positions in the model's reference pose (qpos0): where the controller starts holding."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(sc.world.model))
    return np.array([m.qpos0[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]] for n in names])


def loop_scenario(robot: str, overrides: dict[str, Any] | None = None) -> Scenario:
    """The scenario's physics, sensors and controller in lockstep, nothing else (no planner, no
    recorder, no task): the loop whose step responses are measured."""
    o: dict[str, Any] = {"task.targets": [], "clock.mode": "lockstep"}
    o.update(overrides or {})
    sc = load_scenario(robot, o)
    if sc.controller.type != "joint_trajectory":
        raise ConfigError(f"{sc.source}: controller.type {sc.controller.type!r}: step experiments need the "
                          f"joint_trajectory controller (per-joint PID)")
    sc.services = [s for s in LOOP_SERVICES if s in sc.services]
    missing = [s for s in LOOP_SERVICES if s not in sc.services]
    if missing:
        raise ConfigError(f"{sc.source}: services: a step experiment needs {', '.join(missing)}")
    return sc


def run_experiments(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None = None,
                    progress: Callable[[int, int], None] | None = None, wall_timeout: float = 900.0) -> list[Response]:
    """Run the experiments in one lockstep run of the real services and return what they measured
    (once more if a step reached the controller late: on a starved machine a link can lag)."""
    try:
        return _run_once(sc.model_copy(deep=True), experiments, run_dir, progress, wall_timeout)
    except LateStep as e:
        logging.getLogger("hilsim.step-rig").warning("%s; running the experiments again", e)
        return _run_once(sc.model_copy(deep=True), experiments, run_dir, progress, wall_timeout)


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def _run_once(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None,
              progress: Callable[[int, int], None] | None, wall_timeout: float) -> list[Response]:
    # Ctrl-C and SIGTERM stop the run (and its services) wherever it is; set explicitly, as hilsim up
    # does, since a process started in the background inherits SIGINT ignored
    old = {}
    if threading.current_thread() is threading.main_thread():
        old = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run_services(sc, experiments, run_dir, progress, wall_timeout)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _run_services(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None,
                  progress: Callable[[int, int], None] | None, wall_timeout: float) -> list[Response]:
    from hilsim.launcher import Launcher

    if not experiments:
        return []
    tmp = None
    if run_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="hilsim-rig-")
        run_dir = Path(tmp.name)
    # a router of our own on a free port: never the default one another simulation may be using
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    sc.zenoh.connect = [ep]
    rig = StepRig(sc, experiments, progress)
    sc.duration = rig.end * sc.clock.dt
    session = transport.open_session(sc.zenoh)
    # the rig's lockstep token exists before any service starts, so physics counts it in at step 0
    worker = threading.Thread(target=rig.serve, args=(session,), daemon=True, name="step-rig")
    worker.start()
    la = Launcher(sc, run_dir, router=ep, quiet=True)
    try:
        deadline = time.monotonic() + 10.0
        while rig.state == "starting" and time.monotonic() < deadline:
            time.sleep(0.01)
        if rig.state != "running":
            raise RigError(f"the step rig did not start: {rig.last_error or rig.state}")
        la.start()
        if not la.wait_ready():
            raise RigError(f"the services did not start; see their logs in {run_dir}")
        t0 = time.monotonic()
        while not rig.done.wait(0.2):
            if la.check_children():
                raise RigError(f"a service died: {la.outcome.died}; see {run_dir}")
            if la.outcome.stalled:
                raise RigError(f"the run stalled: {la.outcome.stalled}; see {run_dir}")
            if time.monotonic() - t0 > wall_timeout:
                raise RigError(f"the experiments did not finish within {wall_timeout:.0f} s wall; see {run_dir}")
        if rig.error:
            raise RigError(rig.error)
    finally:
        la.stop()
        rig.request_stop()
        worker.join(timeout=10.0)
        session.close()
        router.close()
        if tmp is not None:
            tmp.cleanup()
    with rig.lock:
        return rig.responses()
