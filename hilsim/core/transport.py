"""Zenoh, configured one way for every hilsim program.

Default (embedded, nothing to install): ``hilsim up`` opens a Zenoh *router* on a loopback
port inside the launcher process, with a user and password made for the run (below); every service
is a *client* of it with multicast scouting off, so nothing leaves the machine. (Without credentials,
e.g. ``--router`` to a plain router, a *peer* that also listens on an ephemeral loopback port.)
To join another network, set ``zenoh.connect`` in the scenario or ``HILSIM_ZENOH_CONNECT``
(e.g. ``tcp/192.0.2.10:7447``) and the same programs connect there instead (docs/deployment.md).
With ``zenoh.tls`` (or ``HILSIM_TLS_*``) every process is a TLS client of the router with its own
certificate, and the router's config file says who may do what (docs/security.md).

Without TLS, ``hilsim up``'s router authenticates (Zenoh's ``transport.auth.usrpwd``) with a user and
password made for the run and lets only that user write (access control by username): every
process of the run gets them from ``zenoh.auth`` (a Zenoh client config file, ``<run
dir>/zenoh-client.json5``) and is then a client of the router (no listener of its own), and the tools
of the same user find them through a pointer file per port (:func:`pointer_path`), as Jupyter's token is.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import stat
import threading
import time
from pathlib import Path
from typing import Any, NamedTuple

import zenoh
import zenoh.ext as zenoh_ext

from hilsim.core.config import ConfigError, TlsConfig, ZenohConfig, tls_from_env
from hilsim.core.keys import DEFAULT_PREFIX, Keys
from hilsim.core.ros2 import wire

LOG = logging.getLogger(__name__)
DEFAULT_ROUTER_PORT = 7447


def zenoh_config(zc: ZenohConfig, *, mode: str | None = None, listen: list[str] | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    if zc.tls is not None and mode != "router":
        # a client of the router, nothing else: no listener a stranger could reach around the
        # router's certificate check and access control (docs/security.md)
        mode, listen = "client", []
        tls = {"root_ca_certificate": zc.tls.root_ca, "connect_certificate": zc.tls.certificate,
               "connect_private_key": zc.tls.private_key}
        for k, v in tls.items():
            conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(Path(v).resolve())))
        conf.insert_json5("transport/link/tls/enable_mtls", "true")  # else the certificate is not presented
        conf.insert_json5("scouting/gossip/enabled", "false")
    elif zc.auth is not None and mode != "router":
        # a client of the router, as with TLS: every sample passes its authentication and access
        # control, and there is no listener of our own. (Peers with a user, password and dictionary
        # of their own lost liveliness tokens between them now and then: seen with Zenoh 1.10.)
        mode, listen = "client", []
        cred = read_credentials(zc.auth)
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(cred.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(cred.password))
    conf.insert_json5("mode", json.dumps(mode or zc.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
    # as rmw_zenoh's default config: transient-local publishers (robot_description, tf_static) are
    # Zenoh advanced publishers, which need timestamps
    conf.insert_json5("timestamping/enabled", "{router: true, peer: true, client: true}")
    if zc.connect and (mode or zc.mode) != "router":
        conf.insert_json5("connect/endpoints", json.dumps(zc.connect))
    ls = listen if listen is not None else zc.listen
    if ls and (mode or zc.mode) != "client":
        conf.insert_json5("listen/endpoints", json.dumps(ls))
    return conf


def open_session(zc: ZenohConfig) -> zenoh.Session:
    try:
        return zenoh.open(zenoh_config(zc))
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot open a Zenoh session (connect={zc.connect}): {e}") from e


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_router(endpoint: str, users: RouterUsers | None = None) -> zenoh.Session:
    """A router session listening on ``endpoint`` (e.g. ``tcp/127.0.0.1:7447``); with ``users``,
    only they may connect, and do what :func:`access_rules` gives them."""
    zc = ZenohConfig(connect=[], listen=[endpoint])
    conf = zenoh_config(zc, mode="router")
    if users is not None:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users.dictionary)))
        conf.insert_json5("access_control", json.dumps(access_rules(users)))
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot start the Zenoh router on {endpoint}: {e}") from e


# ---------------------------------------------------------------- user and password (usrpwd)
# What `hilsim up` writes to its run directory (mode 0600 but the guests' file): the router's
# dictionary, a client config file for the run's user (also what a ROS 2 node on rmw_zenoh takes
# as ZENOH_SESSION_CONFIG_URI), and with zenoh.guests: read one for the read-only guest user.
USERS_FILE = "zenoh-users.txt"
CLIENT_CONFIG = "zenoh-client.json5"
GUEST_CONFIG = "zenoh-guest.json5"
AUTH_ENV = "HILSIM_ZENOH_AUTH"  # a tool's credentials file, when not found through the pointer
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber"]


class Credentials(NamedTuple):
    user: str
    password: str


class RouterUsers(NamedTuple):
    dictionary: Path  # user:password per line (Zenoh's dictionary_file)
    run_user: str  # may do everything
    guest_user: str | None  # may read (subscribe, watch liveliness), nothing else


def access_rules(users: RouterUsers) -> dict[str, Any]:
    """Zenoh access control by username: the run's user everything, the guest (if any) reading only,
    anybody else nothing (no other user can authenticate anyway)."""
    # `**` matches no chunk that starts with '@': the ROS 2 graph, and the advanced publishers' caches and
    # detection (transient-local: /tf_static, robot_description), named
    every = ["**", "@ros2_lv/**", "**/@adv/**", "@adv/**"]
    rules: list[dict[str, Any]] = [{"id": "everything", "messages": ALL_MESSAGES, "flows": ["ingress", "egress"],
                                    "permission": "allow", "key_exprs": every}]
    subjects: list[dict[str, Any]] = [{"id": "run", "usernames": [users.run_user]}]
    policies: list[dict[str, Any]] = [{"id": "the run's processes", "rules": ["everything"], "subjects": ["run"]}]
    if users.guest_user is not None:
        rules += [{"id": "observe", "messages": ["declare_subscriber", "declare_liveliness_subscriber",
                                                "liveliness_query"], "flows": ["ingress"], "permission": "allow",
                   "key_exprs": every},
                  {"id": "deliver", "messages": ["put", "delete", "reply", "liveliness_token"], "flows": ["egress"],
                   "permission": "allow", "key_exprs": every}]
        subjects.append({"id": "guest", "usernames": [users.guest_user]})
        policies.append({"id": "guests read", "rules": ["observe", "deliver"], "subjects": ["guest"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def read_credentials(path: Path) -> Credentials:
    """User and password of a Zenoh config file (``transport.auth.usrpwd``); ConfigError (one line)
    if it has none or cannot be read."""
    try:
        conf = zenoh.Config.from_file(str(path))
        user = json.loads(conf.get_json("transport/auth/usrpwd/user") or "null")
        password = json.loads(conf.get_json("transport/auth/usrpwd/password") or "null")
    except (zenoh.ZError, OSError, ValueError) as e:
        raise ConfigError(f"zenoh.auth: cannot read {path}: {str(e).splitlines()[0] if str(e) else e}") from None
    if not isinstance(user, str) or not isinstance(password, str):
        raise ConfigError(f"zenoh.auth: {path} has no transport.auth.usrpwd user and password")
    return Credentials(user, password)


def write_private(path: Path, text: str, mode: int = 0o600) -> None:
    """Write ``text`` to a file only its owner may read (``mode``), made so before anything is in it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def client_config_text(endpoint: str, cred: Credentials) -> str:
    """A Zenoh client config (JSON, hence JSON5): the router's endpoint, the user and password, and
    timestamping on as rmw_zenoh's default config has it. For ``ZENOH_SESSION_CONFIG_URI``."""
    return json.dumps({
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "timestamping": {"enabled": {"router": True, "peer": True, "client": True}},
        "transport": {"auth": {"usrpwd": {"user": cred.user, "password": cred.password}}},
    }, indent=2) + "\n"


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


def write_pointer(endpoint: str, run_dir: Path, client_config: Path) -> Path | None:
    """Say (mode 0600) that the router on ``endpoint`` is this process's run's, with its credentials."""
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
    write_private(path, json.dumps({"endpoint": endpoint, "run_dir": str(run_dir.resolve()),
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


def find_credentials(endpoints: list[str]) -> Path | None:
    """The client config of the run whose router listens on one of ``endpoints`` (loopback), from its
    pointer file: only one this user owns and no one else may read, of a launcher still running."""
    for ep in endpoints:
        port = loopback_port(ep)
        if port is None:
            continue
        path = pointer_path(port)
        try:
            st = path.stat()
            if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
                continue
            info = json.loads(path.read_text())
            os.kill(int(info["pid"]), 0)  # the launcher that wrote it still runs (not another process
            if b"hilsim" not in Path(f"/proc/{int(info['pid'])}/cmdline").read_bytes():  # with its pid)
                continue
            client = Path(info["client_config"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if client.is_file():
            return client
    return None


# certificate and key paths of a router config file, resolved against the file's directory
_TLS_PATH_KEYS = ("root_ca_certificate", "listen_certificate", "listen_private_key",
                  "connect_certificate", "connect_private_key")


def router_config(path: Path, listen: list[str] | None = None) -> zenoh.Config:
    """A Zenoh router config from a JSON5 file (Zenoh's own format: listen endpoints, TLS, access
    control; ``config/security/router.json5``). Certificate paths in it are relative to the file;
    ``listen`` replaces its endpoints. ConfigError (one line) for a file Zenoh refuses."""
    if not path.is_file():
        raise ConfigError(f"{path}: no such router config file")
    try:
        conf = zenoh.Config.from_file(str(path))
        mode = json.loads(conf.get_json("mode") or "null")
        if mode not in (None, "router"):
            raise ConfigError(f"{path}: mode: expected \"router\" (or nothing), got {mode!r}")
        conf.insert_json5("mode", json.dumps("router"))
        for k in _TLS_PATH_KEYS:
            v = json.loads(conf.get_json(f"transport/link/tls/{k}") or "null")
            if isinstance(v, str) and not Path(v).is_absolute():
                full = (path.parent / v).resolve()
                if not full.is_file():
                    raise ConfigError(f"{path}: transport.link.tls.{k}: file {full} does not exist")
                conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(full)))
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
    except zenoh.ZError as e:
        raise ConfigError(f"{path}: not a Zenoh config Zenoh accepts: {str(e).splitlines()[0]}") from None
    return conf


def open_router_config(conf: zenoh.Config, where: str) -> zenoh.Session:
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot start the Zenoh router ({where}): {str(e).splitlines()[0]}") from e


def publisher(session: zenoh.Session, key: str, *, drop_when_congested: bool = False) -> zenoh.Publisher:
    """A publisher as every hilsim service declares it.

    Lockstep (``drop_when_congested=False``): BLOCK, a slow subscriber (the recorder) slows the
    sender and nothing is lost. Realtime (``True``): DROP, a subscriber that cannot keep up
    loses samples (counted by the receiver from the attachment's sequence numbers) instead of
    delaying the wall-clock loop; except a ``…/result`` key, always BLOCK (a lost result leaves
    its waiters waiting). Not express: Zenoh may then send samples that queued up together in one
    write. Measured (docs/performance.md, "Express off"): the ring round (the latency of a
    lockstep step's hops) no worse, the CPU per sample less than half for sender and receiver,
    composed runs about 1.45x faster.
    """
    if key.endswith("/result"):
        # a goal's or the task's result is one sample that its waiters (launchers on every host,
        # clients) cannot do without: seen lost on a congested link to another host when dropped
        drop_when_congested = False
    cc = zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
    return session.declare_publisher(key, congestion_control=cc, reliability=zenoh.Reliability.RELIABLE, express=False)


def zenoh_session(session: Any) -> zenoh.Session | None:
    """The Zenoh session behind ``session``: itself, the one a composed process's session wraps
    (hilsim.run.compose), or None on an in-process bus (tests, benchmarks)."""
    real = session if isinstance(session, zenoh.Session) else getattr(session, "session", None)
    return real if isinstance(real, zenoh.Session) else None


def latched_publisher(session: Any, key: str) -> Any:
    """A transient-local publisher, as rmw_zenoh makes one: a Zenoh advanced publisher keeping its last
    sample for subscribers that come later (``/robot_description``, ``/tf_static``). On an in-process
    bus (tests, benchmarks) an ordinary publisher."""
    real = zenoh_session(session)
    if real is None:
        return publisher(session, key)
    return zenoh_ext.declare_advanced_publisher(real, key, cache=zenoh_ext.CacheConfig(max_samples=1),
                                                publisher_detection=True)


# ---------------------------------------------------------------- sample attachment
# Every sample a hilsim service publishes carries the attachment rmw_zenoh puts on ROS 2 samples
# (hilsim.core.ros2.wire): int64 sequence number, int64 source timestamp [ns, wall clock], the
# publisher's 16-byte gid as a sequence (length 0x10 first), 33 bytes. Receivers use the sequence
# number to count lost samples and the gid to tell writers apart; a ROS 2 node's samples read the same.
_encode, _decode = wire.encode_attachment, wire.decode_attachment


def new_gid() -> bytes:
    """A random global id, for a writer that has no graph token to derive one from (tests, tools)."""
    return os.urandom(wire.GID_SIZE)


class Attachment(NamedTuple):
    # a tuple: built once per received sample, so it must be cheap (a frozen dataclass is not)
    seq: int
    source_ns: int
    gid: bytes

    def encode(self) -> bytes:
        return _encode(self.seq, self.source_ns, self.gid)

    @property
    def writer(self) -> str:
        """The writer's id as text (hex), as shown in logs and health."""
        return self.gid.hex()


def attachment_bytes(seq: int, gid: bytes) -> bytes:
    return _encode(seq, time.time_ns(), gid)


def read_attachment(sample: Any) -> Attachment | None:
    """The attachment of a received sample, or None if it has none or not in rmw_zenoh's layout."""
    att = sample.attachment
    if att is None:
        return None
    got = _decode(att.to_bytes())
    return None if got is None else Attachment._make(got)


# ---------------------------------------------------------------- command-line tools
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


def tool_zenoh(connect: str | None = None) -> ZenohConfig:
    """The Zenoh settings of a tool: :func:`tool_endpoints`, a TLS identity from ``HILSIM_TLS_*``
    when set, else a user and password: ``HILSIM_ZENOH_AUTH`` (a Zenoh config file), else those of
    the ``hilsim up`` of this user whose router listens there (:func:`find_credentials`; docs/security.md)."""
    from pydantic import ValidationError

    tls = tls_from_env()
    endpoints = tool_endpoints(connect)
    # user and password: HILSIM_ZENOH_AUTH, else those of the run (of this user) whose router it is
    env_auth = os.environ.get(AUTH_ENV, "").strip()
    auth = None if tls else Path(env_auth) if env_auth else find_credentials(endpoints)
    try:
        return ZenohConfig(connect=endpoints, tls=TlsConfig(**tls) if tls else None, auth=auth)
    except ValidationError as e:
        err = e.errors()[0]
        raise ConfigError(f"TLS from the environment: {err['msg'].removeprefix('Value error, ')}") from None


def open_tool_session(connect: str | None = None) -> zenoh.Session:
    """A peer session for a tool (see :func:`tool_zenoh`); ConnectionError if it cannot open."""
    return open_session(tool_zenoh(connect))


def wait_for_service(session: zenoh.Session, keys: Keys, service: str, timeout: float) -> bool:
    """True once ``service``'s liveliness token is seen within ``timeout`` s.

    A session that has just opened does not know the service's queryables yet: a query sent
    then reaches nobody. Services declare the token after their queryables, so once it is
    seen, queries are routed."""
    seen = threading.Event()

    def on_token(s: zenoh.Sample) -> None:
        if s.kind == zenoh.SampleKind.PUT:
            seen.set()

    sub = session.liveliness().declare_subscriber(keys.alive(service), on_token, history=True)
    try:
        return seen.wait(timeout)
    finally:
        sub.undeclare()
