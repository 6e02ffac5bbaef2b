"""Identities a lab hands out (``hilsim creds``): one node or tool, only the rights it was given.

As an SROS2 enclave gives one node its own key and permissions, ``hilsim creds add teleop --may-write
cmd_vel`` makes a credential for one node: a Zenoh user and password that ``hilsim up``'s router admits
with only those rights (a put elsewhere is refused at the router), and a Zenoh client config for the node
(``ZENOH_SESSION_CONFIG_URI=<dir>/teleop.json5`` for a ROS 2 node on rmw_zenoh, ``HILSIM_ZENOH_AUTH`` for
hilsim's tools). What may be given is what a person may command, by the key table
(:func:`hilsim.core.rights.grantable`): ``--may-write`` topics (``cmd_vel``, ``joint_trajectory``),
``--may-ask`` queryables (``planner/goal``, …, and ``actions`` for the services' ROS 2 actions);
``--read-only`` gives nothing but reading.

The lab's credentials live in one directory (``HILSIM_CREDS``, else ``$XDG_CONFIG_HOME/hilsim/creds``,
else ``~/.config/hilsim/creds``; mode 0700): ``<name>.json`` (the grant, with its password; 0600) and
``<name>.json5`` (the client config; 0600). Every router ``hilsim up`` opens afterwards admits them
(:func:`hilsim.launch.router.open_run_router`); a router already open does not change. Reads and writes
no key.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import sys
from dataclasses import dataclass
from pathlib import Path

from hilsim.core import transport
from hilsim.core.config import ConfigError
from hilsim.core.rights import check_grant, grantable
from hilsim.core.transport import Credentials

NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,40}")
ENV = "HILSIM_CREDS"


def creds_dir() -> Path:
    if v := os.environ.get(ENV, "").strip():
        return Path(v)
    base = os.environ.get("XDG_CONFIG_HOME", "").strip() or str(Path.home() / ".config")
    return Path(base) / "hilsim" / "creds"


@dataclass(frozen=True)
class Grant:
    """One credential: its name, Zenoh user and password, and what it may write and ask."""

    name: str
    user: str
    password: str
    may_write: tuple[str, ...]
    may_ask: tuple[str, ...]

    @property
    def credentials(self) -> Credentials:
        return Credentials(self.user, self.password)

    def describe(self) -> str:
        if not self.may_write and not self.may_ask:
            return f"{self.name}: read only"
        parts = [f"may write {', '.join(self.may_write)}"] if self.may_write else []
        parts += [f"may ask {', '.join(self.may_ask)}"] if self.may_ask else []
        return f"{self.name}: {'; '.join(parts)}"


def add(name: str, may_write: list[str], may_ask: list[str], *, connect: str, where: Path | None = None) -> Path:
    """Write the credential ``name`` (replacing one of that name); its client config's path."""
    if not NAME.fullmatch(name):
        raise ConfigError(f"hilsim creds: {name!r}: a name is a letter, then letters, digits, '_' or '-'")
    check_grant(may_write, may_ask)
    d = where or creds_dir()
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    g = Grant(name, f"lab-{name}-{secrets.token_hex(4)}", secrets.token_urlsafe(24), tuple(may_write),
              tuple(may_ask))
    transport.write_private(d / f"{name}.json", json.dumps({
        "name": g.name, "user": g.user, "password": g.password, "may_write": list(g.may_write),
        "may_ask": list(g.may_ask)}, indent=2) + "\n")
    config = d / f"{name}.json5"
    transport.write_private(config, transport.client_config_text(connect, g.credentials))
    return config


def load_all(where: Path | None = None) -> list[Grant]:
    """The lab's credentials, checked against the key table (ConfigError, one line, for one that is not
    this user's own file, or grants what a person may not be given)."""
    d = where or creds_dir()
    if not d.is_dir():
        return []
    out = []
    for f in sorted(d.glob("*.json")):
        st = f.stat()
        if st.st_uid != os.getuid() or st.st_mode & 0o077:
            raise ConfigError(f"{f}: a credential must be this user's and mode 0600 (chmod 600 {f})")
        try:
            raw = json.loads(f.read_text())
            g = Grant(str(raw["name"]), str(raw["user"]), str(raw["password"]), tuple(raw.get("may_write", [])),
                      tuple(raw.get("may_ask", [])))
        except (ValueError, KeyError, TypeError) as e:
            raise ConfigError(f"{f}: not a hilsim credential ({type(e).__name__}: {e})") from None
        check_grant(list(g.may_write), list(g.may_ask), where=str(f))
        out.append(g)
    return out


def cmd_creds(args: argparse.Namespace) -> int:
    try:
        if args.creds_cmd == "add":
            if args.read_only and (args.may_write or args.may_ask):
                raise ConfigError("hilsim creds add: --read-only gives nothing to write or ask; drop --may-write and "
                                  "--may-ask")
            if not args.read_only and not args.may_write and not args.may_ask:
                topics, asks = grantable()
                raise ConfigError("hilsim creds add: say what it may do: --may-write " + ",".join(topics)
                                  + " and/or --may-ask " + ",".join(asks) + ", or --read-only")
            split = [x.strip() for x in (args.may_write or "").split(",") if x.strip()]
            asks = [x.strip() for x in (args.may_ask or "").split(",") if x.strip()]
            config = add(args.name, split, asks, connect=args.connect)
            g = next(g for g in load_all(config.parent) if g.name == args.name)
            print(f"hilsim creds: {g.describe()} (every robot's keys); runs started from now admit it")
            print(f"  a ROS 2 node: ZENOH_SESSION_CONFIG_URI={config}")
            print(f"  a hilsim tool: HILSIM_ZENOH_AUTH={config}  (router {args.connect}: edit the file for another)")
        elif args.creds_cmd == "list":
            grants = load_all()
            if not grants:
                print(f"hilsim creds: none in {creds_dir()}")
            for g in grants:
                print(f"{g.describe()}  ({creds_dir() / (g.name + '.json5')})")
        elif args.creds_cmd == "rm":
            d = creds_dir()
            if not (d / f"{args.name}.json").exists():
                raise ConfigError(f"hilsim creds rm: no credential {args.name!r} in {d}")
            for ext in (".json", ".json5"):
                (d / f"{args.name}{ext}").unlink(missing_ok=True)
            print(f"hilsim creds: {args.name} removed (runs started from now no longer admit it)")
    except ConfigError as e:
        print(str(e), file=sys.stderr)
        return 2
    return 0
