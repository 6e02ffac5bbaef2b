"""Run control: the panel's one run at a time, a child ``hilsim up`` process (:class:`RunManager`:
its own process group, SIGTERM from the kernel if the panel dies, stopped with SIGTERM then waited
for, SIGKILL after a grace), and starting and stopping it from the page (:class:`RunControl`: the
request checked against ``config/``, one simulation per prefix, the run's own verdicts made faults).

Zenoh keys: none of its own. The run is started with ``--router`` on the panel's endpoint (so its
services join the panel's network); a second simulation is refused while the watcher
(:mod:`hilsim.ui.watch`) sees services alive (``alive/*``) on the prefix, and a service of the
running run whose ``alive/<service>`` token disappears is made a fault there, unless it left because
the run ended (its last health ``stopped`` or ``done``, or the launcher's report of the end).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hilsim.core.config import ConfigError, Scenario
from hilsim.core.scenario import load_scenario, parse_overrides
from hilsim.core.threads import sigterm_when_parent_dies
from hilsim.ui.jsonio import BadInput
from hilsim.ui.options import ScenarioOption, option_of
from hilsim.ui.watch import Monitor

log = logging.getLogger("hilsim.ui")

STOP_GRACE = 60.0  # wall seconds a run has to stop after SIGTERM (the recorder drains) before SIGKILL


def child_setup() -> None:
    """In the ``hilsim up`` child: its own process group (the panel's Ctrl-C is not its), and
    SIGTERM from the kernel when the panel's thread that started it dies."""
    os.setpgrp()
    sigterm_when_parent_dies()


@dataclass
class RunRequest:
    scenario: str
    world: str = ""
    planner: str = ""
    clock: str = "realtime"
    mode: str = "interactive"  # interactive: no task, runs until stopped; task: the scenario's targets
    extra: list[str] = field(default_factory=list)  # further `hilsim up` arguments (hilsim up --ui)
    out: str = ""  # the run directory (default runs/<stamp>-ui)


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
            if "logger" in sc.services and "--view" not in req.extra:
                # the robot, live, in the panel's page: streamed once the page shows it (a run nobody looks at
                # costs nothing); not `--view`, whose task would wait for a viewer
                argv += ["--set", "logger.live.enabled=true"]
            argv += req.extra
            env = {**os.environ, "PYTHONUNBUFFERED": "1"}
            self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                         stdin=subprocess.DEVNULL, env=env, preexec_fn=child_setup)
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


def _sets(extra: list[str]) -> list[str]:
    """The ``--set`` values among extra ``hilsim up`` arguments (validated before the run starts)."""
    return [extra[i + 1] for i, a in enumerate(extra[:-1]) if a == "--set"]


class RunControl:
    """Starting and stopping the panel's run from the page (``POST /api/run``, ``POST /api/stop``,
    ``hilsim up … --ui``), and what the run itself says of its services (faults in the watcher)."""

    def __init__(self, monitor: Monitor, options: dict[str, ScenarioOption], planners: list[str], router: str,
                 runs_dir: Path, closing: threading.Event, *, before_start: Any = None) -> None:
        self.monitor = monitor
        self.before_start = before_start  # called (no argument) before a run starts: the router is there
        self.echo = False  # print what the run prints (hilsim up --ui: its progress beside the panel's URL)
        self.options = options
        self.planners = planners
        self.closing = closing
        self.run = RunManager(router, runs_dir)
        self.run.on_end = self._run_ended
        self.run.on_line = self._run_said
        self.current: ScenarioOption | None = None  # the scenario of the panel's run

    def _run_said(self, line: str) -> None:
        """The launcher's own verdicts: a dead service, a stall (``error: …``) is a fault; once the
        run is ending, services leave because they are stopped, not because they died."""
        if self.echo:
            print(line, flush=True)
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
        from hilsim.launch.launcher import world_scenario

        if self.run.busy():
            raise BadInput("run", f"a run is already {self.run.state} ({self.run.info.get('scenario')}): "
                           "stop it first", 409)
        with self.monitor.lock:  # two simulations on the same keys would mix: one at a time here too
            elsewhere = {r: sorted(s for s, up in rv.alive.items() if up) for r, rv in self.monitor.robots.items()}
        elsewhere = {r: s for r, s in elsewhere.items() if s}
        if elsewhere:
            who = "; ".join(f"robot {r}: {', '.join(s)}" for r, s in sorted(elsewhere.items()))
            raise BadInput("run", f"a simulation started elsewhere runs on this Zenoh network with prefix "
                           f"{self.monitor.prefix} ({who}): stop it first", 409)
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
        if self.before_start is not None:
            self.before_start()
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
