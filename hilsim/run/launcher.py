"""``hilsim up``: start a scenario's services as separate processes, run its task, stop, summarise.

This module supervises the processes (the :class:`Launcher`: start, liveliness, restarts, stop) and
holds the command; following what the services report is :mod:`hilsim.run.follow`, the summary
printed at the end :mod:`hilsim.run.summary`, the embedded router :mod:`hilsim.run.router`.

The launcher opens an embedded Zenoh router on a free loopback port (or joins ``--router``) that
admits only the run's processes, each with an identity of its own that may write only what the key
table gives it (:func:`open_run_router`, :mod:`hilsim.core.rights`; docs/security.md; the launcher's own
session only reads), writes the resolved scenario to ``runs/<timestamp>/scenario.yaml``, starts one
``hilsim run SERVICE`` process per service of the scenario and per external joint server it
names (in the reverse of the order the service classes declare for stopping), waits for each
liveliness token, then follows the task result, every service's health and its faults. It stops
when the task result arrives, the scenario duration is reached, a service dies, or on Ctrl-C;
physics is stopped first and the logger last so it can drain and close the recording. Ctrl-C or
SIGTERM again while they stop kills them at once; signals are taken by a watcher thread, never
raised in the main thread, so stopping and the summary always finish. ``--interactive`` runs no
task and stays up until Ctrl-C. Children
get SIGTERM if the launcher itself dies (PR_SET_PDEATHSIG), so no process outlives a run.

Restart policy (``restart.services``, :class:`hilsim.core.config.RestartConfig`): a service with
``on-failure`` that exits with a non-zero code (a crash, SIGKILL) is started again after
``restart.backoff`` seconds (doubled at each attempt), at most ``restart.max_attempts`` times,
with ``HILSIM_RESTART=<attempt>`` in its environment (:mod:`hilsim.core.restart`); its log continues
in the same file. In lockstep physics pauses sim time while it is gone and resumes when it is
back. Without the policy, or once the attempts are used up, a dead service ends the run. Each
restart is printed as it happens and listed in the summary. A lockstep participant that is alive but
silent (stopped, hung) for ``clock.ack_timeout``, as physics says: without the policy a fault ends the
run (the silent process killed at the stop, not resumed); with it, it is killed (SIGKILL, which even a
stopped process gets) and so restarted (:meth:`Launcher.kill_silent`).

Several machines (``--only physics,logger``, docs/deployment.md): only those services start here;
the others are expected from other hosts on the same Zenoh network, and the launcher waits for
their liveliness tokens as for its own (saying who is still missing), follows the run as usual,
and reports a remote service that leaves and does not come back.

Many robots (``robots: N``, :mod:`hilsim.core.fleet`): a per-robot service is one process for every
robot (``controller@*``); the launcher follows every robot's keys (``<domain>/*/…``), names a
robot's service ``<service>@<robot>`` and waits for every robot's ``task/result``.

Reads: ``<prefix>/<robot>/alive/*`` (liveliness tokens: who is up, who left; every robot's
``<prefix>/*/alive/*`` with ``robots: N``), also asked for with a liveliness query while services of
other hosts are expected. Through its :class:`~hilsim.run.follow.Follower`: the ROS 2 graph,
``task/result``, ``planner/result``, ``navigator/result``, ``health/*``, ``log/*``. Writes no key.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import fleet, runs, transport
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.restart import RESTART_ENV, STATE_DIR
from hilsim.core.scenario import load_scenario, write_scenario
from hilsim.core.service import watch_signals
from hilsim.run.follow import Follower, Outcome, Restart
from hilsim.run.router import cmd_router, identity_file, open_default_router, open_run_router
from hilsim.run.summary import summarise
from hilsim.run.worlds import world_scenario

# the names other modules import from here, wherever they are defined
__all__ = ["Child", "Launcher", "Outcome", "Restart", "cmd_router", "cmd_up", "default_run_dir", "local_units",
           "open_default_router", "stop_order", "summarise", "world_scenario"]

LOGGER_NICE = 10
ROUTER_PRIORITY = 5  # realtime: SCHED_FIFO of the run's router (physics 10, the HIL bridges 20)
LOOP_PRIORITY = 8  # realtime: SCHED_FIFO the launcher gives the loop's services that asked for none
PLANNING_PRIORITY = 1  # …and the planner or navigator: below every other, its plans are bursts of CPU
LOGGER_PRIORITY = 1  # realtime: the recorder's receiving (its worker stays in the ordinary class)
# the recorder's writing threads (its worker, Rerun's), left in the ordinary class
RERUN_THREADS = ("logger-worker", "ChunkBatcher", "RecordingStream", "file_writer", "jemalloc")
RESTART_READY_TIMEOUT = 120.0  # wall seconds a restarted service has to announce itself
REMOTE_LEAVE_TIMEOUT = 10.0  # s the recorder waits, at a run's end, for the other hosts' services to leave
REMOTE_MISSES = 2  # --only: polls in a row that must miss a remote service's token before it has left
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
    """In the child: get SIGTERM when the launcher dies, and leave the terminal's signals to it; an
    ordinary scheduling class whatever the launcher's (a realtime run's router: each service asks
    for its own)."""
    os.setpgrp()
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass


def _realtime_process(pid: int, priority: int, skip: tuple[str, ...] = ()) -> bool:
    """Give every thread of a process that has an ordinary scheduling class SCHED_FIFO ``priority``
    (threads it makes later inherit it; one that asked for its own class keeps it), but those whose name
    starts with one of ``skip``. False: not permitted (root or CAP_SYS_NICE) or gone."""
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            if skip and Path(f"/proc/{pid}/task/{tid}/comm").read_text().startswith(skip):
                continue
            if os.sched_getscheduler(int(tid)) == os.SCHED_OTHER:
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
    except OSError:
        return False
    return True


def _renice(pid: int, nice: int) -> None:
    """Give every thread of a process the niceness ``nice`` (Linux keeps it per thread; threads made
    later inherit their maker's). Gone or not permitted: left as it is."""
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.setpriority(os.PRIO_PROCESS, int(tid), nice)
    except OSError:
        pass


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


class Launcher:
    """The processes of one run: started, watched (liveliness, exit codes), restarted, stopped."""

    def __init__(self, sc: Scenario, run_dir: Path, *, router: str | None = None, quiet: bool = False,
                 only: list[str] | None = None, per_service: bool = True) -> None:
        self.sc = sc
        # each process its own identity on the run's router (hilsim.core.rights); False: one for all, with
        # every right (hilsim bench loop's baseline)
        self.per_service = per_service
        self.identities: dict[str, Path] = {}  # launch unit -> its identity's client config
        # --only: the launch units started here; the rest run on other hosts (their tokens only)
        self.local = local_units(sc, only)
        self.remote: dict[str, bool] = {}  # remote service -> alive now
        self.remote_left: dict[str, float] = {}  # remote service -> monotonic time it left
        self.remote_missed: dict[str, int] = {}  # remote service -> polls in a row that did not find it
        self.run_dir = run_dir
        self.keys = Keys.of(sc)
        # the keys followed: the robot's, or with robots > 1 every robot's (<prefix>/*/…)
        self.follow_keys = Keys.of(sc, "*") if sc.robots > 1 else self.keys
        self.robots = fleet.robot_names(sc)
        self.quiet = quiet
        self.router_ep = router
        self._router: zenoh.Session | None = None
        self._pointer: Path | None = None  # the pointer file to this run's router (runs.write_pointer)
        self.children: dict[str, Child] = {}
        self.hurry = False  # a second stop signal: services are killed, not waited for
        self.changed = threading.Event()
        self.lock = threading.Lock()
        # a service of another host: its last samples (task/result) may reach us well after its token
        # left, through the router and a loaded host; believed for longer than the default grace
        self.prov = Provenance(grace=REMOTE_GRACE_S) if len(self.local) < len(sc.launch_units()) else Provenance()
        self._say_lock = threading.Lock()
        # what the services report (results, health, faults), followed into the outcome
        self.follower = Follower(sc, self.follow_keys, self.robots, self.prov, lock=self.lock, changed=self.changed,
                                 say=self.say)

    @property
    def outcome(self) -> Outcome:
        """The run so far: what the follower saw, and the deaths and restarts seen here."""
        return self.follower.outcome

    @property
    def untrusted(self) -> int:
        """Samples on the keys it follows from writers other than the services."""
        return self.follower.untrusted

    def say(self, text: str) -> None:
        if not self.quiet:
            with self._say_lock:  # several threads report: one whole line at a time
                print(text, flush=True)

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        own = self.sc.zenoh.model_copy()  # the launcher's own session: it only reads
        if self.router_ep is None:
            # only this run's processes may join it, each with an identity of its own that may write only
            # what the key table gives it (hilsim.core.rights, docs/security.md)
            rr = open_run_router(self.run_dir, self.sc, per_service=self.per_service)
            self.router_ep, self._router, self._pointer = rr.endpoint, rr.session, rr.pointer
            self.identities = rr.identities
            self.sc.zenoh.auth, own.auth = rr.client_config, rr.launcher_config  # scenario.yaml: the tools' file
            guests = f"; guests read with {rr.guest_config}" if rr.guest_config else ""
            self.say(f"zenoh router: {self.router_ep} (each process an identity of its own in "
                     f"{rr.client_config.parent / transport.IDENTITIES_DIR}; tools and ROS 2 nodes: "
                     f"{rr.client_config}{guests})")
            if self.sc.clock.mode == "realtime":
                self._raise_router_priority()
        else:
            ptr = runs.run_at([self.router_ep])
            if ptr is not None and self.sc.zenoh.tls is None:  # the router of another run of this user
                found = {u: identity_file(ptr.run_dir, u) for u in self.local}
                self.identities = {u: f for u, f in found.items() if f.is_file()}
        self.sc.zenoh.connect = [self.router_ep]
        own.connect = [self.router_ep]
        self.sc.logger.run_dir = self.run_dir.resolve()
        cfg = self.run_dir / "scenario.yaml"
        write_scenario(self.sc, cfg)
        self.cfg_path = cfg
        # what restarted services take over (hilsim.core.restart) belongs to this run only
        shutil.rmtree(self.run_dir / STATE_DIR, ignore_errors=True)
        # before the liveliness subscriber: its history (services of other hosts already up) comes at once
        self.remote = {s: False for u in self.sc.launch_units() if u not in self.local
                       for s in fleet.members(self.sc, u)}
        self.session = transport.open_session(own)
        self._subs = [
            *self.follower.subscribe(self.session),  # first who writes what, then results, health, logs
            self.session.liveliness().declare_subscriber(self.follow_keys.all_alive, self._on_alive, history=True),
        ]
        self.order = [n for n in stop_order(self.sc) if n in self.local]
        for name in reversed(self.order):
            self.children[name] = Child(name, self._spawn(name, 0), self.run_dir / f"{name}.log")

    def _raise_router_priority(self) -> None:
        """Realtime: every sample of the loop crosses the run's router, in this process. Physics steps
        with SCHED_FIFO, and so do the HIL bridges (config/hil/can.yaml), but on a machine busy with
        other work the router's threads waited for a CPU for a quarter of a second at a time, and
        physics faulted a joint server as silent whose estimates were on their way (issue 36). So the
        router gets SCHED_FIFO too, below physics, and so do the threads Zenoh starts later (its receive
        and send runtimes start with their first link: with SCHED_RESET_ON_FORK they came up ordinary);
        the processes this one starts are set back to an ordinary class (:func:`_pdeathsig`). Without the
        privilege (root or CAP_SYS_NICE) it stays as it is."""
        try:
            for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(ROUTER_PRIORITY))
        except (PermissionError, AttributeError, OSError) as e:
            self.say(f"  (the router could not get a real-time scheduling class: {e}; on a busy machine the "
                     "realtime loop's samples may wait for it)")

    def _spawn(self, name: str, attempt: int) -> subprocess.Popen[bytes]:
        """Start ``hilsim run NAME``; a restart (``attempt`` > 0) appends to the same log."""
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        if attempt:
            env[RESTART_ENV] = str(attempt)
        auth = self.identities.get(name, self.sc.zenoh.auth)
        if auth is not None:  # its own identity on the run's router, whatever the caller's environment says
            env[transport.AUTH_ENV] = str(auth)
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
                preexec_fn=_pdeathsig,
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
            if self.outcome.interrupted or self.check_children():
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
        self.outcome.not_started = missing  # a run that never started is no OK run
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
                if self.sc.clock.mode == "realtime" and name != "logger" and self._router is not None:
                    # realtime, with the run's own router on SCHED_FIFO: the loop's services too, once set
                    # up (physics and the HIL bridges ask for more themselves), so that other work on the
                    # machine cannot hold a step; the planner or navigator lowest (its plans are bursts)
                    units = name.split("+")
                    planning = {"planner", "navigator"}.intersection(u.split("@")[0] for u in units)
                    _realtime_process(c.proc.pid, PLANNING_PRIORITY if planning and len(units) == 1
                                      else LOOP_PRIORITY)
                if name == "logger" and self.sc.clock.mode == "realtime":
                    # Realtime: the recorder's receiving on SCHED_FIFO like the loop's services (lowest), so that
                    # no other work on the machine makes it drop samples; its worker (writing the files, the
                    # bulk of its CPU) puts itself back to the ordinary class (services/logger.py), and is not
                    # niced: its queue is bounded, what it cannot write in time is lost. Niced, two runs' recorders
                    # each lost a quarter of their samples.
                    if self._router is not None:
                        _realtime_process(c.proc.pid, LOGGER_PRIORITY, skip=RERUN_THREADS)
                elif name == "logger":
                    # Lockstep: the recorder runs at a lower CPU priority once it is set up: it buffers what it
                    # receives, so on a small machine the loop's services get the cores first and it
                    # catches up when idle. Not before: niced from its start, on a machine busy with
                    # other work it took minutes to import and set up, and the whole run (and a HIL
                    # device's start-up timeouts) waited for it.
                    _renice(c.proc.pid, LOGGER_NICE)
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
        (seen lost through the router under load), so the run still ends, bounded. A service counts
        as gone only when ``REMOTE_MISSES`` polls in a row did not find it: one query's reply can miss
        a token that is there (seen at a run's start: "left", then "back" 2 s later, though nothing
        had left); a reply without any token at all (this host's services answer too) says nothing."""
        try:
            replies = self.session.liveliness().get(self.follow_keys.all_alive, timeout=1.0)
            alive = {fleet.service_id(self.sc, str(r.ok.key_expr), "alive") for r in replies if r.ok is not None}
        except zenoh.ZError:
            return
        if not alive:
            return
        with self.lock:
            for svc, up in list(self.remote.items()):
                if svc in alive:
                    self.remote_missed.pop(svc, None)
                    if not up and svc in self.remote_left:  # back
                        self._on_remote(svc, True)
                elif up:
                    self.remote_missed[svc] = self.remote_missed.get(svc, 0) + 1
                    if self.remote_missed[svc] >= REMOTE_MISSES:  # left, its departure event lost
                        self.remote_missed.pop(svc)
                        self._on_remote(svc, False)

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

    def kill_silent(self) -> None:
        """Kill (SIGKILL) the process of a service physics says is silent for ``clock.ack_timeout``
        while its restart policy is on-failure: stopped (SIGSTOP) or hung, it never exits by itself,
        and SIGKILL reaches even a stopped process; :meth:`check_children` then restarts it. Not one
        that is starting again (not announced yet): a restart may take longer than ``ack_timeout``."""
        with self.lock:  # taken: physics says it once per silence
            silent, self.follower.silent = self.follower.silent, set()
        if not silent:
            return
        for c in self.children.values():
            who = sorted(silent & set(fleet.members(self.sc, c.name)))
            if not who or not c.ready or c.restart_at is not None or c.proc.poll() is not None:
                continue
            self.say(f"error: {', '.join(who)} (pid {c.proc.pid}) silent for clock.ack_timeout "
                     f"({self.sc.clock.ack_timeout:g} s): stopped or hung; killing it to restart it")
            c.proc.kill()

    def restarting(self) -> list[str]:
        """Services that died and are not back yet (restart pending or not announced)."""
        return [c.name for c in self.children.values() if c.restarts and (c.restart_at is not None or not c.ready)]

    def follow(self, wall_timeout: float | None = None) -> None:
        """Wait for the end of the run: task result, duration, a dead service, or Ctrl-C."""
        t0 = time.monotonic()
        last_print = last_poll = t0
        while True:
            if self.outcome.interrupted or self.check_children():
                return
            self.kill_silent()
            if self.follower.ended():  # the task, the duration, or a stalled lockstep
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
                self.follower.progress()
            self.changed.wait(0.2)
            self.changed.clear()

    # ------------------------------------------------------------------ stop
    def stop(self) -> None:
        """Stop every service in order (SIGINT, the recorder given time to close its files), or
        kill them after :meth:`interrupt` said hurry; then close the session and the router,
        whatever happened before (their threads would keep the launcher's process alive)."""
        try:
            for name in getattr(self, "order", []):
                c = self.children.get(name)
                if c is None:
                    continue
                c.restart_at = None  # a restart still pending when the run ends does not happen
                if c.proc.poll() is None:
                    if self.hurry:
                        self.kill_all()
                    elif self._silent(c):
                        # stopped or hung: resumed, it would send what it held before going silent (stale
                        # samples, sequence gaps: losses the stop invented); it has nothing left to finish
                        self.say(f"  killing {name} (pid {c.proc.pid}): silent, it cannot stop by itself")
                        c.proc.kill()
                    else:
                        if name == "logger":  # the loop has stopped: the recorder drains at full priority
                            self._await_remote_leaving()
                            _renice(c.proc.pid, 0)  # (raising it back needs root or CAP_SYS_NICE; else as it was)
                        c.proc.send_signal(signal.SIGINT)
                        c.proc.send_signal(signal.SIGCONT)  # a stopped (suspended) service must handle it too
                    try:
                        c.proc.wait(timeout=300 if name == "logger" else 15)
                    except subprocess.TimeoutExpired:
                        self.say(f"warning: {name} did not stop within the grace period; killing it")
                        c.proc.kill()
                        c.proc.wait()
        finally:
            for s in getattr(self, "_subs", []):
                s.undeclare()
            if hasattr(self, "session"):
                self.session.close()
            if self._router is not None:
                self._router.close()
                runs.remove_pointer(self._pointer)

    def _await_remote_leaving(self, timeout: float = REMOTE_LEAVE_TIMEOUT) -> None:
        """Several hosts: the recorder here stops once the other hosts' services have left (bounded), so
        that what they sent last (their final health, counted in what they published) reaches it: one
        host's recorder stopped first once, and a run that had lost nothing ended FAILED. Not when this host
        was interrupted: the others may go on."""
        if self.outcome.interrupted:
            return
        end = time.monotonic() + timeout
        waited = False
        last_poll = time.monotonic()
        while time.monotonic() < end and not self.hurry:
            with self.lock:
                up = [s for s, on in self.remote.items() if on]
            if not up:
                break
            waited = True
            if time.monotonic() - last_poll > 1.0:  # a departure event can be lost (_poll_remote)
                last_poll = time.monotonic()
                self._poll_remote()
            time.sleep(0.05)
        if waited:
            time.sleep(0.2)  # a sample put just before a token went may reach the recorder after the token's news

    def _silent(self, c: Child) -> bool:
        """A service physics waited for in vain (the run stalled on it), or whose process is stopped (SIGSTOP)."""
        with self.lock:
            named = set(self.follower.stalled_for) & set(fleet.members(self.sc, c.name))
        if named:
            return True
        try:  # /proc/<pid>/stat: "pid (name) STATE …"; T: stopped by a signal, t: by a debugger
            return Path(f"/proc/{c.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("T", "t")
        except (OSError, IndexError):
            return False

    def interrupt(self, signum: int) -> None:
        """A stop signal (``hilsim up``'s watcher thread calls this, never a signal handler): the
        first one ends the run, its services told to stop as at its end; another one kills every
        service still running (SIGKILL), so a second Ctrl-C means faster, never a hang."""
        name = signal.Signals(signum).name
        if not self.outcome.interrupted:
            self.outcome.signal = signum
            self.outcome.interrupted = True
            again = "Ctrl-C" if signum == signal.SIGINT else name
            self.say(f"interrupted ({name}): stopping services… ({again} again to kill them at once)")
            self.changed.set()
        else:
            self.say(f"interrupted again ({name}): killing every service")
            self.hurry = True
            self.kill_all()

    def kill_all(self) -> None:
        """SIGKILL every service still running (recorded in the outcome)."""
        for c in list(self.children.values()):
            if c.proc.poll() is None:
                c.proc.kill()
                if c.name not in self.outcome.killed:
                    self.outcome.killed.append(c.name)


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


def _stop_signals(on_signal: Callable[[int], None]) -> Callable[[], None]:
    """Take SIGINT and SIGTERM, however often they come, by calling ``on_signal(signum)`` from a
    watcher thread (:func:`hilsim.core.service.watch_signals`); returns what puts the previous
    handlers back."""
    return watch_signals(on_signal, (signal.SIGINT, signal.SIGTERM))


def _interactive_hint(la: Launcher, example: list[float] | None) -> str:
    """What ``hilsim up --interactive`` says once ready: how to stop, and a goal to try."""
    sc = la.sc
    robot = fleet.robot_names(sc)[0] if sc.robots > 1 else sc.robot
    connect = "" if la.router_ep == runs.DEFAULT_CONNECT else f" --connect {la.router_ep}"
    if "planner" in sc.services:
        joints = " ".join(f"{v:g}" for v in example) if example else "J1 …"
        try_ = f"hilsim goal {robot} --joints {joints}{connect}"
    elif "navigator" in sc.services:
        xy = " ".join(f"{v:g}" for v in example[:2]) if example else "X Y"
        try_ = f"hilsim goal {robot} --xy {xy}{connect}"
    else:
        try_ = f"geometry_msgs/Twist on {Keys.of(sc, robot).topic_name('cmd_vel')}"
    return f"interactive: Ctrl-C to stop; try {try_}"


def say_viewer(la: Launcher, timeout: float = 60.0) -> None:
    """``--view``: the live viewer's address on a line of its own, once the recorder's viewer listens;
    ``--foxglove``: the Foxglove server's."""
    from hilsim.record.foxglove_live import read_info
    from hilsim.record.live import wait_live

    logger = la.children.get("logger")
    if la.sc.logger.foxglove.enabled:  # started in the recorder's setup, before it announced itself
        fox = read_info(la.run_dir)
        la.say(f"foxglove: {fox['url']}" if fox else f"foxglove: none (see {la.run_dir / 'logger.log'})")
    if not la.sc.logger.live.enabled:
        return
    info = wait_live(la.run_dir, timeout, lambda: logger is None or logger.proc.poll() is None)
    if info is None:
        la.say(f"viewer: none (see {la.run_dir / 'logger.log'})")
    else:
        la.say(f"viewer: {info['viewer']}")


def up_overrides(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, str]]:
    """The scenario fields ``hilsim up``'s options set (``--set`` and the rest), and where each came from.
    ``--interactive`` runs at wall-clock pace (realtime): a person sends goals at their pace, and sim time
    must not race ahead of them (nor a lockstep run's recording fill the disk faster than the run goes);
    ``--clock lockstep`` (or ``--set clock.mode=lockstep``) asks for lockstep all the same."""
    from hilsim.core.scenario import parse_overrides

    overrides = parse_overrides(args.set)
    origins: dict[str, str] = {}  # where an override came from, for its errors
    if args.clock:
        overrides["clock.mode"], origins["clock.mode"] = args.clock, f"--clock {args.clock}"
    elif getattr(args, "interactive", False) and "clock.mode" not in overrides:
        overrides["clock.mode"], origins["clock.mode"] = "realtime", "--interactive (realtime unless --clock lockstep)"
    if args.duration is not None:
        overrides["duration"], origins["duration"] = args.duration, f"--duration {args.duration:g}"
    if args.seed is not None:
        overrides["seed"], origins["seed"] = args.seed, f"--seed {args.seed}"
    if getattr(args, "allow_loss", False):
        overrides["logger.max_loss"], origins["logger.max_loss"] = 1.0, "--allow-loss"
    if getattr(args, "wait", None) is not None:  # physics waits as long as the launcher does
        overrides["clock.start_timeout"], origins["clock.start_timeout"] = args.wait, f"--wait {args.wait:g}"
    if getattr(args, "view", False) or getattr(args, "view_host", None):  # the recorder's live stream
        overrides["logger.live.enabled"], origins["logger.live.enabled"] = True, "--view"
        if getattr(args, "view_host", None):
            overrides["logger.live.host"], origins["logger.live.host"] = args.view_host, f"--view-host {args.view_host}"
    fox = getattr(args, "foxglove", None)
    if fox is not None:  # the recorder's samples on a Foxglove WebSocket server
        overrides["logger.foxglove.enabled"], origins["logger.foxglove.enabled"] = True, "--foxglove"
        overrides["logger.foxglove.port"], origins["logger.foxglove.port"] = fox, f"--foxglove {fox}"
    if args.compose:
        overrides["compose"] = [[n.strip() for n in g.split(",") if n.strip()] for g in args.compose]
        origins["compose"] = " ".join(f"--compose {g}" for g in args.compose)
    return overrides, origins


# --interactive: a run left up records all the time (an arm run some 1 MB/s to the .rrd); its files are
# bounded unless the scenario or --set says otherwise: the .rrd and the bag split at this size
INTERACTIVE_FILE_BYTES = 500 * 1000**2


def bound_interactive(sc: Any) -> None:
    """``hilsim up --interactive``: ``logger.max_rrd_size`` and ``max_bag_size`` at
    :data:`INTERACTIVE_FILE_BYTES` where the scenario (or ``--set``) leaves them unset."""
    for name in ("max_rrd_size", "max_bag_size"):
        if name not in sc.logger.model_fields_set:
            setattr(sc.logger, name, INTERACTIVE_FILE_BYTES)


def cmd_up(args: argparse.Namespace) -> int:
    """``hilsim up``: its exit code is the summary's (:mod:`hilsim.run.summary`): 0 every target
    reached, 1 failed, 3 stopped by ``--duration`` before its task ended, 128 + N interrupted by
    signal N (Ctrl-C: 130, SIGTERM: 143); a second stop signal kills the services at once."""
    from hilsim.core.config import ConfigError

    overrides, origins = up_overrides(args)
    interactive = getattr(args, "interactive", False)
    if interactive and args.duration is not None:
        raise ConfigError("--interactive: the run stays up until Ctrl-C; drop --duration")
    only = [n.strip() for n in args.only.split(",") if n.strip()] if getattr(args, "only", None) else None
    if only and "zenoh.mode" not in overrides and not os.environ.get("HILSIM_ZENOH_MODE"):
        # several hosts: every process a client of the router. Peers listen on loopback, and
        # Zenoh (1.10) did not route between peers of two hosts through the router for them
        overrides["zenoh.mode"] = "client"
    scenario = world_scenario(args.scenario, args.world) if getattr(args, "world", None) else args.scenario
    sc = load_scenario(scenario, overrides, overlays=args.hil, origins=origins)
    example = None
    if interactive:  # no task (every robot's), no duration: up until Ctrl-C, for goals and tools
        bound_interactive(sc)
        example = sc.task.targets[0] if sc.task.targets else None
        sc.task.targets = []
        sc.duration = None
        for over in sc.robot_overrides.values():
            over.pop("task.targets", None)
            if isinstance(over.get("task"), dict):
                over["task"].pop("targets", None)
    if args.no_logger:
        sc.services = [s for s in sc.services if s != "logger"]
    run_dir = Path(args.out) if args.out else default_run_dir(sc)
    held = [n for n in ("recording.rrd", "bag") if "logger" in sc.services and (run_dir / n).exists()]
    if held:  # a recorder restarted within a run adds to them: a second run would be counted with the first
        raise ConfigError(f"--out {run_dir}: already holds a run's recording ({', '.join(held)}); "
                          "give a new directory or remove it")
    if sc.zenoh.tls is not None and not args.router:
        raise ConfigError("zenoh.tls is set: start the router with `hilsim router --config FILE` and pass its "
                          "tls/ endpoint with --router (docs/security.md)")
    if args.router and sc.zenoh.tls is None and sc.zenoh.auth is None:
        # the router of another run of this user (its credentials, as a tool finds them), or one without
        sc.zenoh.auth = runs.find_credentials([args.router])
    la = Launcher(sc, run_dir, router=args.router, only=only)
    here = f" ({', '.join(la.local)} here, the rest from other hosts)" if only else ""
    print(f"hilsim up {sc.name}: {len(sc.processes())} services{here}, clock {sc.clock.mode}, seed {sc.seed}, "
          f"run dir {run_dir}", flush=True)
    restore = _stop_signals(la.interrupt)  # from here on, no signal raises in this thread
    try:
        try:
            la.start()
            if la.wait_ready(sc.clock.start_timeout):
                if (sc.logger.live.enabled or sc.logger.foxglove.enabled) and any(
                        "logger" in u.split("+") for u in la.local):
                    threading.Thread(target=say_viewer, args=(la,), name="viewer", daemon=True).start()
                if interactive:
                    la.say(_interactive_hint(la, example))  # the viewer thread says its lines too
                elif not sc.task.targets and sc.duration is None:
                    robot = fleet.robot_names(sc)[0] if sc.robots > 1 else sc.robot  # robots > 1: e.g. arm0
                    how = (f"send goals with `hilsim goal {robot} --joints …`" if "planner" in sc.services
                           else f"send goals with `hilsim goal {robot} --xy X Y`" if "navigator" in sc.services
                           else f"drive it with geometry_msgs/Twist on {Keys.of(sc, robot).topic_name('cmd_vel')}")
                    la.say(f"no task targets and no --duration: running until Ctrl-C ({how})")
                la.follow()
        finally:
            la.stop()
        return summarise(la)
    finally:
        restore()
