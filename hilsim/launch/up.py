"""``hilsim up``'s command: its options as scenario overrides, the run started, followed, stopped, summarised.

:func:`cmd_up` loads the scenario with the options of ``hilsim up`` (:func:`up_overrides`), makes an
``--interactive`` run endless with bounded files (:func:`bound_interactive`), runs it with a
:class:`~hilsim.launch.launcher.Launcher` (stop signals taken by a watcher thread, never raised in the main
thread, so stopping and the summary always finish), says what a person can do once it is ready
(:func:`say_viewer`, the interactive hint) and returns the summary's exit code
(:mod:`hilsim.launch.summary`). Reads and writes no key itself (the launcher does the following).
"""

from __future__ import annotations

import argparse
import os
import signal
import threading
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from hilsim.core import fleet, run_finder
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.core.service import watch_signals
from hilsim.launch.launcher import Launcher
from hilsim.launch.processes import stop_with_parent
from hilsim.launch.summary import summarise
from hilsim.launch.worlds import world_scenario


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
    connect = "" if la.router_ep == run_finder.DEFAULT_CONNECT else f" --connect {la.router_ep}"
    if "planner" in sc.services:
        joints = " ".join(f"{v:g}" for v in example) if example else "J1 …"
        try_ = f"hilsim goal {robot} --joints {joints}{connect}"
    elif "navigator" in sc.services:
        xy = " ".join(f"{v:g}" for v in example[:2]) if example else "X Y"
        try_ = f"hilsim goal {robot} --xy {xy}{connect}"
    else:
        try_ = f"geometry_msgs/Twist on {Keys.of(sc, robot).topic_name('cmd_vel')}"
    return f"interactive: Ctrl-C to stop; try {try_}"


VIEW_WAIT_S = 120.0  # hilsim up --view with a task: how long the run waits for a viewer before it starts


def _unit_of(la: Launcher, service: str) -> str | None:
    """This host's process (launch unit) that runs ``service``, if any."""
    return next((u for u in la.local if service in u.split("+")), None)


def viewer_gate(la: Launcher) -> list[str]:
    """``logger.live.wait``: the units to hold back until a viewer joins (the one running physics: nothing
    moves before), or none (no wait asked for, no task, or physics not here or in the recorder's process)."""
    sc = la.sc
    if not (sc.logger.live.enabled and sc.logger.live.wait > 0 and sc.task.targets):
        return []
    physics, logger = _unit_of(la, "physics"), _unit_of(la, "logger")
    return [physics] if physics is not None and logger is not None and physics != logger else []


def wait_for_viewer(la: Launcher) -> None:
    """Before the held units start: until a viewer joined the live stream, at most ``logger.live.wait`` s."""
    from hilsim.record.live_viewer import wait_live

    wait = la.sc.logger.live.wait
    logger = la.children.get(_unit_of(la, "logger") or "")
    la.say(f"waiting for a viewer: the run starts once the page is open and its viewer connected (at most "
           f"{wait:g} s; --view-wait 0 starts at once)")

    def alive() -> bool:
        return logger is not None and logger.proc.poll() is None and not la.outcome.interrupted

    if wait_live(la.run_dir, wait, alive, watched=True) is not None:
        la.say("a viewer joined: starting")
    elif alive():
        la.say(f"no viewer joined in {wait:g} s: starting without one")


def say_viewer(la: Launcher, timeout: float = 60.0) -> None:
    """``--view``: the live viewer's address on a line of its own, once the recorder's viewer listens;
    ``--foxglove``: the Foxglove server's."""
    from hilsim.record.foxglove_live import read_info
    from hilsim.record.live_viewer import wait_live

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
        # a run with a task starts once someone watches it, who then sees all of it (streamed from when a viewer
        # joins); not an interactive one, which waits for goals anyway, nor the panel's (hilsim.ui.run_control)
        wait = getattr(args, "view_wait", None)
        if wait is not None:
            overrides["logger.live.wait"], origins["logger.live.wait"] = wait, f"--view-wait {wait:g}"
        elif "logger.live.wait" not in overrides and not getattr(args, "interactive", False):
            overrides["logger.live.wait"], origins["logger.live.wait"] = VIEW_WAIT_S, "--view"
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
    """``hilsim up``: its exit code is the summary's (:mod:`hilsim.launch.summary`): 0 every target
    reached, 1 failed, 3 stopped by ``--duration`` before its task ended, 128 + N interrupted by
    signal N (Ctrl-C: 130, SIGTERM: 143); a second stop signal kills the services at once."""
    from hilsim.core.config import ConfigError

    stop_with_parent()
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
        sc.zenoh.auth = run_finder.find_credentials([args.router])
    la = Launcher(sc, run_dir, router=args.router, only=only)
    here = f" ({', '.join(la.local)} here, the rest from other hosts)" if only else ""
    print(f"hilsim up {sc.name}: {len(sc.processes())} services{here}, clock {sc.clock.mode}, seed {sc.seed}, "
          f"run dir {run_dir}", flush=True)
    restore = _stop_signals(la.interrupt)  # from here on, no signal raises in this thread
    try:
        try:
            gate = viewer_gate(la)
            la.start(hold=gate)
            ready = la.wait_ready(sc.clock.start_timeout)
            if ready and gate:  # the viewer's address, then physics once a viewer joined
                say_viewer(la)
                wait_for_viewer(la)
                ready = not la.outcome.interrupted and not la.check_children()
                if ready:
                    la.release()
                    ready = la.wait_ready(sc.clock.start_timeout)
            if ready:
                if not gate and (sc.logger.live.enabled or sc.logger.foxglove.enabled) and _unit_of(
                        la, "logger") is not None:
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
