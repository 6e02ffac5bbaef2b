"""A ROS 2 node on rmw_zenoh, written from rmw_zenoh's specification without ROS and without hilsim.

What a node on ``rmw_zenoh_cpp`` (Jazzy/Kilted, Zenoh 1.x) does on the wire, rebuilt here from the
published facts (shared/ros2-wire.md; rmw_zenoh's liveliness_utils.cpp, attachment_helpers.cpp,
qos.cpp) so the tests check hilsim against an implementation that shares none of its code:

- types, hashes and CDR come from ``rosbags`` (its own ROS 2 Jazzy type store, its own CDR codec);
- a topic's key is ``<domain>/<name>/<pkg>::msg::dds_::<Type>_/<RIHS01 hash>``;
- a node announces ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/%/<ns>/<name>``, a publisher
  ``…/<nid>/<eid>/MP/%/<ns>/<name>/<topic>/<type>/<hash>/<qos>`` with ``/`` mangled to ``%``;
- a publisher's gid is XXH3-128 of its token (low 64 bits, then high, little endian) and every sample
  carries zenoh-ext's serialization of (int64 sequence number, int64 source time, the gid).
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import xxhash
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, z_deserialize, z_serialize

STORE = get_typestore(Stores.ROS2_JAZZY)
DEFAULT_QOS = "::,10:,:,:,,"  # reliable, volatile, keep-last 10: rmw_zenoh's encoding (qos.cpp)


def dds_name(ros_type: str) -> str:
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(domain: int, topic: str, ros_type: str) -> str:
    return f"{domain}/{topic.strip('/')}/{dds_name(ros_type)}/{STORE.hash_rihs01(ros_type)}"


def mangle(name: str) -> str:
    return name.replace("/", "%") if name else "%"


class Ros2Node:
    """One node: reads the graph, subscribes and publishes as rmw_zenoh does."""

    def __init__(self, endpoint: str, name: str = "lab_node", namespace: str = "/lab", domain: int = 0) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("timestamping/enabled", "{router: true, peer: true, client: true}")  # as rmw_zenoh's
        self.session = zenoh.open(conf)
        self.domain, self.name, self.namespace = domain, name, namespace
        self.zid = str(self.session.info.zid())
        self._ids = iter(range(1_000_000))
        self.node_id = next(self._ids)
        self._decl: list[Any] = [self.session.liveliness().declare_token(
            f"@ros2_lv/{domain}/{self.zid}/{self.node_id}/{self.node_id}/NN/%/{mangle(namespace)}/{name}")]
        self.graph: set[str] = set()
        self._lock = threading.Lock()
        self._decl.append(self.session.liveliness().declare_subscriber(
            f"@ros2_lv/{domain}/**", self._on_token, history=True))

    def _on_token(self, s: zenoh.Sample) -> None:
        with self._lock:
            (self.graph.add if s.kind == zenoh.SampleKind.PUT else self.graph.discard)(str(s.key_expr))

    # ---------------------------------------------------------------- the graph, as `ros2 … list`
    def tokens(self) -> list[list[str]]:
        with self._lock:
            return [t.split("/") for t in self.graph]

    def node_list(self) -> set[str]:
        return {f"{p[7].replace('%', '/').rstrip('/')}/{p[8]}" for p in self.tokens() if p[5] == "NN"}

    def topic_list(self) -> dict[str, set[str]]:
        """topic -> its (DDS type, hash) pairs, from publishers and subscriptions (``ros2 topic list -t``)."""
        out: dict[str, set[str]] = defaultdict(set)
        for p in self.tokens():
            if p[5] in ("MP", "MS") and len(p) == 13:
                out[p[9].replace("%", "/")].add(f"{p[10]}/{p[11]}")
        return out

    def publishers(self, topic: str) -> list[list[str]]:
        return [p for p in self.tokens() if p[5] == "MP" and len(p) == 13 and p[9] == mangle(topic)]

    # ---------------------------------------------------------------- data
    def subscribe(self, topic: str, ros_type: str, cb: Callable[[Any, tuple[int, int, bytes]], None]) -> None:
        def on_sample(s: zenoh.Sample) -> None:
            assert s.attachment is not None, f"sample on {topic} without rmw_zenoh's attachment"
            seq, ts, gid = z_deserialize(tuple[Int64, Int64, bytes], s.attachment)
            cb(STORE.deserialize_cdr(s.payload.to_bytes(), ros_type), (int(seq), int(ts), bytes(gid)))

        self._decl.append(self.session.declare_subscriber(topic_key(self.domain, topic, ros_type), on_sample))

    def subscribe_latched(self, topic: str, ros_type: str, cb: Callable[[Any], None]) -> None:
        """A transient-local subscription, as rmw_zenoh makes one: an advanced subscriber that asks
        the publishers' caches for what they sent before it came."""
        def on_sample(s: zenoh.Sample) -> None:
            cb(STORE.deserialize_cdr(s.payload.to_bytes(), ros_type))

        self._decl.append(zenoh.ext.declare_advanced_subscriber(
            self.session, topic_key(self.domain, topic, ros_type), on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True)))

    def publisher(self, topic: str, ros_type: str, *, keep_all: bool = False) -> Callable[[Any], None]:
        """``keep_all``: reliable, keep-all history, which rmw_zenoh sends with congestion control BLOCK
        (its samples are not dropped on a congested link); else keep-last 10, sent with DROP (qos.cpp)."""
        eid = next(self._ids)
        qos = "::2,10:,:,:,," if keep_all else DEFAULT_QOS
        token = (f"@ros2_lv/{self.domain}/{self.zid}/{self.node_id}/{eid}/MP/%/{mangle(self.namespace)}/{self.name}/"
                 f"{mangle(topic)}/{dds_name(ros_type)}/{STORE.hash_rihs01(ros_type)}/{qos}")
        gid = xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")
        self._decl.append(self.session.liveliness().declare_token(token))
        cc = zenoh.CongestionControl.BLOCK if keep_all else zenoh.CongestionControl.DROP
        pub = self.session.declare_publisher(topic_key(self.domain, topic, ros_type), congestion_control=cc)
        self._decl.append(pub)
        seq = [0]

        def put(msg: Any) -> None:
            seq[0] += 1
            att = z_serialize((Int64(seq[0]), Int64(time.time_ns()), gid))
            pub.put(bytes(STORE.serialize_cdr(msg, ros_type)), attachment=att)

        return put

    def close(self) -> None:
        for d in reversed(self._decl):
            d.undeclare()
        self.session.close()


def msg(ros_type: str, **fields: Any) -> Any:
    return STORE.types[ros_type](**fields)
