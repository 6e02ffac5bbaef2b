"""The Zenoh router of a run: ``hilsim up``'s embedded one, and ``hilsim router`` (a standalone one).

``hilsim up`` opens its router in its own process (:func:`open_default_router`) on the well-known
loopback port when it is free, so ``hilsim topic`` finds it; every service of the run connects to it.
``hilsim router`` is one for several hosts (docs/deployment.md), optionally from a Zenoh config file
(listen endpoints, TLS, access control: docs/security.md).

Reads and writes no key: a router only routes (every key of the runs that connect to it).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import secrets
import sys
import threading
from pathlib import Path
from typing import NamedTuple

import zenoh

from hilsim.core import transport
from hilsim.core.transport import Credentials, RouterUsers


def open_default_router(users: RouterUsers | None = None) -> tuple[str, zenoh.Session]:
    """The well-known loopback port if free (so `hilsim topic` finds it), else any free port;
    ``users``: only they may connect (:func:`transport.open_router`)."""
    ep = f"tcp/127.0.0.1:{transport.DEFAULT_ROUTER_PORT}"
    try:
        return ep, transport.open_router(ep, users)
    except ConnectionError:
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        print(f"note: port {transport.DEFAULT_ROUTER_PORT} is taken (another simulation?); using {ep} "
              f"(pass --connect {ep} to hilsim topic)", flush=True)
        return ep, transport.open_router(ep, users)


class RunRouter(NamedTuple):
    """``hilsim up``'s router and what its processes need to join it."""

    endpoint: str
    session: zenoh.Session
    client_config: Path  # <run dir>/zenoh-client.json5: the run's user (0600)
    guest_config: Path | None  # <run dir>/zenoh-guest.json5: the read-only guest (zenoh.guests: read)
    pointer: Path | None  # where this user's tools find client_config (transport.pointer_path)


def open_run_router(run_dir: Path, guests: str = "none") -> RunRouter:
    """The router of one run, on loopback, that only the run's own processes may join: a user and
    password made for this run (Zenoh's usrpwd authentication, access control by username), written
    to ``run_dir`` with mode 0600 as the router's dictionary and a client config file; with ``guests:
    read`` also a guest user that may only read, its config file readable by anyone. The pointer file
    (:func:`transport.write_pointer`) lets this user's tools find the credentials by port."""
    run_dir.mkdir(parents=True, exist_ok=True)
    user, password = f"run-{secrets.token_hex(6)}", secrets.token_urlsafe(24)
    guest = (f"guest-{secrets.token_hex(6)}", secrets.token_urlsafe(24)) if guests == "read" else None
    users = (run_dir / transport.USERS_FILE).resolve()
    transport.write_private(users, "".join(f"{u}:{p}\n" for u, p in [(user, password), *([guest] if guest else [])]))
    ep, session = open_default_router(RouterUsers(users, user, guest[0] if guest else None))
    client = (run_dir / transport.CLIENT_CONFIG).resolve()
    transport.write_private(client, transport.client_config_text(ep, Credentials(user, password)))
    guest_config = None
    if guest is not None:  # meant to be handed out: readable by anyone who can reach the run directory
        guest_config = (run_dir / transport.GUEST_CONFIG).resolve()
        transport.write_private(guest_config, transport.client_config_text(ep, Credentials(*guest)), 0o644)
    return RunRouter(ep, session, client, guest_config, transport.write_pointer(ep, run_dir, client))


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
    if not args.config and not _loopback(where):
        print(f"warning: {where} is reachable from other machines, with no authentication and no access control: "
              "anyone who reaches it can read every key and command the robot; use --config with TLS "
              "(docs/security.md)", file=sys.stderr, flush=True)
    print(f"zenoh router listening on {where} (Ctrl-C to stop)", flush=True)
    from hilsim.core.service import on_stop_signals

    stop = threading.Event()
    on_stop_signals(stop.set)  # Ctrl-C or SIGTERM: not stop.set in a signal handler (see there)
    stop.wait()
    r.close()
    return 0


def _loopback(endpoint: str) -> bool:
    """Whether a listen endpoint is on loopback only (``tcp/127.0.0.1:7447``, ``tcp/[::1]:7447``, ``localhost``)."""
    host = endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
