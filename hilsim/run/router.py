"""The Zenoh router of a run: ``hilsim up``'s embedded one, and ``hilsim router`` (a standalone one).

``hilsim up`` opens its router in its own process (:func:`open_default_router`) on the well-known
loopback port when it is free, so ``hilsim topic`` finds it; every service of the run connects to it.
``hilsim router`` is one for several hosts (docs/deployment.md), optionally from a Zenoh config file
(listen endpoints, TLS, access control: docs/security.md).

Reads and writes no key: a router only routes (every key of the runs that connect to it).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

import zenoh

from hilsim.core import transport


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
