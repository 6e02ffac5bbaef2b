"""Foxglove, live: the run's ROS 2 topics over Foxglove's WebSocket protocol (``hilsim up … --foxglove [PORT]``).

``logger.foxglove.enabled`` gives the recorder a third consumer of what it takes in, beside its ``.rrd`` and
its bag: every sample, as the raw CDR bytes that arrived (the bag's bytes), is logged on a channel of a
``foxglove-sdk`` WebSocket server (``ws://127.0.0.1:8765`` by default). A channel per key, named after the
key's ROS 2 topic (``/arm/joint_states``, ``/tf``, ``/tf_static``, ``/arm/robot_description``, the rover's
``/rover/scan``, ``/rover/odom``, ``/rover/gps/fix``), ``message_encoding`` ``cdr``, its schema the type's
``.msg`` text with its dependencies (encoding ``ros2msg``, :func:`hilsim.core.ros2.types.full_definition`),
as the bag has them: the Foxglove app decodes and draws them as from a ROS 2 bridge (its 3D panel takes
the robot from ``/robot_description`` and the frames from ``/tf`` and ``/tf_static``). No second subscriber:
the samples are the recorder's.

Latched topics (transient local: ``/tf_static``, ``…/robot_description``) are put once at the start; their
last sample is logged again whenever a client subscribes, as a transient-local publisher gives its cache to a
late subscriber. Any other channel is advertised with its first sample, so no client can have subscribed to it
yet: that sample is logged again for a client that subscribes before the channel's second one (a map put every
few seconds, a path put once a goal: else a client would wait for the next, or never see it). Bounded: the
server keeps at most ``BACKLOG`` messages per client and drops a slow client's oldest (``foxglove-sdk``'s
``message_backlog_size``); logging never waits for a client. Loopback by default (``logger.foxglove.host`` for
another address). It stops with the recorder.

Zenoh keys: none (the recorder's samples). Files: ``<run dir>/foxglove.json`` (its address) while it is up.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
from pathlib import Path
from typing import Any

from hilsim.core.keys import UnknownKey, topic_name
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire

INFO_NAME = "foxglove.json"  # in the run directory while the server is up: its address
BACKLOG = 1024  # messages buffered per client at most (the oldest dropped past it)
LATCHED = ("/tf_static", "/robot_description")  # topic endings of transient-local writers
log = logging.getLogger(__name__)


def channel_of(key: str) -> tuple[str, str, bytes]:
    """The key's ROS 2 topic, type name and ``ros2msg`` schema text ("" and b"" for a key that is not a
    ROS 2 data key, or of a type without a definition)."""
    parts = key.split("/")
    try:
        topic = topic_name(key)
        ros_type = wire.ros_type_name(parts[-2])
    except (UnknownKey, IndexError):
        return "/" + key.strip("/"), "", b""
    if not ros2types.is_known(ros_type):
        return topic, ros_type, b""
    return topic, ros_type, ros2types.full_definition(ros_type).encode()


class FoxgloveLive:
    """The recorder's samples on a Foxglove WebSocket server (see the module's docstring)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "hilsim") -> None:
        import foxglove
        from foxglove.websocket import ServerListener

        self._fox = foxglove
        self.context = foxglove.Context()  # this server's channels only
        self.channels: dict[str, Any] = {}  # key -> foxglove.Channel
        self.by_id: dict[int, str] = {}  # channel id -> key
        self.latch: set[str] = set()  # keys of latched topics
        self.latched: dict[str, tuple[bytes, int]] = {}  # key -> its last sample and log time
        self.first: dict[str, tuple[bytes, int]] = {}  # key -> its first sample, until a second one comes
        self.lock = threading.Lock()
        me = self

        class Listener(ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                me._resend(int(channel.id))

        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                            server_listener=Listener(), message_backlog_size=BACKLOG)
        self.port = int(self.server.port)
        self.url = f"ws://{host}:{self.port}"
        self.messages = 0
        self.info_path: Path | None = None

    def add(self, key: str, payload: bytes, log_ns: int) -> None:
        """One sample the recorder took in (its raw CDR), on the key's channel."""
        ch = self.channels.get(key)
        new = ch is None
        if new:
            ch = self._channel(key)
        ch.log(payload, log_time=log_ns)
        with self.lock:
            if key in self.latch:
                self.latched[key] = (payload, log_ns)
            elif new:
                self.first[key] = (payload, log_ns)
            elif key in self.first:
                del self.first[key]  # a subscriber from now on has missed more than the first: it comes as put
        self.messages += 1  # (called from the recorder's receiving threads: a count, not exact under a race)

    def _channel(self, key: str) -> Any:
        # made outside the lock (the server's callbacks take it); one per key all the same, however many
        # of the recorder's receiving threads see the key's first sample
        topic, ros_type, schema = channel_of(key)
        fox = self._fox
        sch = fox.Schema(name=ros_type or "unknown", encoding="ros2msg", data=schema) if schema else None
        ch = fox.Channel(topic, schema=sch, message_encoding="cdr", context=self.context,
                         metadata={"hilsim_key": key})
        with self.lock:
            got = self.channels.get(key)
            if got is None:
                if topic.endswith(LATCHED):
                    self.latch.add(key)
                self.channels[key] = ch
                self.by_id[int(ch.id())] = key
        if got is not None:
            ch.close()
            return got
        return ch

    def _resend(self, channel_id: int) -> None:
        """A client subscribed: a latched topic's last sample again, another's first while it is its only one
        (the others come as they are put)."""
        with self.lock:
            key = self.by_id.get(channel_id)
            got = (self.latched.get(key) or self.first.get(key)) if key is not None else None
            ch = self.channels.get(key) if key is not None else None
        if got is not None and ch is not None:
            ch.log(got[0], log_time=got[1])

    def close(self) -> None:
        self.server.stop()
        log.info("foxglove server stopped: %d messages logged", self.messages)


# ---------------------------------------------------------------------- the recorder's hooks (services/logger.py)
def start(cfg: Any, warn: Any, run_dir: Path) -> FoxgloveLive | None:
    """The Foxglove server of ``logger.foxglove`` (:class:`hilsim.core.config.FoxgloveConfig`), None when
    it is off or cannot start (said once; the recording goes on without it)."""
    if not cfg.enabled:
        return None
    try:
        fox = FoxgloveLive(cfg.host, cfg.port)
    except Exception as e:  # a port taken, foxglove-sdk missing: the recording goes on
        warn(f"no Foxglove server on {cfg.host}:{cfg.port}: {type(e).__name__}: {e}; the recording goes on")
        return None
    log.info("foxglove: %s", fox.url)
    fox.info_path = Path(run_dir) / INFO_NAME
    tmp = fox.info_path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"url": fox.url, "pid": os.getpid()}) + "\n")
    tmp.replace(fox.info_path)
    return fox


def stop(fox: FoxgloveLive | None) -> None:
    """The recording ended: so does the server (its clients are disconnected), and its address file goes."""
    if fox is not None:
        fox.close()
        if fox.info_path is not None:
            with contextlib.suppress(OSError):
                fox.info_path.unlink()


def read_info(run_dir: str | Path) -> dict[str, Any] | None:
    """The Foxglove server's address of a run that is up with ``--foxglove`` (``url``), else None."""
    try:
        info = json.loads((Path(run_dir) / INFO_NAME).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and "url" in info else None
