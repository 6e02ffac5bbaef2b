"""Zenoh, configured one way for every hilsim program.

Default (embedded, nothing to install): ``hilsim up`` opens a Zenoh *router* on a loopback
port inside the launcher process, with a user and password made for the run (below); every service
is a *client* of it with multicast scouting off, so nothing leaves the machine. (Without credentials,
e.g. ``--router`` to a plain router, a *peer* that also listens on an ephemeral loopback port.)
To join another network, set ``zenoh.connect`` in the scenario or ``HILSIM_ZENOH_CONNECT``
(e.g. ``tcp/192.0.2.10:7447``) and the same programs connect there instead (docs/deployment.md).
With ``zenoh.tls`` (or ``HILSIM_TLS_*``) every process is a TLS client of the router with its own
certificate, and the router's config file says who may do what (docs/security.md).

Without TLS, ``hilsim up``'s router authenticates (Zenoh's ``transport.auth.usrpwd``) every process of
the run with a user and password of its own and lets each write only what the key table gives it
(access control by username, :mod:`hilsim.core.rights`): a service gets its identity from ``zenoh.auth``
(a Zenoh client config file, ``<run dir>/identities/<process>.json5``, through ``HILSIM_ZENOH_AUTH``) and is
then a client of the router (no listener of its own); the tools of the same user find theirs
(``<run dir>/zenoh-client.json5``) through a pointer file per port, as Jupyter's token is, and name the
run they joined (:mod:`hilsim.core.run_finder`).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any, NamedTuple

import zenoh
import zenoh.ext as zenoh_ext

from hilsim.core.config import ConfigError, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.ros2 import wire

LOG = logging.getLogger(__name__)
DEFAULT_ROUTER_PORT = 7447

if os.environ.get("RUST_LOG"):
    # Zenoh's own log (a link closed, a lease expired) on stderr, i.e. in the service's log, as a
    # Zenoh application does with RUST_LOG: what to look at when samples went missing
    zenoh.init_log_from_env_or("error")


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
    # No shared memory between processes (Zenoh's default hands a sample over 3 kB to a process on the
    # same host as a shared buffer): on a loaded machine its watchdog overran ("timer overrun") and
    # receivers got such samples with their bytes gone (batches starting with zeros) or not at all
    # (a goal's result, a trajectory): issue 36. Over loopback TCP every byte arrives or is counted lost.
    conf.insert_json5("transport/shared_memory/enabled", "false")
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
        if "Unable to connect" in str(e):  # a client (a tool, a service of hilsim up): no router, or refused
            raise ConnectionError(f"nothing answers at {', '.join(zc.connect)}, or it refused these credentials (no "
                                  "router or simulation there, or not its run's; is the run up?)") from None
        raise ConnectionError(f"cannot open a Zenoh session (connect={zc.connect}): {e}") from e


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_router(endpoint: str, users: RouterUsers | None = None) -> zenoh.Session:
    """A router session listening on ``endpoint`` (e.g. ``tcp/127.0.0.1:7447``); with ``users``, only
    those of its dictionary may connect, and do what its access control (``users.acl``) lets them."""
    zc = ZenohConfig(connect=[], listen=[endpoint])
    conf = zenoh_config(zc, mode="router")
    if users is not None:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users.dictionary)))
        conf.insert_json5("access_control", json.dumps(users.acl))
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot start the Zenoh router on {endpoint}: {e}") from e


# ---------------------------------------------------------------- user and password (usrpwd)
# What `hilsim up` writes to its run directory (mode 0600 but the guests' file): the router's
# dictionary, a client config file for the tools' identity (also what a ROS 2 node on rmw_zenoh takes
# as ZENOH_SESSION_CONFIG_URI), one per process of the run in identities/ (hilsim.core.rights), and
# with zenoh.guests: read one for the read-only guest user.
USERS_FILE = "zenoh-users.txt"
CLIENT_CONFIG = "zenoh-client.json5"
GUEST_CONFIG = "zenoh-guest.json5"
IDENTITIES_DIR = "identities"
AUTH_ENV = "HILSIM_ZENOH_AUTH"  # a tool's credentials file, when not found through the pointer


class Credentials(NamedTuple):
    user: str
    password: str


class RouterUsers(NamedTuple):
    dictionary: Path  # user:password per line (Zenoh's dictionary_file)
    acl: dict[str, Any]  # Zenoh's access_control section (hilsim.core.rights.access_control)


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
    delaying the wall-clock loop (the caller passes False for a sample given once, e.g. a result:
    hilsim.core.keys.given_once). Not express: Zenoh may then send samples that queued up together in one
    write. Measured (docs/performance.md, "Express off"): the ring round (the latency of a
    lockstep step's hops) no worse, the CPU per sample less than half for sender and receiver,
    composed runs about 1.45x faster.
    """
    cc = zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
    return session.declare_publisher(key, congestion_control=cc, reliability=zenoh.Reliability.RELIABLE, express=False)


def zenoh_session(session: Any) -> zenoh.Session | None:
    """The Zenoh session behind ``session``: itself, the one a composed process's session wraps
    (hilsim.launch.compose), or None on an in-process bus (tests, benchmarks)."""
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
def connected(session: zenoh.Session, wait: float) -> bool:
    """True once ``session`` reaches a router or a peer (within ``wait`` seconds)."""
    end = time.monotonic() + wait
    while True:
        if any(True for _ in session.info.routers_zid()) or any(True for _ in session.info.peers_zid()):
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(0.02)


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
