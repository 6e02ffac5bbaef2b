"""The panel: one object wiring the Zenoh session (and, without ``--connect``, the router it opens)
to the watcher (:mod:`hilsim.ui.watch`), run control (:mod:`hilsim.ui.runs`), commands
(:mod:`hilsim.ui.commands`) and the recording viewer (:mod:`hilsim.ui.viewer`); it decides which
robot is shown and what goals are checked against, and composes the state the page is sent
(``GET /api/state``, the event stream of :mod:`hilsim.ui.events`).

Zenoh keys: none of its own; it opens the session the others use (``transport.open_tool_session``)
and reads the robots' liveliness (``alive/*``) from the watcher to find a run started elsewhere.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import transport
from hilsim.ui.commands import Commands
from hilsim.ui.options import ScenarioOption, planner_names, scenario_options
from hilsim.ui.runs import RunControl
from hilsim.ui.viewer import Viewer
from hilsim.ui.watch import Monitor


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
        self.closing = threading.Event()
        self.control = RunControl(self.monitor, self.options, self.planners, self.endpoint, runs_dir, self.closing)
        self.run = self.control.run  # the run's process
        self.default_robot = robot
        self.commands = Commands(self.session, self.prefix, self.monitor, self.planners, self.robot, self.option)
        self.viewer = Viewer()

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
