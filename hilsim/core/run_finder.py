"""The runs of this user on this machine, and which one a tool joins.

``hilsim up`` says which run owns its router's port in a pointer file (``$XDG_RUNTIME_DIR/hilsim`` or
``~/.cache/hilsim``, this user's only, one per port and network namespace: :func:`write_pointer`) with
the run's directory, scenario and the tools' credentials (``<run dir>/zenoh-client.json5``), as Jupyter
says where its token is. A tool (``hilsim topic``, ``gains``, ``goal``, ``play``, ``ui`` …) finds the run it
joins from these (:func:`tool_target`: ``--run DIR``, ``--connect``, or the one run up; several: asked,
never guessed) and names it in its first line (:func:`open_tool_session`).

Reads and writes no Zenoh key; files: the pointer files.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path
from typing import NamedTuple

import zenoh

from hilsim.core.config import ConfigError, TlsConfig, ZenohConfig, tls_from_env
from hilsim.core.keys import DEFAULT_PREFIX, Keys
from hilsim.core.transport import AUTH_ENV, DEFAULT_ROUTER_PORT, IDENTITIES_DIR, connected, open_session, write_private


def _net_namespace() -> str:
    """This process's network namespace (two namespaces may each have a router on one port)."""
    try:
        return str(os.stat("/proc/self/ns/net").st_ino)
    except OSError:
        return "0"


def pointer_dir() -> Path:
    """Where ``hilsim up`` says which run owns a router port: ``$XDG_RUNTIME_DIR/hilsim``, else
    ``~/.cache/hilsim`` (this user's only: mode 0700)."""
    base = os.environ.get("XDG_RUNTIME_DIR", "")
    if base and os.path.isdir(base) and os.access(base, os.W_OK):
        return Path(base) / "hilsim"
    return Path.home() / ".cache" / "hilsim"


def pointer_path(port: int) -> Path:
    """The pointer file of the run whose router listens on loopback ``port`` (in this network namespace)."""
    return pointer_dir() / f"{port}-{_net_namespace()}.json"


def loopback_port(endpoint: str) -> int | None:
    """The port of a ``tcp/`` endpoint on this machine's loopback, else None (credentials are given
    to nothing else)."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    if proto != "tcp" or host not in ("127.0.0.1", "localhost", "[::1]") or not port.isdigit():
        return None
    return int(port)


def write_pointer(endpoint: str, run_dir: Path, client_config: Path, scenario: str = "") -> Path | None:
    """Say (mode 0600) that the router on ``endpoint`` is this process's run's (its directory and
    scenario), with the tools' credentials."""
    port = loopback_port(endpoint)
    if port is None:
        return None
    path = pointer_path(port)
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    for old in path.parent.glob("*.json"):  # those of launchers that were killed (no stop, no removal)
        try:
            os.kill(int(json.loads(old.read_text())["pid"]), 0)
        except ProcessLookupError:
            old.unlink(missing_ok=True)
        except (OSError, ValueError, KeyError, TypeError):
            pass
    write_private(path, json.dumps({"endpoint": endpoint, "run_dir": str(run_dir.resolve()), "scenario": scenario,
                                    "client_config": str(client_config.resolve()), "pid": os.getpid()}) + "\n")
    return path


def remove_pointer(path: Path | None) -> None:
    """Remove a pointer this process wrote (not one a later run wrote over it)."""
    if path is None:
        return
    try:
        if json.loads(path.read_text()).get("pid") == os.getpid():
            path.unlink()
    except (OSError, ValueError):
        pass


class RunPointer(NamedTuple):
    """A run of this user that is up: what its pointer file says (:func:`write_pointer`)."""

    endpoint: str
    run_dir: Path
    scenario: str
    client_config: Path  # the tools' credentials
    pid: int  # its launcher

    def describe(self) -> str:
        """The run as a tool names it: directory, scenario, router endpoint."""
        return f"run {_shown(self.run_dir)} (scenario {self.scenario or '?'}) at {self.endpoint}"


def _shown(path: Path) -> str:
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def read_pointer(path: Path) -> RunPointer | None:
    """The run a pointer file names, if it is trustworthy and up: a file this user owns that nobody else
    may read, written by a launcher that still runs (not another process with its pid), whose
    credentials file exists; else None."""
    try:
        st = path.stat()
        if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
            return None
        info = json.loads(path.read_text())
        pid = int(info["pid"])
        os.kill(pid, 0)
        if b"hilsim" not in Path(f"/proc/{pid}/cmdline").read_bytes():
            return None
        got = RunPointer(str(info["endpoint"]), Path(info["run_dir"]), str(info.get("scenario") or ""),
                         Path(info["client_config"]), pid)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return got if got.client_config.is_file() else None


def live_runs() -> list[RunPointer]:
    """The runs of this user that are up, in this network namespace (by their pointers), oldest first."""
    d = pointer_dir()
    found = [read_pointer(p) for p in sorted(d.glob(f"*-{_net_namespace()}.json"))] if d.is_dir() else []
    return sorted((r for r in found if r is not None), key=lambda r: (str(r.run_dir), r.endpoint))


def run_at(endpoints: list[str]) -> RunPointer | None:
    """The run of this user whose router listens on one of ``endpoints`` (loopback), from its pointer."""
    for ep in endpoints:
        port = loopback_port(ep)
        if port is not None:
            got = read_pointer(pointer_path(port))
            if got is not None:
                return got
    return None


def find_credentials(endpoints: list[str]) -> Path | None:
    """The tools' credentials of the run whose router listens on one of ``endpoints`` (loopback), from its
    pointer file: only one this user owns and no one else may read, of a launcher still running."""
    got = run_at(endpoints)
    return got.client_config if got is not None else None


# `hilsim topic`, `gains`, `goal`, … join a running simulation from outside: they resolve where
# to connect and which prefix to use here, the same way for every tool.
DEFAULT_CONNECT = f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}"  # where `hilsim up` puts its router


def tool_endpoints(connect: str | None = None) -> list[str]:
    """Endpoints a tool connects to: ``--connect``, else ``HILSIM_ZENOH_CONNECT``, else the
    launcher's well-known :data:`DEFAULT_CONNECT`; comma-separated lists are split."""
    text = connect or os.environ.get("HILSIM_ZENOH_CONNECT") or DEFAULT_CONNECT
    return [e.strip() for e in text.split(",") if e.strip()] or [DEFAULT_CONNECT]


def tool_prefix(prefix: str | None = None) -> str:
    """Liveliness prefix a tool uses: ``--prefix``, else ``HILSIM_PREFIX``, else ``hilsim``."""
    return prefix or os.environ.get("HILSIM_PREFIX") or DEFAULT_PREFIX


def tool_domain(domain: int | None = None) -> int:
    """ROS 2 domain a tool uses: ``--domain``, else ``ROS_DOMAIN_ID`` (as every ROS 2 tool), else 0."""
    if domain is not None:
        return domain
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) > 232:
        raise ConfigError(f"ROS_DOMAIN_ID: expected a number from 0 to 232, got {text!r}")
    return int(text)


def tool_keys(robot: str = "arm", prefix: str | None = None, domain: int | None = None) -> Keys:
    """The keys of ``robot`` as a tool sees them (:func:`tool_prefix`, :func:`tool_domain`)."""
    return Keys(tool_prefix(prefix), robot, tool_domain(domain))


class ToolTarget(NamedTuple):
    """Where a tool connects, with what, and the run of this user it joins there (None: not known)."""

    zenoh: ZenohConfig
    run: RunPointer | None

    def describe(self) -> str:
        """The tool's first line: the run it joined (directory, scenario, endpoint), or the endpoint."""
        if self.run is not None:
            return f"joined {self.run.describe()}"
        return f"joined {', '.join(self.zenoh.connect)} (no run of yours is known there)"


def choose_run(runs: list[RunPointer], tool: str) -> RunPointer:
    """One of several runs of this user that are up: asked on a terminal; otherwise ConfigError (one
    line) listing them, never a guess."""
    listed = "; ".join(r.describe() for r in runs)
    if not (sys.stdin.isatty() and sys.stderr.isatty()):
        raise ConfigError(f"{tool}: {len(runs)} runs of yours are up ({listed}): say which with --run DIR "
                          f"or --connect ENDPOINT")
    sys.stderr.write(f"{tool}: {len(runs)} runs of yours are up:\n")
    for i, r in enumerate(runs, 1):
        sys.stderr.write(f"  {i}. {r.describe()}\n")
    while True:
        sys.stderr.write(f"which one (1-{len(runs)})? ")
        sys.stderr.flush()
        answer = sys.stdin.readline()
        if not answer:
            raise ConfigError(f"{tool}: no run chosen; say which with --run DIR or --connect ENDPOINT")
        if answer.strip().isdigit() and 1 <= int(answer) <= len(runs):
            return runs[int(answer) - 1]


# tools that get an identity of their own in a run, only what they do (hilsim.core.rights: play_rights,
# panel_rights): <run dir>/identities/<name>.json5, written by the run's router
TOOL_IDENTITIES = {"hilsim play": "play", "hilsim ui": "panel"}


def tool_identity(ptr: RunPointer, tool: str) -> Path:
    """The run's identity for ``tool``: its own if the run made one (:data:`TOOL_IDENTITIES`), else the tools'."""
    own = TOOL_IDENTITIES.get(tool)
    path = ptr.run_dir / IDENTITIES_DIR / f"{own}.json5" if own else None
    return path if path is not None and path.is_file() else ptr.client_config


def tool_target(connect: str | None = None, run: str | Path | None = None, tool: str = "hilsim") -> ToolTarget:
    """Where a tool connects and with what (docs/tools.md):

    - ``--run DIR``: the run of this user up in ``DIR`` (its router, its tools' credentials);
    - ``--connect`` (or ``HILSIM_ZENOH_CONNECT``): there (:func:`tool_endpoints`), with the credentials of
      the run of this user whose router it is, if any;
    - neither: the run of this user that is up, if there is one; several: :func:`choose_run` (asked,
      never guessed); none: the well-known :data:`DEFAULT_CONNECT`.

    Credentials: a TLS identity from ``HILSIM_TLS_*`` when set, else ``HILSIM_ZENOH_AUTH`` (a Zenoh config
    file), else the run's tools' file (docs/security.md). ConfigError (one line) for a ``--run`` that is
    not up, or several runs and no choice."""
    from pydantic import ValidationError

    tls = tls_from_env()
    ptr: RunPointer | None
    if run is not None:
        want = Path(run).resolve()
        up = live_runs()
        ptr = next((r for r in up if r.run_dir.resolve() == want), None)
        if ptr is None:
            others = f" (up: {'; '.join(r.describe() for r in up)})" if up else " (none of yours is up)"
            raise ConfigError(f"{tool}: --run {run}: no run of yours is up there{others}")
        endpoints = [ptr.endpoint]
    elif connect or os.environ.get("HILSIM_ZENOH_CONNECT"):
        endpoints = tool_endpoints(connect)
        ptr = run_at(endpoints)
    else:
        up = live_runs()
        ptr = up[0] if len(up) == 1 else choose_run(up, tool) if up else None
        endpoints = [ptr.endpoint] if ptr is not None else tool_endpoints()
    env_auth = os.environ.get(AUTH_ENV, "").strip()
    auth = None if tls else Path(env_auth) if env_auth else tool_identity(ptr, tool) if ptr is not None else None
    try:
        # a client of the router, as rmw_zenoh has a remote tool (rviz) be: its samples take one path, through
        # the router, in the order sent. A peer's path moves once gossip gives it its own link to a service
        # (late on a loaded machine): a joint state sent that way overtook the trajectory played before it
        zc = ZenohConfig(mode="client", connect=endpoints, tls=TlsConfig(**tls) if tls else None, auth=auth)
    except ValidationError as e:
        err = e.errors()[0]
        raise ConfigError(f"TLS from the environment: {err['msg'].removeprefix('Value error, ')}") from None
    return ToolTarget(zc, ptr)


def tool_zenoh(connect: str | None = None) -> ZenohConfig:
    """The Zenoh settings of a tool connecting to ``connect`` (:func:`tool_target`)."""
    return tool_target(connect).zenoh


def run_joints(run: RunPointer) -> list[str]:
    """The joints of the robot of a run of this user that is up, from its resolved scenario (its world model's
    actuated joints); empty if its files cannot say (the tool then leaves the check to the service)."""
    from hilsim.core.scenario import load_scenario, model_joints

    try:
        return model_joints(load_scenario(str(run.run_dir / "scenario.yaml")))
    except (OSError, ConfigError, ValueError):
        return []


def no_run_up(tool: str, where: str) -> str:
    """What a tool says when no run of this user is known and nothing answers where it tried."""
    return (f"{tool}: no run is up: none of yours, and nothing answers at {where} (start one with hilsim up; "
            "or name one with --run DIR or --connect ENDPOINT)")


def open_tool_session(connect: str | None = None, *, run: str | Path | None = None, tool: str | None = None,
                      wait: float = 2.0) -> zenoh.Session:
    """A session for a tool (:func:`tool_target`). With ``tool`` (its name, e.g. ``hilsim topic``), its first
    line on standard error names the run it joined, and a session that reaches nobody within ``wait``
    seconds (no router, no peer: an empty port) is a ConnectionError instead of a quiet tool."""
    target = tool_target(connect, run, tool or "hilsim")
    if tool is not None and target.run is not None:
        print(f"{tool}: {target.describe()}", file=sys.stderr, flush=True)
    where = ", ".join(target.zenoh.connect)
    try:
        session = open_session(target.zenoh)
    except ConnectionError:
        if tool is None or target.run is not None:
            raise
        raise ConnectionError(no_run_up(tool, where)) from None
    if tool is not None and not connected(session, wait):
        session.close()
        if target.run is None:  # said plainly, not as a join that then fails
            raise ConnectionError(no_run_up(tool, where))
        raise ConnectionError(f"{tool}: nothing answers at {where} (the run's router is gone?)")
    if tool is not None and target.run is None:
        print(f"{tool}: {target.describe()}", file=sys.stderr, flush=True)
    return session
