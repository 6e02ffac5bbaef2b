"""The Zenoh router of a run: ``hilsim up``'s embedded one, and ``hilsim router`` (a standalone one).

``hilsim up`` opens its router in its own process (:func:`open_run_router`) on the well-known
loopback port when it is free; every process of the run connects to it with an identity of its own,
whose rights the access control derives from the key table (:mod:`hilsim.core.rights`), and this user's
tools find theirs through a pointer file.
``hilsim router`` is one for several hosts (docs/deployment.md), optionally from a Zenoh config file
(listen endpoints, TLS, access control: docs/security.md).

Reads and writes no key: a router only routes (every key of the runs that connect to it).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import re
import secrets
import sys
import threading
from pathlib import Path
from typing import NamedTuple

import zenoh

from hilsim.core import run_finder, transport
from hilsim.core.config import Scenario
from hilsim.core.rights import (
    EVERY,
    Rights,
    access_control,
    grant_rights,
    panel_rights,
    play_rights,
    tools_rights,
    unit_rights,
)
from hilsim.core.transport import Credentials, RouterUsers
from hilsim.launch import creds


def open_default_router(users: RouterUsers | None = None) -> tuple[str, zenoh.Session]:
    """The well-known loopback port if free (so `hilsim topic` finds it), else any free port;
    ``users``: only they may connect (:func:`transport.open_router`)."""
    ep = f"tcp/127.0.0.1:{transport.DEFAULT_ROUTER_PORT}"
    try:
        return ep, transport.open_router(ep, users)
    except ConnectionError:
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        print(f"note: port {transport.DEFAULT_ROUTER_PORT} is taken (another simulation?); using {ep} "
              f"(pass --connect {ep} to hilsim topic)", file=sys.stderr, flush=True)
        return ep, transport.open_router(ep, users)


class RunRouter(NamedTuple):
    """``hilsim up``'s router and what its processes need to join it."""

    endpoint: str
    session: zenoh.Session
    client_config: Path  # <run dir>/zenoh-client.json5: the tools' identity (0600), for tools and ROS 2 nodes
    guest_config: Path | None  # <run dir>/zenoh-guest.json5: the read-only guest (zenoh.guests: read)
    pointer: Path | None  # where this user's tools find client_config (run_finder.pointer_path)
    identities: dict[str, Path]  # launch unit -> its identity's client config (<run dir>/identities/, 0600)
    launcher_config: Path  # the launcher's own identity: it reads, and writes nothing


# the tools with an identity of their own in a run (<run dir>/identities/<name>.json5; run_finder.tool_target)
PLAY, PANEL = run_finder.TOOL_IDENTITIES["hilsim play"], run_finder.TOOL_IDENTITIES["hilsim ui"]


def identity_file(run_dir: Path, unit: str) -> Path:
    """Where the identity of launch unit ``unit`` (``physics``, ``controller@*``, ``a+b+c``) is written."""
    return (run_dir / transport.IDENTITIES_DIR / f"{_safe(unit)}.json5").resolve()


def _safe(unit: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", unit.replace("@*", "@all")).replace("@", "_at_")


def open_run_router(run_dir: Path, sc: Scenario, *, per_service: bool = True) -> RunRouter:
    """The router of one run, on loopback, that only the run's own processes may join, each with the
    rights of its identity (Zenoh's usrpwd authentication, access control by username,
    :mod:`hilsim.core.rights`): a user and password for every launch unit of the scenario (written to
    ``<run dir>/identities/<unit>.json5``), one for the launcher (it only reads), one for the tools and
    the ROS 2 nodes a person points at the run (``zenoh-client.json5``), and with ``zenoh.guests: read``
    a guest that may only read (its file readable by anyone). Every file but the guest's is mode 0600,
    and so is the router's dictionary. The pointer file (:func:`run_finder.write_pointer`) lets this
    user's tools find theirs by port.

    ``per_service`` False (``hilsim bench loop``'s baseline only): every process with the tools' file,
    which may then do everything, as before identities of their own."""
    run_dir.mkdir(parents=True, exist_ok=True)
    ids = run_dir / transport.IDENTITIES_DIR
    ids.mkdir(mode=0o700, exist_ok=True)
    units = sc.launch_units()
    cred: dict[str, Credentials] = {}  # identity -> user and password
    rights: dict[str, Rights | None] = {}  # username -> what it may do (None: read only)

    def user(name: str, r: Rights | None) -> Credentials:
        c = Credentials(f"{_safe(name)}-{secrets.token_hex(4)}", secrets.token_urlsafe(24))
        cred[name], rights[c.user] = c, r
        return c

    if per_service:
        for u in units:
            user(u, unit_rights(sc, u))
        user("launcher", None)
        user("tools", tools_rights(sc))
        # hilsim play and the panel: each its own, with only what it does (run_finder.tool_target hands them out)
        user(PLAY, play_rights(sc))
        user(PANEL, panel_rights(sc))
        # the lab's own (hilsim creds add): their fixed user and password, only what each was given
        for g in creds.load_all():
            cred[f"lab:{g.name}"], rights[g.user] = g.credentials, grant_rights(sc, list(g.may_write),
                                                                                 list(g.may_ask))
    else:  # one identity for every process, with every right: the baseline of `hilsim bench loop`
        user("tools", Rights(put={*EVERY}, serve={*EVERY}, ask={*EVERY}, tokens={*EVERY}))
    if sc.zenoh.guests == "read":
        user("guest", None)
    users = (run_dir / transport.USERS_FILE).resolve()
    transport.write_private(users, "".join(f"{c.user}:{c.password}\n" for c in cred.values()))
    ep, session = open_default_router(RouterUsers(users, access_control(rights)))

    def config(name: str, path: Path, mode: int = 0o600) -> Path:
        transport.write_private(path, transport.client_config_text(ep, cred[name]), mode)
        return path

    client = config("tools", (run_dir / transport.CLIENT_CONFIG).resolve())
    identities = {u: config(u, identity_file(run_dir, u)) if per_service else client for u in units}
    launcher = config("launcher", identity_file(run_dir, "launcher")) if per_service else client
    if per_service:
        for name in (PLAY, PANEL):
            config(name, identity_file(run_dir, name))
    guest_config = None
    if "guest" in cred:  # meant to be handed out: readable by anyone who can reach the run directory
        guest_config = config("guest", (run_dir / transport.GUEST_CONFIG).resolve(), 0o644)
    pointer = run_finder.write_pointer(ep, run_dir, client, scenario=sc.name)
    return RunRouter(ep, session, client, guest_config, pointer, identities, launcher)


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
            where = args.listen or run_finder.DEFAULT_CONNECT
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
