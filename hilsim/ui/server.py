"""``hilsim ui``: the browser control panel (Starlette + uvicorn, plain HTML, server-sent events).

The panel is a Zenoh client like ``hilsim topic``: it watches a simulation through the keys every
tool uses, sends goals and gains through the services' own queryables, and starts one run at a
time as a child ``hilsim up`` process (its own process group; SIGTERM from the kernel if the panel
dies; stopped with SIGTERM, then waited for). Unless ``--connect`` names a router, the panel opens
the Zenoh router itself (``tcp/127.0.0.1:7447`` when free, as ``hilsim up`` would) and starts its
runs with ``--router`` on it, so it sees every run it starts and ``hilsim topic`` finds it too.

Reads (``<prefix>/<robot>/…``, any robot): ``alive/*`` (liveliness), ``health/*``, ``log/*``
(faults: level ERROR and above), ``<prefix>/clock``, ``truth/joint_states`` (positions; the latest
about 20 times a second, for the plot), ``controller/reference`` (setpoints), ``truth/odom`` (a rover's pose),
``planner/feedback``, ``planner/result``, ``navigator/feedback``, ``navigator/result``.
Samples are believed as every service believes them (:mod:`hilsim.core.provenance`: on a key with an
announced writer, only that writer's), and whatever is shown is text, never markup.
Queries: ``planner/goal``, ``planner/cancel``, ``navigator/goal``, ``navigator/cancel`` (through
:class:`hilsim.planning.client.MoveClient`), ``controller/set_parameters`` (:mod:`hilsim.tools.params`);
the gains in force are read back from the controller's health (``gains:<joint>``).

HTTP (JSON; bad input is a 4xx with ``{"error", "field"}``, never a server error):
``GET /api/options``, ``GET /api/state``, ``GET /api/events`` (server-sent events: the state, 4 Hz),
``POST /api/run``, ``POST /api/stop``, ``POST /api/goal``, ``POST /api/cancel``, ``POST /api/gains``,
``POST /api/viewer`` (Rerun's bundled web viewer on the recording, served on loopback),
``GET /recording.rrd`` (the current run's recording).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
import zenoh
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from hilsim.core import msgs, transport
from hilsim.core.config import CONFIG_DIR, ConfigError, Scenario
from hilsim.core.geometry import yaw_of
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.scenario import load_scenario, parse_overrides
from hilsim.sim.control import GAIN_FIELDS

log = logging.getLogger("hilsim.ui")

STATIC = Path(__file__).resolve().parent / "static"
PLOT_PERIOD = 0.05  # wall seconds between plot samples (the truth comes at 500-1000 Hz)
PLOT_POINTS = 240  # samples kept for the plot: 12 s at 20 Hz
RING = 64  # samples of a high-rate key Zenoh keeps between two reads (the latest of each robot among them)
EVENT_PERIOD = 0.25  # wall seconds between two server-sent states
STOP_GRACE = 60.0  # wall seconds a run has to stop after SIGTERM (the recorder drains) before SIGKILL
GAINS_SHOWN = ("kp", "ki", "kd", "i_limit")


class BadInput(ValueError):
    """A request the panel refuses: the message is shown beside ``field`` in the page."""

    def __init__(self, fld: str, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.field = fld
        self.status = status


# ---------------------------------------------------------------- what can be run
@dataclass
class ScenarioOption:
    name: str
    robot: str
    prefix: str
    mobile: bool  # a navigator takes map goals (the rover), else a planner joint/pose goals (the arm)
    worlds: list[str]
    services: list[str]
    clock: str
    targets: int
    planner: str  # the scenario's default planner ("" without a planner service)
    joints: list[str] = field(default_factory=list)
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        # JSON has no infinity: an unlimited joint gets ±π on its slider (it is a revolute joint)
        d["lower"] = [v if math.isfinite(v) else -math.pi for v in self.lower]
        d["upper"] = [v if math.isfinite(v) else math.pi for v in self.upper]
        return d


def _is_scenario_file(p: Path) -> bool:
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and ("services" in data or "extends" in data) and "planners" not in data


def scenario_options(config_dir: Path = CONFIG_DIR) -> dict[str, ScenarioOption]:
    """The scenarios of ``config/`` (not the overlays), with their worlds, joints and limits."""
    out: dict[str, ScenarioOption] = {}
    files = sorted(p for p in config_dir.glob("*.yaml") if _is_scenario_file(p))
    for p in files:
        try:
            sc = load_scenario(p)
        except ConfigError as e:
            log.warning("scenario %s not offered: %s", p, e)
            continue
        own = sc.world.model.stem
        variants = [q.stem[len(p.stem) + 1:] for q in files if q.stem.startswith(p.stem + "-")]
        worlds = [own, *[w for w in variants if _world_stem(config_dir / f"{p.stem}-{w}.yaml") == w]]
        opt = option_of(sc, p.stem, worlds)
        out[p.stem] = opt
    return out


def option_of(sc: Scenario, name: str, worlds: list[str] | None = None) -> ScenarioOption:
    """What the panel needs of a scenario: its robot, services, joints and their limits."""
    from hilsim.sim.control import joint_table

    opt = ScenarioOption(
        name=name, robot=sc.robot, prefix=sc.prefix, mobile="navigator" in sc.services,
        worlds=worlds or [sc.world.model.stem], services=sc.processes(), clock=sc.clock.mode,
        targets=len(sc.task.targets), planner=sc.planner.planner if "planner" in sc.services else "",
    )
    if not opt.mobile:
        jt = joint_table(sc.world.model)
        opt.joints, opt.lower, opt.upper = list(jt.names), jt.lower.tolist(), jt.upper.tolist()
    return opt


def _world_stem(path: Path) -> str | None:
    try:
        return load_scenario(path).world.model.stem
    except ConfigError:
        return None


def planner_names(config_dir: Path = CONFIG_DIR) -> list[str]:
    """The planner library's names (read as YAML: the panel does not load OMPL)."""
    try:
        data = yaml.safe_load((config_dir / "planners.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return []
    return sorted((data.get("planners") or {}).keys())


# ---------------------------------------------------------------- the Zenoh side
def _robot_of(key: str, prefix: str) -> str:
    rest = key[len(prefix) + 1:] if key.startswith(prefix + "/") else key
    return rest.split("/", 1)[0]


def shown_robot(sc: Scenario) -> tuple[str, list[str]]:
    """The robot a run's page shows and the services it lists. With ``robots: N`` (hilsim.core.fleet)
    that is the first robot, ``arm0``: its own services by their names (``controller@arm0`` is
    ``controller`` under ``<prefix>/arm0/``) beside the ones every robot shares (physics, logger)."""
    from hilsim.core import fleet

    robots = fleet.robot_names(sc)
    if len(robots) <= 1:
        return sc.robot, sc.processes()
    first = robots[0]
    names = []
    for p in sc.processes():
        svc, _, r = p.partition("@")
        if not r or r in (first, "*"):
            names.append(svc)
    return first, list(dict.fromkeys(names))


@dataclass
class RobotView:
    """What the panel knows of one robot of the simulation."""

    alive: dict[str, bool] = field(default_factory=dict)
    health: dict[str, dict[str, Any]] = field(default_factory=dict)
    joints: list[str] = field(default_factory=list)
    position: list[float] = field(default_factory=list)
    ref_names: list[str] = field(default_factory=list)
    setpoint: list[float] = field(default_factory=list)
    history: deque[tuple[float, list[float], list[float]]] = field(default_factory=lambda: deque(maxlen=PLOT_POINTS))
    pose: tuple[float, float, float] | None = None  # a rover's truth: x, y, yaw
    goals: dict[str, dict[str, Any]] = field(default_factory=dict)


class Monitor:
    """Subscribes to the simulation's keys and keeps the latest of each (Zenoh callbacks; the
    high-rate keys through rings read by one thread)."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.session = session
        self.prefix = prefix
        k = Keys(prefix, "*")
        self.lock = threading.Lock()
        self.robots: dict[str, RobotView] = {}
        self.sim_time: float | None = None
        self.clock_wall = 0.0
        self.faults: deque[dict[str, Any]] = deque(maxlen=50)
        self.expected: set[str] = set()  # the services of the panel's run while it runs (a departure is a fault)
        self.watch_departures = False
        self.prov = Provenance()
        self._prov_lock = threading.Lock()
        self.ignored = 0  # samples from writers other than the keys' announced ones, or undecodable
        self._subs: list[Any] = [
            # first: who writes what, so that only the services' own samples are believed
            session.liveliness().declare_subscriber(k.all_writers, self._on_writer, history=True),
            session.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True),
            session.declare_subscriber(k.health("*"), self._on_health),
            session.declare_subscriber(k.log("*"), self._on_log),
        ]
        # The keys written every step (up to 1 kHz) go into bounded rings inside Zenoh, read 20 times
        # a second by one thread: no Python call per sample (the panel would cost a busy loop a core's
        # tenth otherwise), and the plot gets the latest of each. The setpoint before the truth, so
        # each plot sample pairs a position with the setpoint in force.
        self._rings: list[tuple[Any, Any]] = [
            (session.declare_subscriber(key, zenoh.handlers.RingChannel(RING)), handle)
            for key, handle in ((k.clock, self._on_clock), (k.topic("controller/reference"), self._on_reference),
                                (k.truth("odom"), self._on_odom), (k.truth("joint_states"), self._on_truth))
        ]
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll, name="panel-poll", daemon=True)
        self._poller.start()
        for svc in ("planner", "navigator"):
            self._subs += [
                session.declare_subscriber(k.topic(f"{svc}/feedback"), self._feedback_cb(svc)),
                session.declare_subscriber(k.topic(f"{svc}/result"), self._result_cb(svc)),
            ]

    def robot(self, name: str) -> RobotView:
        """Under self.lock."""
        return self.robots.setdefault(name, RobotView())

    def fault(self, source: str, text: str) -> None:
        with self.lock:
            self.faults.append({"wall": time.time(), "source": source, "text": text})

    def _on_writer(self, sample: zenoh.Sample) -> None:
        with self._prov_lock:
            self.prov.on_token(sample)

    def _decode(self, sample: zenoh.Sample, cls: type) -> Any:
        """The message, if it comes from the key's announced writer (as every service judges it:
        :mod:`hilsim.core.provenance`) and decodes; else None, counted in ``ignored``."""
        with self._prov_lock:
            why, _ = self.prov.check(str(sample.key_expr), transport.read_attachment(sample))
            if why is not None:
                self.ignored += 1
                return None
        try:
            return msgs.decode(cls, sample.payload.to_bytes())
        except msgs.BadMessage:
            with self._prov_lock:
                self.ignored += 1
            return None  # a stranger's garbage on a key must not reach the page

    def _on_alive(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        svc = key.rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            rv = self.robot(_robot_of(key, self.prefix))
            was = rv.alive.get(svc, False)
            rv.alive[svc] = up
            departed = was and not up and self.watch_departures and svc in self.expected
        if departed:  # a service of the running run left: it died (a stop clears watch_departures first)
            self.fault(svc, f"service {svc} is gone (its liveliness token disappeared)")

    def _on_health(self, sample: zenoh.Sample) -> None:
        h = self._decode(sample, msgs.DiagnosticArray)
        if h is None:
            return
        robot = _robot_of(str(sample.key_expr), self.prefix)
        new_faults = []
        with self.lock:
            rv = self.robot(robot)
            for st in h.status:
                vals = {kv.key: kv.value for kv in st.values}
                old = rv.health.get(st.name, {})
                if st.level >= 2 and old.get("level", 0) < 2:
                    new_faults.append((st.name, st.message or vals.get("last_error", "error")))
                rv.health[st.name] = {"level": int(st.level), "message": st.message, "values": vals,
                                      "wall": time.time()}
        for name, text in new_faults:
            self.fault(name, f"health: {text}")

    def _on_log(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.Log)
        if m is not None and m.level >= 40:
            self.fault(m.name, m.msg)

    def _poll(self) -> None:
        while not self._stop.wait(PLOT_PERIOD):
            for sub, handle in self._rings:
                latest: dict[str, zenoh.Sample] = {}  # per key: one robot's latest each
                try:
                    while (sample := sub.try_recv()) is not None:
                        latest[str(sample.key_expr)] = sample
                except zenoh.ZError:  # undeclared while closing
                    return
                for sample in latest.values():
                    handle(sample)

    def _on_clock(self, sample: zenoh.Sample) -> None:
        c = self._decode(sample, msgs.Clock)
        if c is not None:
            with self.lock:
                self.sim_time = msgs.seconds(c.clock)
                self.clock_wall = time.monotonic()

    def _on_truth(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is None:
            return
        with self.lock:
            rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
            rv.joints, rv.position = list(m.name), list(m.position)
            ref = dict(zip(rv.ref_names, rv.setpoint, strict=False))
            sp = [ref.get(n, math.nan) for n in rv.joints]
            rv.history.append((msgs.seconds(m.header.stamp), rv.position, sp))

    def _on_reference(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is not None:
            with self.lock:
                rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
                rv.ref_names, rv.setpoint = list(m.name), list(m.position)

    def _on_odom(self, sample: zenoh.Sample) -> None:
        o = self._decode(sample, msgs.Odometry)
        if o is not None:
            p, yaw = o.pose.pose.position, yaw_of(o.pose.pose.orientation)
            with self.lock:
                rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
                rv.pose = (p.x, p.y, yaw)

    def _goal(self, rv: RobotView, gid: str, service: str) -> dict[str, Any]:
        g = rv.goals.get(gid)
        if g is None:
            g = rv.goals[gid] = {"id": gid, "service": service, "state": "sent", "progress": 0.0,
                                 "done": False, "success": None, "message": "", "error": [], "wall": time.time()}
            while len(rv.goals) > 12:  # the oldest go first (dicts keep insertion order)
                rv.goals.pop(next(iter(rv.goals)))
        return g

    def _feedback_cb(self, service: str) -> Any:
        def on(sample: zenoh.Sample) -> None:
            fb = self._decode(sample, msgs.MoveFeedback)
            if fb is None:
                return
            with self.lock:
                g = self._goal(self.robot(_robot_of(str(sample.key_expr), self.prefix)), fb.goal_id, service)
                if not g["done"]:
                    g.update(state=fb.state, progress=fb.progress, sim=msgs.seconds(fb.header.stamp))
        return on

    def _result_cb(self, service: str) -> Any:
        def on(sample: zenoh.Sample) -> None:
            r = self._decode(sample, msgs.MoveResult)
            if r is None:
                return
            with self.lock:
                g = self._goal(self.robot(_robot_of(str(sample.key_expr), self.prefix)), r.goal_id, service)
                state = "reached" if r.success else "canceled" if "cancel" in r.message.lower() else "failed"
                g.update(state=state, done=True, success=r.success, message=r.message,
                         error=list(r.execution_error), progress=1.0 if r.success else g["progress"],
                         sim=msgs.seconds(r.header.stamp))
        return on

    def note_goal(self, robot: str, gid: str, service: str) -> None:
        with self.lock:
            self._goal(self.robot(robot), gid, service)

    def gains(self, robot: str) -> dict[str, dict[str, float]]:
        """The gains in force, from the controller's health (``gains:<joint>`` = ``kp=… ki=…``)."""
        with self.lock:
            vals = self.robot(robot).health.get("controller", {}).get("values", {})
        out: dict[str, dict[str, float]] = {}
        for k, v in vals.items():
            if k.startswith("gains:"):
                g = {}
                for item in v.split():
                    name, _, num = item.partition("=")
                    with contextlib.suppress(ValueError):
                        g[name] = float(num)
                out[k[6:]] = g
        return out

    def snapshot(self, robot: str) -> dict[str, Any]:
        with self.lock:
            rv = self.robot(robot)
            now = time.time()
            services = []
            for name in sorted(set(rv.alive) | set(rv.health)):
                h = rv.health.get(name, {})
                vals = h.get("values", {})
                services.append({
                    "name": name, "alive": rv.alive.get(name, False), "level": h.get("level"),
                    "state": vals.get("state", ""), "message": h.get("message", ""),
                    "age": round(now - h["wall"], 1) if h else None,
                    "errors": vals.get("errors", ""), "last_error": vals.get("last_error", ""),
                })
            ph = rv.health.get("physics", {}).get("values", {})
            hist = list(rv.history)
            snap = {
                "robot": robot,
                "sim_time": self.sim_time,
                "clock_age": round(time.monotonic() - self.clock_wall, 1) if self.clock_wall else None,
                "rtf": ph.get("real_time_factor"),
                "paused_for": ph.get("paused_for", ""),
                # realtime: steps physics finished after their deadline (a loaded machine)
                "overruns": ph.get("overruns"),
                "services": services,
                "joints": {"names": rv.joints, "position": rv.position,
                           "setpoint": [dict(zip(rv.ref_names, rv.setpoint, strict=False)).get(n) for n in rv.joints]},
                "history": {"t": [h[0] for h in hist], "pos": [h[1] for h in hist], "ref": [h[2] for h in hist]},
                "pose": rv.pose,
                "goals": list(reversed(rv.goals.values())),
                "faults": list(reversed(self.faults))[:20],
                "ignored": self.ignored,
            }
        snap["gains"] = self.gains(robot)
        return _finite(snap)

    def close(self) -> None:
        self._stop.set()
        self._poller.join(2)
        for s in [*self._subs, *(sub for sub, _ in self._rings)]:
            with contextlib.suppress(Exception):
                s.undeclare()


def _finite(x: Any) -> Any:
    """JSON without NaN/inf (the browser's JSON.parse refuses them): null instead."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x


# ---------------------------------------------------------------- one run at a time
def _child_setup() -> None:
    """In the ``hilsim up`` child: its own process group (the panel's Ctrl-C is not its), and
    SIGTERM from the kernel when the panel's thread that started it dies."""
    os.setpgrp()
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@dataclass
class RunRequest:
    scenario: str
    world: str = ""
    planner: str = ""
    clock: str = "realtime"
    mode: str = "interactive"  # interactive: no task, runs until stopped; task: the scenario's targets
    extra: list[str] = field(default_factory=list)  # further `hilsim up` arguments (hilsim up --ui)
    out: str = ""  # the run directory (default runs/<stamp>-ui)


class RunManager:
    """The panel's run: a ``hilsim up`` child process, one at a time."""

    def __init__(self, router: str, runs_dir: Path) -> None:
        self.router = router
        self.runs_dir = runs_dir
        self.lock = threading.Lock()
        self.proc: subprocess.Popen[str] | None = None
        self.state = "idle"  # idle | running | stopping | finished
        self.info: dict[str, Any] = {}
        self.output: deque[str] = deque(maxlen=200)
        self.ready = False
        self.rc: int | None = None
        self.on_end: Any = None  # called (no argument) when the run process has ended
        self.on_line: Any = None  # called with each line the run prints

    def busy(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self, req: RunRequest, sc: Scenario, scenario_arg: str) -> dict[str, Any]:
        """Start ``hilsim up`` (call from a long-lived thread: the kernel's PDEATHSIG follows the
        thread that forked, so a worker thread that ends would stop the run)."""
        with self.lock:
            if self.busy():
                raise BadInput("run", f"a run is already {self.state} ({self.info.get('scenario')}, pid "
                               f"{self.proc.pid if self.proc else '?'}): stop it first", 409)
            stamp = time.strftime("%Y%m%d-%H%M%S") + f"-{int(time.time() * 1000) % 1000:03d}-ui"
            run_dir = (Path(req.out) if req.out else self.runs_dir / stamp).resolve()
            argv = [sys.executable, "-m", "hilsim.cli", "up", scenario_arg, "--clock", req.clock,
                    "--router", self.router, "--out", str(run_dir)]
            if req.mode == "interactive":
                argv += ["--set", "task.targets=[]"]
            if req.planner:
                argv += ["--set", f"planner.planner={req.planner}"]
            argv += req.extra
            env = {**os.environ, "PYTHONUNBUFFERED": "1"}
            self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                         stdin=subprocess.DEVNULL, env=env, preexec_fn=_child_setup)
            self.state, self.ready, self.rc = "running", False, None
            self.output.clear()
            robot, services = shown_robot(sc)
            self.info = {"scenario": req.scenario, "world": req.world or sc.world.model.stem, "robot": robot,
                         "base_robot": sc.robot, "prefix": sc.prefix, "clock": req.clock, "mode": req.mode,
                         "planner": req.planner or (sc.planner.planner if "planner" in sc.services else ""),
                         "services": services, "pid": self.proc.pid, "run_dir": str(run_dir),
                         "recording": str(run_dir / "recording.rrd") if "logger" in sc.services else "",
                         "command": " ".join(argv[2:]).replace("hilsim.cli", "hilsim", 1).removeprefix("-m "),
                         "started": time.time()}
            threading.Thread(target=self._pump, args=(self.proc,), daemon=True).start()
            return dict(self.info)

    def _pump(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip("\n")
            with self.lock:
                self.output.append(line)
                if line.startswith("ready:"):
                    self.ready = True
            if self.on_line is not None:
                self.on_line(line)
        rc = proc.wait()
        with self.lock:
            if proc is self.proc:
                self.state, self.rc = "finished", rc
        if self.on_end is not None:
            self.on_end()

    def stop(self, wait: bool = False, timeout: float = STOP_GRACE) -> bool:
        """SIGTERM to the run (it stops its services and closes the recording); SIGKILL after
        ``timeout`` (its services then get SIGTERM from the kernel). False if nothing ran."""
        with self.lock:
            proc = self.proc
            if proc is None or proc.poll() is not None:
                return False
            self.state = "stopping"
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)

        def reap() -> None:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("run pid %d did not stop within %.0f s: killing it", proc.pid, timeout)
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()

        if wait:
            reap()
        else:
            threading.Thread(target=reap, daemon=True).start()
        return True

    def status(self) -> dict[str, Any]:
        with self.lock:
            return {"state": self.state, "ready": self.ready, "rc": self.rc, **self.info,
                    "output": list(self.output)[-40:]}


# ---------------------------------------------------------------- the panel
def _num(body: dict[str, Any], name: str, fld: str | None = None, *, required: bool = True) -> float | None:
    """A finite number from a JSON body (a number or a numeric string), else BadInput on ``fld``."""
    v = body.get(name)
    if v is None or (isinstance(v, str) and not v.strip()):
        if required:
            raise BadInput(fld or name, f"{name}: a number is required")
        return None
    if isinstance(v, bool):
        raise BadInput(fld or name, f"{name}: expected a number, got {v!r}")
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise BadInput(fld or name, f"{name}: expected a number, got {str(v)[:40]!r}") from None
    if not math.isfinite(x):
        raise BadInput(fld or name, f"{name}: expected a finite number, got {v!r}")
    return x


class Panel:
    def __init__(self, *, connect: str | None = None, prefix: str | None = None, runs_dir: Path = Path("runs"),
                 robot: str = "arm") -> None:
        self.prefix = transport.tool_prefix(prefix)
        self.router: zenoh.Session | None = None
        if connect:
            self.endpoint = connect
        else:
            from hilsim.run.launcher import open_default_router

            self.endpoint, self.router = open_default_router()
        self.session = transport.open_tool_session(self.endpoint)
        self.monitor = Monitor(self.session, self.prefix)
        self.options = scenario_options()
        self.planners = planner_names()
        self.run = RunManager(self.endpoint, runs_dir)
        self.run.on_end = self._run_ended
        self.run.on_line = self._run_said
        self.default_robot = robot
        self.clients: dict[tuple[str, str], Any] = {}
        self.current: ScenarioOption | None = None  # the scenario of the panel's run
        self.viewer: subprocess.Popen[bytes] | None = None
        self.viewer_url = ""
        self.goal_seq = 0
        self.closing = threading.Event()

    # -- state
    def robot(self) -> str:
        """The robot shown: the panel's run's; else one whose services are alive (a run started
        elsewhere, e.g. ``hilsim up`` in a terminal with ``hilsim ui --connect``)."""
        if self.run.busy():
            return str(self.run.info.get("robot") or self.default_robot)
        with self.monitor.lock:
            live = sorted(r for r, rv in self.monitor.robots.items() if any(rv.alive.values()))
        return live[0] if live else str(self.run.info.get("robot") or self.default_robot)

    def option(self) -> ScenarioOption | None:
        """What goals and gains are checked against: the panel's run's scenario while it runs; for a
        run started elsewhere whose planner (or navigator) is alive, a scenario of ``config/`` for
        the same robot (its joints and their limits)."""
        if self.run.busy():
            return self.current
        robot = self.robot()
        with self.monitor.lock:
            rv = self.monitor.robots.get(robot)
            alive = {s for s, up in rv.alive.items() if up} if rv is not None else set()
        if not alive & {"planner", "navigator"}:
            return None
        same = [o for o in self.options.values() if o.robot == robot and ("navigator" in alive) == o.mobile]
        return next((o for o in same if o.name == robot), same[0] if same else None)

    def state(self) -> dict[str, Any]:
        robot = self.robot()
        snap = self.monitor.snapshot(robot)
        base = self.run.info.get("base_robot") if self.run.busy() else None
        if base and base != robot:  # robots: N: physics and the recorder serve them all, under the base name
            shared = self.monitor.snapshot(base)
            have = {s["name"] for s in snap["services"]}
            snap["services"] = sorted([*snap["services"], *(s for s in shared["services"] if s["name"] not in have)],
                                      key=lambda s: s["name"])
            for k in ("rtf", "overruns", "paused_for"):  # physics' health figures
                snap[k] = snap.get(k) or shared.get(k)
        snap["run"] = self.run.status()
        snap["endpoint"] = self.endpoint
        opt = self.option()
        snap["scenario"] = opt.as_json() if opt is not None else None
        snap["external"] = opt is not None and not self.run.busy()  # commanding a run started elsewhere
        snap["viewer"] = self.viewer_url if self.viewer is not None and self.viewer.poll() is None else ""
        return snap

    def _run_said(self, line: str) -> None:
        """The launcher's own verdicts: a dead service, a stall (``error: …``) is a fault; once the
        run is ending, services leave because they are stopped, not because they died."""
        if line.startswith("error:"):
            self.monitor.fault("hilsim up", line.removeprefix("error:").strip())
        if line.startswith(("error:", "interrupted", "summary:")):
            self.monitor.watch_departures = False

    def _run_ended(self) -> None:
        self.monitor.watch_departures = False
        rc = self.run.rc
        if rc not in (0, None) and self.run.state == "finished":
            tail = [ln for ln in self.run.output if "error" in ln.lower() or "fault" in ln.lower()]
            self.monitor.fault("hilsim up", f"the run ended with exit code {rc}" + (f": {tail[-1]}" if tail else ""))

    # -- actions
    def start(self, body: dict[str, Any]) -> dict[str, Any]:
        name = body.get("scenario")
        if not isinstance(name, str) or name not in self.options:
            raise BadInput("scenario", f"unknown scenario {str(name)[:40]!r}; one of: {', '.join(self.options)}")
        opt = self.options[name]
        world = body.get("world") or ""
        if not isinstance(world, str) or (world and world not in opt.worlds):
            raise BadInput("world", f"scenario {name} has no world {str(world)[:40]!r}; "
                           f"one of: {', '.join(opt.worlds)}")
        planner = body.get("planner") or ""
        if not isinstance(planner, str) or (planner and planner not in self.planners):
            raise BadInput("planner", f"unknown planner {str(planner)[:40]!r}; one of: {', '.join(self.planners)}")
        if planner and not opt.planner:
            raise BadInput("planner", f"scenario {name} has no joint planner (its navigator plans)")
        clock = body.get("clock") or "realtime"
        if clock not in ("realtime", "lockstep"):
            raise BadInput("clock", f"clock: expected realtime or lockstep, got {str(clock)[:40]!r}")
        mode = body.get("mode") or "interactive"
        if mode not in ("interactive", "task"):
            raise BadInput("mode", f"mode: expected interactive or task, got {str(mode)[:40]!r}")
        return self.start_request(RunRequest(name, world, planner, clock, mode))

    def start_request(self, req: RunRequest) -> dict[str, Any]:
        from hilsim.run.launcher import world_scenario

        if self.run.busy():
            raise BadInput("run", f"a run is already {self.run.state} ({self.run.info.get('scenario')}): "
                           "stop it first", 409)
        with self.monitor.lock:  # two simulations on the same keys would mix: one at a time here too
            elsewhere = {r: sorted(s for s, up in rv.alive.items() if up) for r, rv in self.monitor.robots.items()}
        elsewhere = {r: s for r, s in elsewhere.items() if s}
        if elsewhere:
            who = "; ".join(f"robot {r}: {', '.join(s)}" for r, s in sorted(elsewhere.items()))
            raise BadInput("run", f"a simulation started elsewhere runs on this Zenoh network with prefix "
                           f"{self.prefix} ({who}): stop it first", 409)
        try:
            arg = world_scenario(req.scenario, req.world) if req.world else req.scenario
            overrides: dict[str, Any] = {"clock.mode": req.clock}
            if req.mode == "interactive":
                overrides["task.targets"] = []
            if req.planner:
                overrides["planner.planner"] = req.planner
            sc = load_scenario(arg, {**overrides, **parse_overrides(_sets(req.extra))})
        except ConfigError as e:
            raise BadInput("scenario", str(e)) from None
        info = self.run.start(req, sc, arg)
        with self.monitor.lock:  # a new run: the last one's faults, goals and plot are history
            self.monitor.faults.clear()
            self.monitor.robots.pop(sc.robot, None)
        self.current = option_of(sc, req.scenario)
        self.monitor.expected = {s.split("@")[0] for s in sc.processes()}  # alive/<service>, per robot
        self.monitor.watch_departures = False  # until they have all come
        threading.Thread(target=self._arm_departures, args=(info["pid"],), daemon=True).start()
        return info

    def _arm_departures(self, pid: int) -> None:
        """Once the run said ``ready``, a service leaving while it runs is a fault."""
        while not self.closing.is_set() and self.run.info.get("pid") == pid and self.run.state == "running":
            if self.run.ready:
                self.monitor.watch_departures = True
                return
            time.sleep(0.2)

    def stop(self) -> dict[str, Any]:
        self.monitor.watch_departures = False
        if not self.run.stop():
            raise BadInput("run", "no run is running", 409)
        return {"state": "stopping"}

    def _client(self, service: str) -> Any:
        from hilsim.planning.client import MoveClient

        key = (self.robot(), service)
        if key not in self.clients:
            self.clients[key] = MoveClient(self.session, Keys(self.prefix, self.robot()), query_timeout=15.0,
                                           service=service)
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
                v = _num({name: pos[i]}, name, f"joint-{name}")
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
            x, y, z = (_num(body, n, f"pose-{n}") for n in ("x", "y", "z"))
            rpy = [_num(body, n, f"pose-{n}", required=False) for n in ("roll", "pitch", "yaw")]
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
            x, y = _num(body, "x", "xy-x"), _num(body, "y", "xy-y")
            yaw = _num(body, "yaw", "xy-yaw", required=False)
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
        from hilsim.tools.params import set_parameters

        opt = self._live_option("gains")
        joint = body.get("joint")
        if not isinstance(joint, str) or joint not in opt.joints:
            raise BadInput("gains", f"joint: expected one of {', '.join(opt.joints) or 'the joints'}, got "
                           f"{str(joint)[:40]!r}")
        values: dict[str, float] = {}
        for f in GAIN_FIELDS:
            v = _num(body, f, f"gain-{joint}-{f}", required=False)
            if v is not None:
                if v < 0 and f != "feedforward":
                    raise BadInput(f"gain-{joint}-{f}", f"{f}: must not be negative, got {v:g}")
                values[f"{joint}.{f}"] = v
        unknown = [k for k in body if k not in (*GAIN_FIELDS, "joint")]
        if unknown:
            raise BadInput("gains", f"unknown field(s) {', '.join(map(str, unknown))[:80]}; gains are "
                           f"{', '.join(GAIN_FIELDS)}")
        if not values:
            raise BadInput("gains", "no gain given")
        res = set_parameters(self.session, Keys(self.prefix, self.robot()), values, timeout=10.0)
        if not res.successful:
            raise BadInput("gains", f"not set: {res.reason}", 422)
        return {"set": values, "reason": res.reason}

    def open_viewer(self) -> dict[str, Any]:
        """Rerun's own web viewer (bundled with rerun-sdk) on the recording, served on loopback:
        ``rerun --serve-web``; analytics off as everywhere in hilsim."""
        from hilsim.core.recording import rerun_config_home, rerun_env, rerun_executable

        rec = str(self.run.info.get("recording") or "")
        if not rec or not Path(rec).is_file():
            raise BadInput("viewer", "no recording yet: start a run (with the logger) first", 409)
        self._stop_viewer()
        web, grpc = transport.free_port(), transport.free_port()
        env = {**os.environ, **rerun_env(), "XDG_CONFIG_HOME": str(rerun_config_home())}
        self.viewer = subprocess.Popen(
            [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
             "--port", str(grpc), rec], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL, env=env, preexec_fn=_child_setup)
        self.viewer_url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
        return {"url": self.viewer_url}

    def _stop_viewer(self) -> None:
        """The viewer's whole process group: ``rerun`` may be a wrapper that starts the real binary."""
        v = self.viewer
        if v is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(v.pid, signal.SIGTERM)
        try:
            v.wait(5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(v.pid, signal.SIGKILL)
            v.wait()
        self.viewer = None

    def close(self) -> None:
        self.closing.set()
        self.run.stop(wait=True)
        self._stop_viewer()
        for c in self.clients.values():
            with contextlib.suppress(Exception):
                c.close()
        self.monitor.close()
        self.session.close()
        if self.router is not None:
            self.router.close()


def _sets(extra: list[str]) -> list[str]:
    """The ``--set`` values among extra ``hilsim up`` arguments (validated before the run starts)."""
    return [extra[i + 1] for i, a in enumerate(extra[:-1]) if a == "--set"]


# ---------------------------------------------------------------- HTTP
async def _body(request: Request) -> dict[str, Any]:
    try:
        data = json.loads(await request.body() or b"{}")
    except ValueError:  # not JSON, not UTF-8, or a number too long to convert
        raise BadInput("request", "the request body is not JSON") from None
    if not isinstance(data, dict):
        raise BadInput("request", "the request body must be a JSON object")
    return data


def make_app(panel: Panel) -> Starlette:
    def bad(e: BadInput) -> JSONResponse:
        return JSONResponse({"error": str(e), "field": e.field}, status_code=e.status)

    def action(fn: Any, *, blocking: bool) -> Any:
        async def endpoint(request: Request) -> Response:
            try:
                body = await _body(request)
                if body.get("extra"):
                    raise BadInput("request", "extra: not accepted over HTTP")
                # queries wait for a service's answer: in a worker thread; a run is started from the
                # event loop's own (long-lived) thread, whose death alone should stop the run
                out = await run_in_threadpool(fn, body) if blocking else fn(body)
            except BadInput as e:
                return bad(e)
            return JSONResponse(_finite(out))
        return endpoint

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def options(request: Request) -> Response:
        return JSONResponse({"scenarios": [o.as_json() for o in panel.options.values()],
                             "planners": panel.planners, "gain_fields": list(GAINS_SHOWN),
                             "endpoint": panel.endpoint})

    async def state(request: Request) -> Response:
        return JSONResponse(panel.state())

    async def events(request: Request) -> Response:
        async def stream() -> AsyncIterator[str]:
            while not panel.closing.is_set():
                yield f"data: {json.dumps(panel.state())}\n\n"
                await asyncio.sleep(EVENT_PERIOD)
                if await request.is_disconnected():
                    break
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def stop(request: Request) -> Response:
        try:
            return JSONResponse(panel.stop())
        except BadInput as e:
            return bad(e)

    async def viewer(request: Request) -> Response:
        try:
            return JSONResponse(await run_in_threadpool(panel.open_viewer))
        except BadInput as e:
            return bad(e)

    async def recording(request: Request) -> Response:
        rec = str(panel.run.info.get("recording") or "")
        if not rec or not Path(rec).is_file():
            return JSONResponse({"error": "no recording yet", "field": "recording"}, status_code=404)
        return FileResponse(rec, media_type="application/octet-stream", filename="recording.rrd")

    async def not_found(request: Request, exc: Exception) -> Response:
        return JSONResponse({"error": f"no such page: {request.url.path}", "field": "request"}, status_code=404)

    async def not_allowed(request: Request, exc: Exception) -> Response:
        return JSONResponse({"error": f"{request.method} is not allowed on {request.url.path}", "field": "request"},
                            status_code=405)

    async def server_error(request: Request, exc: Exception) -> Response:
        log.exception("request %s %s failed", request.method, request.url.path)
        return JSONResponse({"error": f"internal error: {type(exc).__name__}: {exc}"[:300], "field": "request"},
                            status_code=500)

    routes = [
        Route("/", index),
        Route("/api/options", options),
        Route("/api/state", state),
        Route("/api/events", events),
        Route("/api/run", action(panel.start, blocking=False), methods=["POST"]),
        Route("/api/stop", stop, methods=["POST"]),
        Route("/api/goal", action(panel.goal, blocking=True), methods=["POST"]),
        Route("/api/cancel", action(panel.cancel, blocking=True), methods=["POST"]),
        Route("/api/gains", action(panel.gains, blocking=True), methods=["POST"]),
        Route("/api/viewer", viewer, methods=["POST"]),
        Route("/recording.rrd", recording),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes, exception_handlers={404: not_found, 405: not_allowed, 500: server_error})


def serve(host: str, port: int, *, connect: str | None = None, prefix: str | None = None,
          first: RunRequest | None = None, runs_dir: Path = Path("runs")) -> int:
    """Run the panel until SIGINT/SIGTERM; the run it started is stopped before it exits."""
    import uvicorn

    # uvicorn shuts down on SIGINT/SIGTERM, then raises the signal again for the handler it found:
    # with Python's defaults that would end the process before the run is stopped. Installed first,
    # so that a signal while the panel is starting also stops it in order (it then does not serve).
    stopped: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stopped.append(signum))
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: the panel listens on {host}: anyone who reaches it can start runs and move the robot "
              "(it has no authentication); keep it on a trusted network", file=sys.stderr, flush=True)
    try:  # a taken port is said before anything starts (not after a run was started for nothing)
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as e:
        print(f"hilsim ui: cannot listen on {host}:{port}: {e.strerror} (choose another with --port)",
              file=sys.stderr)
        return 2
    try:
        panel = Panel(connect=connect, prefix=prefix, runs_dir=runs_dir)
    except (ConnectionError, zenoh.ZError) as e:
        print(f"hilsim ui: {e}", file=sys.stderr)
        return 2
    try:
        if first is not None:
            try:
                info = panel.start_request(first)
            except BadInput as e:
                print(f"hilsim ui: {e}", file=sys.stderr)
                return 2
            print(f"started: {info['command']} (pid {info['pid']})", flush=True)
        print(f"hilsim panel: http://{host if ':' not in host else f'[{host}]'}:{port}/ (zenoh {panel.endpoint})",
              flush=True)
        config = uvicorn.Config(make_app(panel), host=host, port=port, log_level="warning",
                                timeout_graceful_shutdown=2)
        server = uvicorn.Server(config)
        if stopped:  # asked to stop while starting
            return 0
        server.run()
        return 0 if server.started or stopped else 2
    finally:
        print("hilsim panel: stopping", flush=True)
        panel.close()


def cmd_ui(args: argparse.Namespace) -> int:
    return serve(args.host, args.port, connect=args.connect, prefix=args.prefix)


def cmd_up_ui(args: argparse.Namespace) -> int:
    """``hilsim up SCENARIO … --ui``: the panel, with this run started from it."""
    extra: list[str] = []
    for s in args.set:
        extra += ["--set", s]
    for flag, val in (("--duration", args.duration), ("--seed", args.seed)):
        if val is not None:
            extra += [flag, str(val)]
    for h in args.hil:
        extra += ["--hil", h]
    for c in args.compose:
        extra += ["--compose", c]
    if args.no_logger:
        extra.append("--no-logger")
    if args.only or args.router:
        print("hilsim up --ui: --only and --router are not supported with the panel (it owns the router; "
              "use hilsim ui --connect EP)", file=sys.stderr)
        return 2
    req = RunRequest(args.scenario, args.world or "", "", args.clock or "realtime", "task", extra, args.out or "")
    return serve(args.ui_host, args.ui_port, first=req)
