"""``hilsim ui``: the browser control panel (Starlette + uvicorn, plain HTML, server-sent events).

The panel is a Zenoh client like ``hilsim topic``: it watches a simulation through the keys every
tool uses, sends goals and gains through the services' own queryables, and starts one run at a
time as a child ``hilsim up`` process (its own process group; SIGTERM from the kernel if the panel
dies; stopped with SIGTERM, then waited for). Unless ``--connect`` names a router, the panel opens
the Zenoh router itself (``tcp/127.0.0.1:7447`` when free, as ``hilsim up`` would) and starts its
runs with ``--router`` on it, so it sees every run it starts and ``hilsim topic`` finds it too; when
a ``hilsim up`` already holds that port, ``hilsim ui`` joins its router and shows its run
(:class:`hilsim.ui.panel.Panel`). ``hilsim up … --ui`` prints the run's progress beside the URL.

This module builds the app and serves it (``hilsim ui``, ``hilsim up … --ui``); the parts, one
concern each, with the Zenoh keys each reads or queries in its own docstring:

- :mod:`hilsim.ui.guard`: who may command through it (a token, its own origin and host, JSON commands);
- :mod:`hilsim.ui.routes`: the HTTP interface (the Starlette app, its routes and handlers);
- :mod:`hilsim.ui.events`: the event stream (the state as server-sent events);
- :mod:`hilsim.ui.panel`: the panel object wiring the parts, and the state the page is sent;
- :mod:`hilsim.ui.watch`: the Zenoh watcher and the state it keeps of each robot;
- :mod:`hilsim.ui.run_control`: run control (the ``hilsim up`` child, starting and stopping it);
- :mod:`hilsim.ui.commands`: goals, cancels and gains to the robot's services;
- :mod:`hilsim.ui.viewer`: Rerun's web viewer on the recording;
- :mod:`hilsim.ui.options`: what can be run (the scenarios and planners of ``config/``);
- :mod:`hilsim.ui.jsonio`: refused requests (:class:`BadInput`), numbers in, finite JSON out.

Zenoh keys: none here; the session and router are opened by :class:`hilsim.ui.panel.Panel`.
"""

from __future__ import annotations

import argparse
import signal
import socket
import sys
from pathlib import Path

import zenoh

from hilsim.core import run_finder
from hilsim.ui.guard import Guard, new_token
from hilsim.ui.jsonio import BadInput
from hilsim.ui.panel import Panel
from hilsim.ui.routes import make_app
from hilsim.ui.run_control import RunRequest, shown_robot

__all__ = ["BadInput", "Panel", "RunRequest", "cmd_ui", "cmd_up_ui", "make_app", "serve", "shown_robot"]


def serve(host: str, port: int, *, connect: str | None = None, prefix: str | None = None,
          first: RunRequest | None = None, runs_dir: Path = Path("runs"), token: bool = True) -> int:
    """Run the panel until SIGINT/SIGTERM; the run it started is stopped before it exits. ``token``
    False: ``--no-token`` (:mod:`hilsim.ui.guard`: the host, origin and JSON checks stay)."""
    import uvicorn

    # uvicorn shuts down on SIGINT/SIGTERM, then raises the signal again for the handler it found:
    # with Python's defaults that would end the process before the run is stopped. Installed first,
    # so that a signal while the panel is starting also stops it in order (it then does not serve).
    stopped: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stopped.append(signum))
    secret = new_token() if token else None
    if secret is None:
        print("hilsim panel: --no-token: any process or user of this machine that reaches the port may command "
              "the robot", file=sys.stderr, flush=True)
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: the panel listens on {host}: anyone who reaches it "
              + ("and holds the token " if secret else "") + "can start runs and move the robot (plain HTTP: "
              "the token travels in clear); keep it on a trusted network", file=sys.stderr, flush=True)
    try:  # a taken port is said before anything starts (not after a run was started for nothing)
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as e:
        print(f"hilsim ui: cannot listen on {host}:{port}: {e.strerror} (choose another with --port)",
              file=sys.stderr)
        return 2
    try:
        # hilsim ui joins a simulation already running on the well-known router; hilsim up --ui runs its own
        panel = Panel(connect=connect, prefix=prefix, runs_dir=runs_dir, attach=first is None)
    except (ConnectionError, zenoh.ZError) as e:
        print(f"hilsim ui: {e}", file=sys.stderr)
        return 2
    try:
        if first is not None:
            panel.control.echo = True  # the run's progress here too, as hilsim up alone prints it
            try:
                info = panel.control.start_request(first)
            except BadInput as e:
                print(f"hilsim ui: {e}", file=sys.stderr)
                return 2
            print(f"started: {info['command']} (pid {info['pid']})", flush=True)
        query = f"?token={secret}" if secret else ""
        print(f"hilsim panel: http://{host if ':' not in host else f'[{host}]'}:{port}/{query} "
              f"(zenoh {panel.endpoint})", flush=True)
        app = Guard(make_app(panel), host=host, port=port, token=secret,
                    say=lambda line: print(line, flush=True))
        config = uvicorn.Config(app, host=host, port=port, log_level="warning", timeout_graceful_shutdown=2)
        server = uvicorn.Server(config)
        if stopped:  # asked to stop while starting
            return 0
        server.run()
        return 0 if server.started or stopped else 2
    finally:
        print("hilsim panel: stopping", flush=True)
        panel.close()


def cmd_ui(args: argparse.Namespace) -> int:
    connect = args.connect
    if getattr(args, "run", None):  # the run's router (hilsim.core.run_finder.tool_target)
        connect = ",".join(run_finder.tool_target(run=args.run, tool="hilsim ui").zenoh.connect)
    return serve(args.host, args.port, connect=connect, prefix=args.prefix, token=not args.no_token)


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
    mode = "interactive" if getattr(args, "interactive", False) else "task"
    req = RunRequest(args.scenario, args.world or "", "", args.clock or "realtime", mode, extra, args.out or "")
    return serve(args.ui_host, args.ui_port, first=req, token=not getattr(args, "ui_no_token", False))
