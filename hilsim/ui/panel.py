"""The panel: one object wiring the Zenoh session (and, without ``--connect``, the router it opens)
to the watcher (:mod:`hilsim.ui.watch`), run control (:mod:`hilsim.ui.run_control`), commands
(:mod:`hilsim.ui.commands`) and the recording viewer (:mod:`hilsim.ui.viewer`); it decides which
robot is shown and what goals are checked against, and composes the state the page is sent
(``GET /api/state``, the event stream of :mod:`hilsim.ui.events`).

Zenoh keys: none of its own; it opens the session the others use (``run_finder.open_tool_session``)
and reads the robots' liveliness (``alive/*``) from the watcher to find a run started elsewhere, whose
own scenario (joints and limits: an imported arm's too) it reads from that run's directory, found by
its pointer (:func:`hilsim.core.run_finder.run_at`).

Without ``--connect`` (``hilsim ui``), the panel finds a simulation already running on this machine
by itself: the run of this user that is up (its pointer, wherever its port; among several it asks, never
guesses: :func:`hilsim.core.run_finder.tool_target`), saying which in its first line; else, when a Zenoh
router already listens on the well-known ``tcp/127.0.0.1:7447`` (``hilsim router``), it joins that router
instead of opening one of its own; when
that router is gone by the time the panel starts a run, it opens the router there itself. With
``hilsim up … --ui`` (``attach=False``) it keeps to a router of its own, as before (7447 when free).
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import run_finder, transport
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario
from hilsim.ui.commands import Commands
from hilsim.ui.jsonio import BadInput
from hilsim.ui.options import ScenarioOption, option_of, planner_names, scenario_options
from hilsim.ui.run_control import RunControl
from hilsim.ui.viewer import Viewer
from hilsim.ui.watch import Monitor

ROUTER_WAIT_S = 3.0  # for the panel's session to reach a router it joins (or reopened)


def _has_router(session: zenoh.Session, wait: float) -> bool:
    """True once ``session`` is connected to a Zenoh router (within ``wait`` seconds)."""
    end = time.monotonic() + wait
    while True:
        if any(True for _ in session.info.routers_zid()):
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(0.05)


class Panel:
    def __init__(self, *, connect: str | None = None, prefix: str | None = None, runs_dir: Path = Path("runs"),
                 robot: str = "arm", attach: bool = True) -> None:
        self.prefix = run_finder.tool_prefix(prefix)
        self.router: zenoh.Session | None = None
        joined = None
        if connect:
            self.endpoint = connect
        else:
            joined = self._own_or_join_router(attach)
        # joining a run: the first line names it (directory, scenario, endpoint); nothing there is an error
        self.session = joined or run_finder.open_tool_session(self.endpoint, tool="hilsim ui" if connect else None)
        self.monitor = Monitor(self.session, self.prefix)
        self.options = scenario_options()
        self.planners = planner_names()
        self.closing = threading.Event()
        self.control = RunControl(self.monitor, self.options, self.planners, self.endpoint, runs_dir, self.closing,
                                  before_start=None if connect else self._router_for_a_run)
        self.run = self.control.run  # the run's process
        self.default_robot = robot
        self.commands = Commands(self.session, self.prefix, self.monitor, self.planners, self.robot, self.option)
        self.viewer = Viewer()
        # the scenario of a run started elsewhere, read from its directory: ((path, mtime), what it offers)
        self._elsewhere: tuple[tuple[str, int] | None, ScenarioOption | None] = (None, None)

    def _own_or_join_router(self, attach: bool) -> zenoh.Session | None:
        """The well-known router: opened here when its port is free; else (``attach``) joined, when a
        Zenoh router answers there (a simulation already running on this machine: the session on it
        is returned); else a router of the panel's own on a free port."""
        from hilsim.launch.launcher import open_default_router

        up = run_finder.live_runs() if attach else []
        if up:  # runs of this user are up: join one, wherever its port (asked among several, never guessed)
            run = up[0] if len(up) == 1 else run_finder.choose_run(up, "hilsim ui")
            self.endpoint = run.endpoint
            session = run_finder.open_tool_session(run.endpoint, tool="hilsim ui")
            print("hilsim ui: its simulation is shown", flush=True)
            return session
        ep = run_finder.DEFAULT_CONNECT
        try:
            self.endpoint, self.router = ep, transport.open_router(ep)
            return None
        except ConnectionError:
            pass
        if attach:
            session = run_finder.open_tool_session(ep)
            if _has_router(session, ROUTER_WAIT_S):
                self.endpoint = ep
                run = run_finder.run_at([ep])
                which = run.describe() if run is not None else f"{ep} (a hilsim up running?)"
                print(f"hilsim ui: joined {which}: its simulation is shown", flush=True)
                return session
            session.close()
        self.endpoint, self.router = open_default_router()  # says which port it took instead
        return None

    def _router_for_a_run(self) -> None:
        """Before the panel starts a run on a router it joined: if that router has gone (its ``hilsim
        up`` ended), open it here, on the same endpoint, and let the session reconnect to it."""
        if self.router is not None or _has_router(self.session, 0.0):
            return
        try:
            self.router = transport.open_router(self.endpoint)
        except ConnectionError as e:
            raise BadInput("run", f"the Zenoh router the panel joined ({self.endpoint}) is gone and its port "
                           f"cannot be taken: {e}", 503) from None
        print(f"hilsim panel: the router it had joined is gone; opened the Zenoh router on {self.endpoint}",
              file=sys.stderr, flush=True)
        if not _has_router(self.session, ROUTER_WAIT_S):
            raise BadInput("run", f"the panel did not reconnect to its router on {self.endpoint}", 503)

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
            return self.control.current
        robot = self.robot()
        with self.monitor.lock:
            rv = self.monitor.robots.get(robot)
            alive = {s for s, up in rv.alive.items() if up} if rv is not None else set()
        if not alive & {"planner", "navigator"}:
            return None
        own = self._run_option()
        if own is not None and own.robot == robot:
            return own
        same = [o for o in self.options.values() if o.robot == robot and ("navigator" in alive) == o.mobile]
        return next((o for o in same if o.name == robot), same[0] if same else None)

    def _run_option(self) -> ScenarioOption | None:
        """The scenario of the run whose router the panel is on, from that run's own directory (its pointer:
        a ``hilsim up`` of this user with its own router): an arm imported from a lab's URDF, in no scenario
        of ``config/``, is commanded with its own joints and limits. None when no pointer names a run."""
        ptr = run_finder.run_at([self.endpoint])
        if ptr is None:
            return None
        path = ptr.run_dir / "scenario.yaml"  # the run's scenario as resolved (hilsim.launch.up)
        try:
            key = (str(path), path.stat().st_mtime_ns)
        except OSError:
            return None
        if self._elsewhere[0] != key:  # read once per run (state() asks many times a second)
            try:
                opt: ScenarioOption | None = option_of(load_scenario(str(path)), ptr.scenario or path.stem)
            except (ConfigError, ValueError) as e:
                print(f"hilsim panel: {path}: {e} (the run is shown by its robot's name only)", file=sys.stderr,
                      flush=True)
                opt = None
            self._elsewhere = (key, opt)
        return self._elsewhere[1]

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
        snap["viewer"] = self.viewer.shown()
        return snap

    def open_viewer(self) -> dict[str, Any]:
        """Rerun's web viewer on the current run's recording (:class:`hilsim.ui.viewer.Viewer`)."""
        return self.viewer.open(str(self.run.info.get("recording") or ""))

    def close(self) -> None:
        self.closing.set()
        self.run.stop(wait=True)
        self.viewer.stop()
        self.commands.close()
        self.monitor.close()
        self.session.close()
        if self.router is not None:
            self.router.close()
