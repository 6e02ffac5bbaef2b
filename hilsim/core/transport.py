"""Zenoh, configured one way for every hilsim program.

Default (embedded, nothing to install): ``hilsim up`` opens a Zenoh *router* on a loopback
port inside the launcher process; every service is a *peer* that connects to it, listens on
an ephemeral loopback port and has multicast scouting off, so nothing leaves the machine.
To join another network, set ``zenoh.connect`` in the scenario or ``HILSIM_ZENOH_CONNECT``
(e.g. ``tcp/192.0.2.10:7447``) and the same programs connect there instead (docs/deployment.md).
With ``zenoh.tls`` (or ``HILSIM_TLS_*``) every process is a TLS client of the router with its own
certificate, and the router's config file says who may do what (docs/security.md).
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


def open_router(endpoint: str) -> zenoh.Session:
    """A router session listening on ``endpoint`` (e.g. ``tcp/127.0.0.1:7447``)."""
    zc = ZenohConfig(connect=[], listen=[endpoint])
    try:
        return zenoh.open(zenoh_config(zc, mode="router"))
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot start the Zenoh router on {endpoint}: {e}") from e


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


def latched_publisher(session: Any, key: str) -> Any:
    """A transient-local publisher, as rmw_zenoh makes one: a Zenoh advanced publisher keeping its last
    sample for subscribers that come later (``/robot_description``, ``/tf_static``). On an in-process
    bus (tests, benchmarks) an ordinary publisher."""
    real = session if isinstance(session, zenoh.Session) else getattr(session, "session", None)
    if not isinstance(real, zenoh.Session):
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
    """The Zenoh settings of a tool: :func:`tool_endpoints`, and a TLS identity from
    ``HILSIM_TLS_*`` when set (docs/security.md)."""
    from pydantic import ValidationError

    tls = tls_from_env()
    try:
        return ZenohConfig(connect=tool_endpoints(connect), tls=TlsConfig(**tls) if tls else None)
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
