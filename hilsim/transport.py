"""Zenoh, configured one way for every hilsim program.

Default (embedded, nothing to install): ``hilsim up`` opens a Zenoh *router* on a loopback
port inside the launcher process; every service is a *peer* that connects to it, listens on
an ephemeral loopback port and has multicast scouting off, so nothing leaves the machine.
To join another network, set ``zenoh.connect`` in the scenario or ``HILSIM_ZENOH_CONNECT``
(e.g. ``tcp/192.0.2.10:7447``) and the same programs connect there instead.
"""

from __future__ import annotations

import json
import logging
import socket

import zenoh

from hilsim.config import ZenohConfig

LOG = logging.getLogger(__name__)
DEFAULT_ROUTER_PORT = 7447


def zenoh_config(zc: ZenohConfig, *, mode: str | None = None, listen: list[str] | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode or zc.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
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


def publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    # BLOCK: a slow subscriber (the recorder) must slow the sender, never lose samples.
    # express: no batching, lockstep latency matters more than throughput.
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
        express=True,
    )
