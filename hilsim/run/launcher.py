"""``hilsim up``: start a scenario's services as separate processes, run its task, stop, summarise.

The launcher opens an embedded Zenoh router on a free loopback port (or joins ``--router``),
writes the resolved scenario to ``runs/<timestamp>/scenario.yaml``, starts one
``hilsim run SERVICE`` process per service of the scenario and per external joint server it
names (in the reverse of the order the service classes declare for stopping), waits for each
liveliness token, then follows the task result, every service's health and its faults. It stops
when the task result arrives, the scenario duration is reached, a service dies, or on Ctrl-C;
physics is stopped first and the logger last so it can drain and close the recording. Children
get SIGTERM if the launcher itself dies (PR_SET_PDEATHSIG), so no process outlives a run.

Restart policy (``restart.services``, :class:`hilsim.core.config.RestartConfig`): a service with
``on-failure`` that exits with a non-zero code (a crash, SIGKILL) is started again after
``restart.backoff`` seconds (doubled at each attempt), at most ``restart.max_attempts`` times,
with ``HILSIM_RESTART=<attempt>`` in its environment (:mod:`hilsim.core.restart`); its log continues
in the same file. In lockstep physics pauses sim time while it is gone and resumes when it is
back. Without the policy, or once the attempts are used up, a dead service ends the run. Each
restart is printed as it happens and listed in the summary.

Several machines (``--only physics,logger``, docs/deployment.md): only those services start here;
the others are expected from other hosts on the same Zenoh network, and the launcher waits for
their liveliness tokens as for its own (saying who is still missing), follows the run as usual,
and reports a remote service that leaves and does not come back.

Many robots (``robots: N``, :mod:`hilsim.core.fleet`): a per-robot service is one process for every
robot (``controller@*``); the launcher follows every robot's keys (``<prefix>/*/…``), names a
robot's service ``<service>@<robot>`` and waits for every robot's ``task/result``.

Reads: ``<prefix>/<robot>/task/result``, ``planner/result`` and ``navigator/result``, ``health/*``, ``log/*`` (faults,
printed as they happen), ``alive/*``.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import fleet, msgs, transport
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.restart import RESTART_ENV, STATE_DIR
from hilsim.core.scenario import load_scenario, write_scenario

LOGGER_NICE = 10
RESTART_READY_TIMEOUT = 120.0  # wall seconds a restarted service has to announce itself
REMOTE_GRACE_S = 10.0  # --only: how long a departed remote writer's samples are still its own


def stop_order(sc: Scenario) -> list[str]:
    """The scenario's processes in the order they stop (each class's ``stop_rank``: physics
    first, the recorder last); they start in the reverse order."""
    from hilsim.core.registry import service_class

    names = sc.launch_units()

    def rank(unit: str) -> int:
        # a composed process a+b+c stops at the rank of its first-stopping member, except one that
        # holds the recorder: it stops last, recording what the others publish as they stop
        ranks = {b: service_class(b, sc).stop_rank for b in (fleet.split_id(m)[0] for m in unit.split("+"))}
        return ranks["logger"] if "logger" in ranks else min(ranks.values())

    return sorted(names, key=lambda n: (rank(n), names.index(n)))


def _pdeathsig() -> None:
    """In the child: get SIGTERM when the launcher dies, and leave the terminal's signals to it."""
    os.setpgrp()
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _recorder_child() -> None:
    """The logger runs at a lower CPU priority: it buffers what it receives, so on a small
    machine the loop's services get the cores first and the logger catches up when idle."""
    _pdeathsig()
    os.nice(LOGGER_NICE)


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    ready: bool = False  # every service of the process has announced itself
    alive: set[str] = field(default_factory=set)  # those that have (a composed process has several)
    restarts: int = 0
    restart_at: float | None = None  # monotonic time of the pending restart
    died_at: float = 0.0  # monotonic time its last process was found dead


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
    restarts: list[Restart] = field(default_factory=list)


class Launcher:
    def __init__(self, sc: Scenario, run_dir: Path, *, router: str | None = None, quiet: bool = False,
                 only: list[str] | None = None) -> None:
        self.sc = sc
        # --only: the launch units started here; the rest run on other hosts (their tokens only)
        self.local = local_units(sc, only)
        self.remote: dict[str, bool] = {}  # remote service -> alive now
        self.remote_left: dict[str, float] = {}  # remote service -> monotonic time it left
        self.run_dir = run_dir
        self.keys = Keys(sc.prefix, sc.robot)
        # the keys followed: the robot's, or with robots > 1 every robot's (<prefix>/*/…)
        self.follow_keys = Keys(sc.prefix, "*") if sc.robots > 1 else self.keys
        self.robots = fleet.robot_names(sc)
        self.quiet = quiet
        self.router_ep = router
        self._router: zenoh.Session | None = None
        self.children: dict[str, Child] = {}
        self.outcome = Outcome()
        self.changed = threading.Event()
        self.lock = threading.Lock()
        # a service of another host: its last samples (task/result) may reach us well after its token
        # left, through the router and a loaded host; believed for longer than the default grace
        self.prov = Provenance(grace=REMOTE_GRACE_S) if len(self.local) < len(sc.launch_units()) else Provenance()
        self.untrusted = 0  # samples on the keys it follows from writers other than the services
        self.paused_for = ""  # lockstep: the services physics waits for to come back (its health)
        self._say_lock = threading.Lock()

    def say(self, text: str) -> None:
        if not self.quiet:
            with self._say_lock:  # several threads report: one whole line at a time
                print(text, flush=True)

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if self.router_ep is None:
            self.router_ep, self._router = open_default_router()
            self.say(f"zenoh router: {self.router_ep}")
        self.sc.zenoh.connect = [self.router_ep]
        self.sc.logger.run_dir = self.run_dir.resolve()
        cfg = self.run_dir / "scenario.yaml"
        write_scenario(self.sc, cfg)
        self.cfg_path = cfg
        # what restarted services take over (hilsim.core.restart) belongs to this run only
        shutil.rmtree(self.run_dir / STATE_DIR, ignore_errors=True)
        # before the liveliness subscriber: its history (services of other hosts already up) comes at once
        self.remote = {s: False for u in self.sc.launch_units() if u not in self.local
                       for s in fleet.members(self.sc, u)}
        self.session = transport.open_session(self.sc.zenoh)
        self._subs = [
            # first: who writes what, so that only the services' own samples are believed
            self.session.liveliness().declare_subscriber(self.keys.all_writers, self.prov.on_token, history=True),
            self.session.declare_subscriber(self.follow_keys.topic("planner/result"), self._on_result),
            self.session.declare_subscriber(self.follow_keys.topic("navigator/result"), self._on_result),
            self.session.declare_subscriber(self.follow_keys.topic("task/result"), self._on_result),
            self.session.declare_subscriber(self.follow_keys.health("*"), self._on_health),
            self.session.declare_subscriber(self.follow_keys.log("*"), self._on_log),
            self.session.liveliness().declare_subscriber(self.follow_keys.all_alive, self._on_alive, history=True),
        ]
        self.order = [n for n in stop_order(self.sc) if n in self.local]
        for name in reversed(self.order):
            self.children[name] = Child(name, self._spawn(name, 0), self.run_dir / f"{name}.log")

    def _spawn(self, name: str, attempt: int) -> subprocess.Popen[bytes]:
        """Start ``hilsim run NAME``; a restart (``attempt`` > 0) appends to the same log."""
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        if attempt:
            env[RESTART_ENV] = str(attempt)
        log_path = self.run_dir / f"{name}.log"
        with open(log_path, "ab" if attempt else "wb") as logf:
            if attempt:
                logf.write(f"--- hilsim up: restart {attempt} of {name} ---\n".encode())
                logf.flush()
            proc = subprocess.Popen(
                [sys.executable, "-m", "hilsim.cli", "run", name, "--config", str(self.cfg_path)],
                stdout=logf if name != "logger" else subprocess.PIPE,
                stderr=logf,
                stdin=subprocess.DEVNULL,
                env=env,
                preexec_fn=_recorder_child if name == "logger" else _pdeathsig,
            )
        if name == "logger":
            # the logger's stdout is its per-key summary, shown to the user at the end
            assert proc.stdout is not None
            threading.Thread(target=self._pump, args=(proc.stdout, log_path, attempt), daemon=True).start()
        return proc

    def _pump(self, stream: Any, log_path: Path, attempt: int = 0) -> None:
        with open(log_path.with_suffix(".out"), "ab" if attempt else "wb") as f:
            for line in stream:
                f.write(line)
                f.flush()

    def missing(self) -> list[str]:
        """Services not announced yet: this host's (by process) and the remote ones (marked)."""
        with self.lock:
            return ([c.name for c in self.children.values() if not c.ready]
                    + [f"{s} (remote)" for s, up in self.remote.items() if not up])

    def wait_ready(self, timeout: float = 120.0) -> bool:
        deadline = time.monotonic() + timeout
        last_print = time.monotonic()
        while time.monotonic() < deadline:
            if self.check_children():
                return False
            missing = self.missing()
            if not missing:
                pids = ", ".join(f"{c.name} (pid {c.proc.pid})" for c in self.children.values())
                remote = f"; remote: {', '.join(self.remote)}" if self.remote else ""
                self.say(f"ready: {pids}{remote}")
                return True
            if self.remote and time.monotonic() - last_print > 5.0:
                last_print = time.monotonic()
                self.say(f"  waiting for: {', '.join(missing)} ({deadline - last_print:.0f} s left)")
            self.changed.wait(0.1)
            self.changed.clear()
        missing = self.missing()
        hint = ""
        if any(m.endswith("(remote)") for m in missing):
            hint = (f"; start the remote ones on their hosts (hilsim up {self.sc.source or self.sc.name} --only … "
                    f"--router {self.router_ep}) and check they reach that router")
        self.say(f"error: services did not announce themselves within {timeout:.0f}s: {', '.join(missing)}{hint}")
        return False

    # ------------------------------------------------------------------ follow
    def _on_alive(self, sample: zenoh.Sample) -> None:
        svc = fleet.service_id(self.sc, str(sample.key_expr), "alive")
        name = next((u for u in self.children if svc in fleet.members(self.sc, u)), svc)  # its process
        with self.lock:
            if svc in self.remote and name not in self.children:
                self._on_remote(svc, sample.kind == zenoh.SampleKind.PUT)
                self.changed.set()
                return
            c = self.children.get(name)
            if c is None:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                c.alive.add(svc)
            else:
                c.alive.discard(svc)
            if sample.kind == zenoh.SampleKind.PUT and not c.ready and c.alive >= set(fleet.members(self.sc, name)):
                c.ready = True
                if c.restarts:
                    back = time.monotonic() - c.died_at
                    r = next((r for r in reversed(self.outcome.restarts) if r.name == name), None)
                    if r is not None:
                        r.back_after = back
                    self.say(f"  {name} is back (pid {c.proc.pid}), {back:.1f} s after it died")
        self.changed.set()

    def _on_remote(self, svc: str, up: bool) -> None:
        """A service of another host announced itself or left (under self.lock)."""
        was = self.remote[svc]
        self.remote[svc] = up
        if up and svc in self.remote_left:
            self.say(f"  remote {svc} is back, {time.monotonic() - self.remote_left.pop(svc):.1f} s after it left")
        elif was and not up:
            self.remote_left[svc] = time.monotonic()
            self.say(f"  remote {svc} left (its host's launcher may restart it)")

    def _poll_remote(self) -> None:
        """Ask who is alive: a remote service's departure must not hang on one liveliness event
        (seen lost through the router under load), so the run still ends, bounded."""
        try:
            replies = self.session.liveliness().get(self.follow_keys.all_alive, timeout=1.0)
            alive = {fleet.service_id(self.sc, str(r.ok.key_expr), "alive") for r in replies if r.ok is not None}
        except zenoh.ZError:
            return
        with self.lock:
            for svc, up in list(self.remote.items()):
                if up != (svc in alive) and (up or svc in self.remote_left):  # left, or back
                    self._on_remote(svc, not up)

    def _trusted(self, sample: zenoh.Sample) -> bool:
        """A sample from the key's announced writer (not a stranger's, nor a duplicate)."""
        why, _ = self.prov.check(str(sample.key_expr), transport.read_attachment(sample))
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
        robot = key.split("/")[1]
        with self.lock:
            if key.endswith("/task/result"):
                self.outcome.tasks[robot] = res
                if len(self.robots) == 1:
                    self.outcome.task = res
            elif res.goal_id != "task":  # the planner repeats the task's result on planner/result
                self.outcome.results.append(res)
                self.outcome.result_robots.append(robot)
                err = max((abs(e) for e in res.execution_error), default=float("nan"))
                status = "reached" if res.success else f"FAILED ({res.message})"
                if key.endswith("/navigator/result"):  # a rover goal: [m, rad]
                    pos, yaw = (*res.execution_error, float("nan"), float("nan"))[:2]
                    what = f"position error {pos:.3f} m, yaw error {yaw:.3f} rad (odometry)"
                else:
                    what = f"max joint error {err:.4f} rad"
                who = f"{robot}: " if len(self.robots) > 1 else ""
                self.say(f"  {who}{res.goal_id}: {status} at t={msgs.seconds(res.header.stamp):.2f}s sim, "
                         f"planning {res.planning_time:.2f}s, {what}")
        self.changed.set()

    def _on_log(self, sample: zenoh.Sample) -> None:
        """Faults of any service (a silent joint server, a stalled lockstep) as they happen."""
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

    def _on_health(self, sample: zenoh.Sample) -> None:
        if not self._trusted(sample):
            return
        try:
            h = msgs.decode(msgs.DiagnosticArray, sample.payload.to_bytes())
        except msgs.BadMessage:
            return
        # a robot's service (robots > 1) by <service>@<robot>: the robots' health apart
        sid = fleet.service_id(self.sc, str(sample.key_expr), "health")
        for st in h.status:
            vals = {kv.key: kv.value for kv in st.values}
            with self.lock:
                self.outcome.health[sid if st.name == sid.split("@")[0] else st.name] = vals
                if st.name == "physics" and vals.get("state") == "done":
                    self.outcome.physics_done = True
                if st.name == "physics" and vals.get("state") == "stalled" and not self.outcome.stalled:
                    self.outcome.stalled = vals.get("last_error", "lockstep stalled")
                if st.name == "physics":
                    self._paused(vals)
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

    def check_children(self) -> bool:
        """True if a service died and is not restarted (recorded in the outcome); a service
        whose restart policy allows it is started again once its backoff has passed."""
        dead = False
        now = time.monotonic()
        for c in self.children.values():
            if c.restart_at is not None:
                if now >= c.restart_at:
                    c.restart_at = None
                    c.proc = self._spawn(c.name, c.restarts)
                    self.say(f"  restarted {c.name} (pid {c.proc.pid}, attempt {c.restarts}/"
                             f"{self.sc.restart.max_attempts})")
                continue
            rc = c.proc.poll()
            if rc is None or (c.name, rc) in self.outcome.died:
                continue
            tail = _tail(c.log_path)
            why = f": {tail}" if tail else ""
            self.say(f"error: service {c.name} (pid {c.proc.pid}) exited with code {rc}{why}")
            rs = self.sc.restart
            if rc != 0 and rs.policy(c.name) == "on-failure" and c.restarts < rs.max_attempts:
                c.restarts += 1
                delay = rs.backoff * 2 ** (c.restarts - 1)
                with self.lock:
                    c.ready = False
                    c.alive.clear()  # its tokens died with it (their removal may still be on its way)
                    c.died_at = now
                    sim = self.outcome.health.get("physics", {}).get("sim_time", "?")
                    self.outcome.restarts.append(Restart(c.name, rc, sim))
                c.restart_at = now + delay
                self.say(f"  restart policy on-failure: restarting {c.name} in {delay:.1f} s "
                         f"(attempt {c.restarts}/{rs.max_attempts})")
                continue
            if rc != 0 and rs.policy(c.name) == "on-failure":
                self.say(f"error: {c.name} died {c.restarts + 1} times; restart.max_attempts "
                         f"({rs.max_attempts}) used up")
            self.outcome.died.append((c.name, rc))
            dead = True
        return dead

    def restarting(self) -> list[str]:
        """Services that died and are not back yet (restart pending or not announced)."""
        return [c.name for c in self.children.values() if c.restarts and (c.restart_at is not None or not c.ready)]

    def follow(self, wall_timeout: float | None = None) -> None:
        """Wait for the end of the run: task result, duration, a dead service, or Ctrl-C."""
        t0 = time.monotonic()
        last_print = last_poll = t0
        while True:
            if self.check_children():
                return
            with self.lock:
                if self.outcome.task is not None or self.outcome.physics_done:
                    return
                if len(self.robots) > 1 and len(self.outcome.tasks) == len(self.robots):
                    return  # every robot's task ended
                if self.outcome.stalled:
                    self.say(f"error: the simulation stalled: {self.outcome.stalled}; stopping")
                    return
            if wall_timeout is not None and time.monotonic() - t0 > wall_timeout:
                self.say(f"error: run did not finish within {wall_timeout:.0f}s wall")
                return
            if self.remote and time.monotonic() - last_poll > 2.0:
                last_poll = time.monotonic()
                self._poll_remote()
            with self.lock:
                gone = [s for s, t in self.remote_left.items() if time.monotonic() - t > RESTART_READY_TIMEOUT]
            if gone:
                self.say(f"error: remote {', '.join(gone)} left and did not come back within "
                         f"{RESTART_READY_TIMEOUT:.0f}s")
                self.outcome.died.extend((s, -1) for s in gone)
                return
            late = [c for c in self.children.values() if c.restarts and c.restart_at is None and not c.ready
                    and time.monotonic() - c.died_at > RESTART_READY_TIMEOUT]
            if late:
                names = ", ".join(c.name for c in late)
                self.say(f"error: restarted {names} did not announce itself within {RESTART_READY_TIMEOUT:.0f}s")
                self.outcome.died.extend((c.name, -1) for c in late)
                return
            if time.monotonic() - last_print > 10.0:
                last_print = time.monotonic()
                ph = self.outcome.health.get("physics", {})
                self.say(f"  … sim time {ph.get('sim_time', '?')} s, "
                         f"real-time factor {ph.get('real_time_factor', '?')}")
            self.changed.wait(0.2)
            self.changed.clear()

    # ------------------------------------------------------------------ stop
    def stop(self) -> None:
        for name in getattr(self, "order", []):
            c = self.children.get(name)
            if c is None:
                continue
            c.restart_at = None  # a restart still pending when the run ends does not happen
            if c.proc.poll() is None:
                c.proc.send_signal(signal.SIGINT)
                c.proc.send_signal(signal.SIGCONT)  # a stopped (suspended) service must handle it too
                try:
                    c.proc.wait(timeout=300 if name == "logger" else 15)
                except subprocess.TimeoutExpired:
                    self.say(f"warning: {name} did not stop within the grace period; killing it")
                    c.proc.kill()
                    c.proc.wait()
        for s in getattr(self, "_subs", []):
            s.undeclare()
        if hasattr(self, "session"):
            self.session.close()
        if self._router is not None:
            self._router.close()

    def kill_all(self) -> None:
        for c in self.children.values():
            if c.proc.poll() is None:
                c.proc.kill()


def open_default_router() -> tuple[str, zenoh.Session]:
    """The well-known loopback port if free (so `hilsim topic` finds it), else any free port."""
    ep = f"tcp/127.0.0.1:{transport.DEFAULT_ROUTER_PORT}"
    try:
        return ep, transport.open_router(ep)
    except ConnectionError:
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        print(f"note: port {transport.DEFAULT_ROUTER_PORT} is taken (another simulation?); using {ep} "
              f"(pass --connect {ep} to hilsim topic)", flush=True)
        return ep, transport.open_router(ep)


def local_units(sc: Scenario, only: list[str] | None) -> list[str]:
    """The launch units this host starts: all of them, or those of ``--only`` (services by name;
    a composed group ``a+b`` as a whole). ConfigError (one line) for a name the scenario lacks."""
    from hilsim.core.config import ConfigError

    units = sc.launch_units()
    if not only:
        return units
    procs = sc.processes()
    unknown = [n for n in only if n not in procs and n not in units]
    if unknown:
        raise ConfigError(f"--only {','.join(only)}: {', '.join(unknown)} not among this scenario's services "
                          f"({', '.join(procs)})")
    out = []
    for u in units:
        members = u.split("+")
        picked = [m for m in members if m in only or u in only]
        if picked and len(picked) != len(members):
            raise ConfigError(f"--only {','.join(only)}: {u} runs as one process (compose); name all of "
                              f"{', '.join(members)} or none")
        if picked:
            out.append(u)
    return out


def _num(v: str | None) -> int:
    """A count from a health value (0 when absent or not a number)."""
    try:
        return int(v or 0)
    except ValueError:
        return 0


def _tail(path: Path, n: int = 1) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    errs = [ln for ln in lines if "ERROR" in ln or "Error" in ln or "error" in ln]
    return " | ".join((errs or lines)[-n:])[-300:]


def default_run_dir(sc: Scenario) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]
    return Path(sc.logger.out_dir) / stamp


def summarise(la: Launcher) -> int:
    o, sc = la.outcome, la.sc
    # with no task and no duration, Ctrl-C is how a run ends: not a failure
    open_ended = not sc.task.targets and sc.duration is None
    ok = not o.died and not o.stalled and (not o.interrupted or open_ended)
    n_targets = len(sc.task.targets)
    print("summary:")
    if n_targets and len(la.robots) > 1:  # robots > 1: each robot's own task
        for robot in la.robots:
            reached = sum(1 for r, who in zip(o.results, o.result_robots, strict=True)
                          if who == robot and r.success and r.goal_id.startswith("task-"))
            task = o.tasks.get(robot)
            if task is None:
                print(f"  {robot}: targets reached {reached}/{n_targets}, task not finished")
                ok = ok and sc.duration is not None and o.physics_done
                continue
            err = max((abs(e) for e in task.execution_error), default=float("nan"))
            print(f"  {robot}: targets reached {reached}/{n_targets}, final max joint error {err:.4f} rad")
            ok = ok and task.success and reached == n_targets
    elif n_targets:
        reached = sum(1 for r in o.results if r.success and r.goal_id.startswith("task-"))
        print(f"  targets reached: {reached}/{n_targets}")
        if o.task is not None:
            # the joints as the planner named them in its trajectories (index if it sent none)
            named = next((list(r.trajectory.joint_names) for r in o.results if r.trajectory.joint_names), [])
            err = o.task.execution_error
            names = named if len(named) == len(err) else [f"#{i}" for i in range(len(err))]
            errs = ", ".join(f"{n} {e:+.4f}" for n, e in zip(names, err, strict=True))
            if "navigator" in sc.services and len(err) == 2:  # the rover: [position m, yaw rad]
                print(f"  final error: position {err[0]:.3f} m, yaw {err[1]:.3f} rad (odometry)")
            else:
                print(f"  final error per joint [rad]: {errs}")
            ok = ok and o.task.success and reached == n_targets
        else:
            print("  task: not finished")
            ok = ok and sc.duration is not None and o.physics_done
    ph = o.health.get("physics", {})
    if ph:
        print(f"  sim time {ph.get('sim_time', '?')} s, real-time factor {ph.get('real_time_factor', '?')}, "
              f"clock {sc.clock.mode}, seed {sc.seed}")
    for name, h in sorted(o.health.items()):
        bad = _num(h.get("rejected")) + _num(h.get("errors"))
        if bad:
            print(f"  {name}: {h.get('rejected')} rejected, {h.get('errors')} errors (last: {h.get('last_error', '')})")
    rrd = la.run_dir / "recording.rrd"
    if any("logger" in u.split("+") for u in la.local):  # a recorder on another host summarises there
        # a recorder that died left no footer (and no counts): make its file whole, say what it holds
        logger_restarted = any(r.name == "logger" for r in o.restarts)
        if logger_restarted or any(n == "logger" for n, _ in o.died):
            ok = _recover_recordings(la.run_dir) and ok
        summary = la.run_dir / "record_summary.json"
        if summary.exists():
            counts = json.loads(summary.read_text())
            rec = sum(v.get("recorded", 0) for v in counts.values())
            recv = sum(v.get("received", 0) for v in counts.values())
            mismatch = sorted(k for k, v in counts.items() if v.get("received") != v.get("recorded"))
            lost = {k: v["lost"] for k, v in counts.items() if v.get("lost")}
            n_lost, n_full = sum(lost.values()), sum(v.get("dropped", 0) for v in counts.values())
            realtime = sc.clock.mode == "realtime"

            def short(key: str) -> str:  # keys as the user names them: clock, truth/joint_states, …
                for p in (f"{sc.prefix}/{sc.robot}/", f"{sc.prefix}/"):
                    if key.startswith(p):
                        return key[len(p):]
                return key

            line = f"  recorded {rec} of {recv} received messages on {len(counts)} keys"
            if n_lost:
                where = "in transport"
                if n_full:
                    where = f"({n_lost - n_full} in transport, {n_full} dropped by the recorder)"
                why = "realtime: the recorder could not keep up" if realtime else "lockstep, where nothing may be lost"
                top = sorted(lost.items(), key=lambda kv: (-kv[1], kv[0]))
                keys = ", ".join(f"{short(k)} {n}" for k, n in top[:8]) + (", …" if len(top) > 8 else "")
                line += f"; lost {n_lost} {where} ({why}): {keys}"
            if mismatch:
                line += f"; MISMATCH (received but not recorded) on {mismatch}"
            print(line)
            # Samples sent after the last one of their writer that reached the recorder (dropped, or
            # still in flight when the run stopped) leave no gap it could count: compare with what
            # every service says it published per key (final health).
            published: dict[str, int] = {}
            for h in o.health.values():
                for k, v in h.items():
                    if k.startswith("published:"):
                        published[k[10:]] = published.get(k[10:], 0) + _num(v)
            unseen = {}
            for k, v in counts.items():
                seen = v["received"] + v.get("lost", 0) + v.get("before_first", 0)
                if published.get(k, 0) > seen:
                    unseen[k] = published[k] - seen
            if unseen:
                top = sorted(unseen.items(), key=lambda kv: (-kv[1], kv[0]))
                keys = ", ".join(f"{short(k)} {n}" for k, n in top[:8]) + (", …" if len(top) > 8 else "")
                print(f"  {sum(unseen.values())} published samples never reached the recorder: {keys}")
                n_lost += sum(unseen.values())
            if logger_restarted:
                # what the killed recorder had received is in its part of the recording, but its
                # counts died with it, and what it had not flushed yet is lost: reported, not
                # judged (the restart policy asked for the run to go on)
                print("  (the recorder was restarted: these counts are its last process's; samples the killed "
                      "one had not written yet are lost)")
                n_lost = 0
            # realtime: a loss is reported, not a failure; lockstep promises that nothing is lost
            ok = ok and not mismatch and (realtime or not n_lost)
        else:
            print("  recording summary missing")
            ok = False
        print(f"  recording: {rrd}")
    print(f"  logs: {la.run_dir}/")
    for name, rc in o.died:
        print(f"  service {name} died (exit code {rc})")
    if o.stalled:
        print(f"  stalled: {o.stalled}")
    if o.faults:
        print(f"  faults reported: {len(o.faults)} (first: {o.faults[0]})")
    for r in o.restarts:
        back = f"back after {r.back_after:.1f} s" if r.back_after is not None else "not back"
        print(f"  restarted {r.name} (exit code {r.rc} at sim time {r.sim_time} s; {back})")
    if la.untrusted:
        print(f"  ignored {la.untrusted} samples on results, health and logs from writers other than the services")
    print("result: " + ("OK" if ok else "FAILED"))
    return 0 if ok else 1


def _world_of(path: Path) -> str | None:
    try:
        return load_scenario(path).world.model.stem
    except Exception:  # not a scenario (an overlay), or a broken one: no world to offer
        return None


def world_scenario(scenario: str, world: str) -> str:
    """``hilsim up SCENARIO --world NAME``: the scenario itself when its world is
    ``models/worlds/NAME.xml``, else its variant ``<scenario>-NAME.yaml`` next to it (which sets that
    world and what goes with it: the GPS and its datum, the goals); anything else is a one-line error."""
    from hilsim.core.config import ConfigError
    from hilsim.core.scenario import scenario_path

    base = scenario_path(scenario)
    own = load_scenario(base).world.model.stem
    if world == own:
        return str(base)
    variant = base.with_name(f"{base.stem}-{world}.yaml")
    if variant.exists():
        return str(variant)
    variants = {p.stem[len(base.stem) + 1:]: p for p in base.parent.glob(f"{base.stem}-*.yaml")}
    worlds = [own, *sorted(w for w, p in variants.items() if _world_of(p) == w)]
    raise ConfigError(f"--world {world}: scenario {base.stem} has no such world (worlds: {', '.join(worlds)}; "
                      f"a world W needs {base.parent.name}/{base.stem}-W.yaml)")


def _recover_recordings(run_dir: Path) -> bool:
    """After a recorder died: make each part of the run's recording complete (a SIGKILL leaves no
    RRD footer) and say what it holds; False if a part could not be recovered."""
    from hilsim.core.recording import RecordingError, contents, recording_parts, recover_rrd

    ok = True
    for part in recording_parts(run_dir):
        try:
            rewritten = recover_rrd(part)
            c = contents(part)
        except RecordingError as e:
            print(f"  recording {part}: NOT RECOVERED: {str(e).splitlines()[0]}")
            ok = False
            continue
        upto = f"up to t={c.last_sim_ns / 1e9:.3f} s sim" if c.last_sim_ns is not None else "no sim time"
        how = "the recorder was killed: recovered, verified" if rewritten else "complete, verified"
        print(f"  recording {part}: {sum(c.rows.values())} rows on {len(c.rows)} entities {upto} ({how})")
    return ok


def cmd_up(args: argparse.Namespace) -> int:
    from hilsim.core.scenario import parse_overrides

    overrides = parse_overrides(args.set)
    if args.clock:
        overrides["clock.mode"] = args.clock
    if args.duration is not None:
        overrides["duration"] = args.duration
    if args.seed is not None:
        overrides["seed"] = args.seed
    if getattr(args, "wait", None) is not None:  # physics waits as long as the launcher does
        overrides["clock.start_timeout"] = args.wait
    if args.compose:
        overrides["compose"] = [[n.strip() for n in g.split(",") if n.strip()] for g in args.compose]
    only = [n.strip() for n in args.only.split(",") if n.strip()] if getattr(args, "only", None) else None
    if only and "zenoh.mode" not in overrides and not os.environ.get("HILSIM_ZENOH_MODE"):
        # several hosts: every process a client of the router. Peers listen on loopback, and
        # Zenoh (1.10) did not route between peers of two hosts through the router for them
        overrides["zenoh.mode"] = "client"
    scenario = world_scenario(args.scenario, args.world) if getattr(args, "world", None) else args.scenario
    sc = load_scenario(scenario, overrides, overlays=args.hil)
    if args.no_logger:
        sc.services = [s for s in sc.services if s != "logger"]
    run_dir = Path(args.out) if args.out else default_run_dir(sc)
    if sc.zenoh.tls is not None and not args.router:
        from hilsim.core.config import ConfigError

        raise ConfigError("zenoh.tls is set: start the router with `hilsim router --config FILE` and pass its "
                          "tls/ endpoint with --router (docs/security.md)")
    la = Launcher(sc, run_dir, router=args.router, only=only)
    here = f" ({', '.join(la.local)} here, the rest from other hosts)" if only else ""
    print(f"hilsim up {sc.name}: {len(sc.processes())} services{here}, clock {sc.clock.mode}, seed {sc.seed}, "
          f"run dir {run_dir}")

    def on_signal(signum: int, _frame: Any) -> None:
        la.outcome.interrupted = True
        la.changed.set()
        raise KeyboardInterrupt

    # explicit for SIGINT too: a launcher started in the background of a script inherits
    # SIGINT ignored, and Python then never raises KeyboardInterrupt
    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        la.start()
        if la.wait_ready(sc.clock.start_timeout):
            if not sc.task.targets and sc.duration is None:
                robot = fleet.robot_names(sc)[0] if sc.robots > 1 else sc.robot  # robots > 1: e.g. arm0
                how = (f"send goals with `hilsim goal {robot} --joints …`" if "planner" in sc.services
                       else f"send goals with `hilsim goal {robot} --xy X Y`" if "navigator" in sc.services
                       else f"drive it with geometry_msgs/Twist on {Keys(sc.prefix, robot).topic('cmd_vel')}")
                print(f"no task targets and no --duration: running until Ctrl-C ({how})", flush=True)
            la.follow()
    except KeyboardInterrupt:
        la.outcome.interrupted = True
        print("interrupted: stopping services…", flush=True)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        try:
            la.stop()
        except KeyboardInterrupt:
            la.kill_all()
    return summarise(la)


def cmd_router(args: argparse.Namespace) -> int:
    """``hilsim router [--listen EP] [--config FILE]``: a standalone router; with a Zenoh config
    file (listen endpoints, TLS, access control: docs/security.md), ``--listen`` replaces its
    endpoints."""
    try:
        if args.config:
            conf = transport.router_config(Path(args.config), [args.listen] if args.listen else None)
            where = ", ".join(json.loads(conf.get_json("listen/endpoints") or "[]")) or "no endpoint"
            r = transport.open_router_config(conf, f"{args.config}: {where}")
        else:
            where = args.listen or transport.DEFAULT_CONNECT
            r = transport.open_router(where)
    except ConnectionError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"zenoh router listening on {where} (Ctrl-C to stop)", flush=True)
    from hilsim.core.service import on_stop_signals

    stop = threading.Event()
    on_stop_signals(stop.set)  # Ctrl-C or SIGTERM: not stop.set in a signal handler (see there)
    stop.wait()
    r.close()
    return 0
