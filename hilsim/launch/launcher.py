"""``hilsim up``'s supervisor: start a scenario's services as separate processes, follow, restart, stop.

This module supervises the processes (the :class:`Launcher`: start, readiness, liveliness, restarts,
stop). The command around it (options, the run's directory, signals) is :mod:`hilsim.launch.up`; starting
one process and its log :mod:`hilsim.launch.processes`; their scheduling classes :mod:`hilsim.launch.priorities`;
which units start here and in what order :mod:`hilsim.launch.units`; the services of other hosts
:mod:`hilsim.launch.remote`; following what the services report :mod:`hilsim.launch.follow`, the summary
printed at the end :mod:`hilsim.launch.summary`, the embedded router :mod:`hilsim.launch.router`.

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
other hosts are expected. Through its :class:`~hilsim.launch.follow.Follower`: the ROS 2 graph,
``task/result``, ``planner/result``, ``navigator/result``, ``health/*``, ``log/*``. Writes no key.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Collection
from pathlib import Path

import zenoh

from hilsim.core import fleet, run_finder, transport
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.restart import STATE_DIR
from hilsim.core.scenario import write_scenario
from hilsim.launch.follow import Follower, Outcome, Restart
from hilsim.launch.priorities import prioritise_ready, raise_router_priority, renice
from hilsim.launch.processes import Child, spawn
from hilsim.launch.processes import tail as tail_of
from hilsim.launch.remote import REMOTE_GRACE_S, RemoteHosts
from hilsim.launch.router import cmd_router, identity_file, open_default_router, open_run_router
from hilsim.launch.summary import summarise
from hilsim.launch.units import local_units, stop_order
from hilsim.launch.worlds import world_scenario

# the names other modules import from here, wherever they are defined
__all__ = ["Child", "Launcher", "Outcome", "Restart", "cmd_router", "local_units", "open_default_router", "stop_order",
           "summarise", "world_scenario"]

RESTART_READY_TIMEOUT = 120.0  # wall seconds a restarted service has to announce itself


class Launcher(RemoteHosts):
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
        self._pointer: Path | None = None  # the pointer file to this run's router (run_finder.write_pointer)
        self.children: dict[str, Child] = {}
        self.held: list[str] = []  # units start() held back until release()
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
    def start(self, hold: Collection[str] = ()) -> None:
        """Start the run's router (unless given) and this host's processes, except those of ``hold`` (started
        by :meth:`release`)."""
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
                raise_router_priority(self.say)
        else:
            ptr = run_finder.run_at([self.router_ep])
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
        self.held = [n for n in reversed(self.order) if n in hold]
        for name in reversed(self.order):
            if name not in self.held:
                self.children[name] = Child(name, self._spawn(name, 0), self.run_dir / f"{name}.log")

    def release(self) -> None:
        """Start the processes :meth:`start` held back."""
        held, self.held = self.held, []
        for name in held:
            self.children[name] = Child(name, self._spawn(name, 0), self.run_dir / f"{name}.log")

    def _spawn(self, name: str, attempt: int) -> subprocess.Popen[bytes]:
        """Start ``hilsim run NAME`` with its own identity (:func:`hilsim.launch.processes.spawn`)."""
        return spawn(name, attempt, self.run_dir, self.cfg_path, self.identities.get(name, self.sc.zenoh.auth))

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
                prioritise_ready(name, c.proc.pid, self.sc.clock.mode == "realtime", self._router is not None)
                if c.restarts:
                    back = time.monotonic() - c.died_at
                    r = next((r for r in reversed(self.outcome.restarts) if r.name == name), None)
                    if r is not None:
                        r.back_after = back
                    self.say(f"  {name} is back (pid {c.proc.pid}), {back:.1f} s after it died")
        self.changed.set()

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
            tail = tail_of(c.log_path)
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
                            renice(c.proc.pid, 0)  # (raising it back needs root or CAP_SYS_NICE; else as it was)
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
                run_finder.remove_pointer(self._pointer)

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
