"""The rmw_zenoh wire format (ROS 2 Jazzy >= 0.2.4 and Kilted, Zenoh 1.x), as plain functions.

A leaf module: it imports nothing from hilsim. It builds and reads what ``rmw_zenoh_cpp`` puts on
Zenoh, so a hilsim process can publish to, subscribe from and appear in the graph of ROS 2 nodes
that run on ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``.

Every fact below names the file it comes from in ``github.com/ros2/rmw_zenoh`` (``path@commit``;
paths relative to ``rmw_zenoh_cpp/src/detail/`` unless they start otherwise). Files read at the
commits listed; "index copy" means a stored copy of the file whose commit the source index did not
show.

Topic and service keys
    * ``<domain>/<name>/<type>/<hash>``: ``TopicInfo::TopicInfo`` in
      liveliness_utils.cpp@3411fdec149fe0c932f24d4d79ef908eb81d7482 builds
      ``to_string(domain_id) + "/" + strip_slashes(name) + "/" + type + "/" + type_hash``;
      ``strip_slashes`` removes one leading and one trailing ``/``. Publishers
      (rmw_publisher_data.cpp@3e19ec730c529035a648aec80c0ae0a056943b8c), subscribers
      (rmw_subscription_data.cpp@a72659a6a65404a4ed43b7f41a6fc514d737e602), service queryables
      (rmw_service_data.cpp@028bbe30b72c9069be14e54b7073f6e2bfd9d00f) and clients
      (rmw_client_data.cpp@57fb1f8c607ff1af427a7500a777b62cd98a3c3d) all use that one key.
    * Type name: ``<namespace>::dds_::<Name>_`` with the type support's namespace
      (``sensor_msgs::msg``): ``_create_type_name`` in type_support_common.cpp@bfc065f8c80c
      (= bfc065f8c80cc3bc4d1963dc44ac5a472460903a, the pre-1.0 snapshot); the 1.x design.md
      examples below show the same form.
      Services: the response type's name cut at ``rfind("Response_")``
      (rmw_service_data.cpp@028bbe30), the client the request type's cut at ``find("Request_")``
      (rmw_client_data.cpp@57fb1f8c), e.g. ``example_interfaces::srv::dds_::AddTwoInts_``.
      ``ros2 topic list -t`` shows it demangled (``_demangle_if_ros_type`` in
      graph_cache.cpp@bfc065f8c80c): ``sensor_msgs/msg/JointState``.
    * Hash: ``rosidl_stringify_type_hash`` of the type support's hash (``RIHS01_<64 hex>``); for a
      service the hash of the *service* type (``type_support->get_type_hash_func`` on the service
      type support, rmw_client_data.cpp@57fb1f8c and rmw_service_data.cpp@b9508dbc2512df3ae7842ec2444c36300a1282f6,
      the latter pre-1.0; the 1.x server copy at 028bbe30 is Humble's, which has no hashes).
      Worked examples (docs/design.md, Zenoh 1.x edition, index copy):
      ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…`` and
      ``2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118…``.
    * Payload: the CDR stream as fastcdr writes it, encapsulation header included
      (rmw_publisher_data.cpp@3e19ec73 ``publish``).

Attachment (every put, every query, every reply)
    * 33 bytes: int64 LE sequence number, int64 LE source timestamp (ns since the UNIX epoch, from
      ``std::chrono::system_clock``: ``get_system_time_in_ns`` in
      zenoh_utils.cpp@1322545421bb9f937c9e91bb0d1edceb2d52186f), then the 16-byte gid as a
      zenoh-ext sequence, i.e. LEB128 length ``0x10`` + 16 bytes: ``AttachmentData::serialize_to_zbytes``
      serializes ``int64_t, int64_t, std::array<uint8_t, 16>`` with ``zenoh::ext::Serializer``
      (attachment_helpers.cpp@534747dca92adf15e1b1b975123037ca278db5ba); docs/design.md (1.x
      edition) spells out the same bytes. ``zenoh.ext.z_serialize((Int64(seq), Int64(ts), gid))``
      gives identical bytes (tests/test_ros2_wire.py checks it).
    * Older layout: the first Zenoh 1.x releases wrote a key/value list instead (strings
      ``"sequence_number"``, ``"source_timestamp"``, ``"source_gid"`` before each value;
      attachment_helpers.cpp@038b5a4fbb337e8033a7474a4a788fa381204c3c). ros2/rmw_zenoh#601
      (rolling 0.6.0, April 2025, before Kilted branched) and its backport #605 (Jazzy 0.2.4,
      April 2025) replaced it, breaking wire compatibility with older Jazzy releases.
      ``decode_attachment`` returns ``None`` for it.
    * Publisher sequence numbers start at 1 and grow by one per put (``sequence_number_(1)``,
      ``sequence_number_++``: rmw_publisher_data.cpp@3e19ec73); the gid is the publisher entity's
      gid (below). A subscriber drops a sample without an attachment ("Unable to obtain attachment",
      rmw_subscription_data.cpp@a72659a6).

Services
    * Server: a queryable on the service key, ``complete = true`` (rmw_service_data.cpp@028bbe30).
    * Client: ``get`` on that key with the request as payload, attachment (client's own sequence
      number from 1, now, client gid), ``target = ALL_COMPLETE``, ``consolidation = NONE``,
      timeout ``UINT64_MAX`` ms (rmw_client_data.cpp@57fb1f8c ``send_request``).
    * Reply: ``query.reply(<service key>, response)`` with attachment (request's sequence number,
      a new timestamp, the *client's* gid from the request) (rmw_service_data.cpp@028bbe30
      ``send_response``); the client reads sequence number and gid from it as the request id
      (rmw_client_data.cpp@57fb1f8c ``take_response``). See ``reply_attachment``.

Graph: liveliness tokens
    * ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<namespace>/<node name>`` and, for
      kinds other than ``NN``, ``/<topic>/<type>/<hash>/<qos>`` (``KeyexprIndex`` and
      ``Entity::Entity`` in liveliness_utils.cpp@3411fdec). ``ADMIN_SPACE = "@ros2_lv"``; kinds
      ``NN`` node, ``MP`` publisher, ``MS`` subscription, ``SS`` service server, ``SC`` client.
    * Enclave, namespace, node name, topic, type and hash each go through ``mangle_name`` (every
      ``/`` becomes ``%``). rcl hands a root namespace and the default enclave as ``/``, so they
      are ``%``; ``/arm`` is ``%arm``, ``/arm/joint_states`` is ``%arm%joint_states``.
      ``Entity::make(keyexpr)`` demangles them and refuses tokens with an empty chunk.
    * ``<zid>`` is ``session->get_zid().to_string()`` (``Entity::make`` in liveliness_utils.cpp@3411fdec)
      → zenoh-cpp ``Id::to_string`` → zenoh-c ``z_id_to_string`` → the Rust ``ZenohId`` Display
      (zenoh-c src/info.rs, index copy): lowercase hex without leading zeros, at most 32 digits.
      zenoh-python's ``str(session.info.zid())`` is that same Display. (Before the Zenoh 1.0 port
      rmw_zenoh printed the zid with its own unpadded loop: liveliness_utils.cpp@bfc065f8c80c.)
    * ``<nid>``/``<id>``: decimal, from one counter per context (= per Zenoh session) shared by
      nodes and all their entities, starting at 0 (``next_entity_id_(0)``,
      ``get_next_entity_id() { return next_entity_id_++; }``: rmw_context_impl_s.cpp 1.x index
      copy, and @b3a8ef1c6e482a77429c702bdd25773ab3b95d67; callers in rmw_zenoh.cpp@bfc065f8c80c).
      A node token repeats its own id (``std::to_string(id)`` twice: rmw_node_data.cpp@3411fdec);
      an entity token carries its node's id then its own. (design.md calls ``<id>`` "the ID of the
      entity within the node", but the code draws it from the context counter.)
    * QoS chunk (``qos_to_keyexpr``, liveliness_utils.cpp@3411fdec):
      ``R:D:H,depth:dl_s,dl_ns:ls_s,ls_ns:L,lease_s,lease_ns`` with rmw enum numbers, every field
      left empty where it equals rmw_zenoh's default profile (``QoS::QoS`` in
      qos.cpp@7efeee2b9009b816a4bd4a3148af3cca40f753d5): reliable, volatile, keep-last, depth 42,
      deadline/lifespan/lease ``RMW_DURATION_INFINITE`` = (9223372036 s, 854775807 ns), liveliness
      automatic. The profile is first passed through ``QoS::best_available_qos`` (system-default
      policies → those defaults, depth 0 → 42, durations ``{0, 0}`` → infinite), before the token
      is built (rmw_publisher_data.cpp@3e19ec73 ``make``). So ROS 2's default publisher (reliable,
      volatile, keep-last 10) is ``::,10:,:,:,,`` (design.md shows ``::,7:,:,:,,`` for the demo
      talker's depth 7). ``keyexpr_to_qos`` reads empty fields back as the defaults.
    * Jazzy before 0.2.3 used transient-local as the default durability (ros2/rmw_zenoh#485,
      #521/#530 "Switch default durability to volatile", Jazzy 0.2.3, March 2025), which changes
      which durability is elided; this module follows the volatile default of Jazzy >= 0.2.3 and
      Kilted.
    * Gid: XXH3-128 (seed 0, default secret) of the token's key expression, stored as the low
      64 bits then the high 64 bits in host (little-endian) order (``Entity::Entity``,
      liveliness_utils.cpp@3411fdec, with simplified_xxhash3.cpp). ``xxhash.xxh3_128`` agrees with
      rmw_zenoh's simplified_xxhash3.cpp on every input of 0..1499 bytes (checked by compiling the
      latter once, outside this repository).
    * Discovery: a context does ``liveliness_get`` on ``@ros2_lv/<domain>/**`` and then declares a
      liveliness subscriber on it with ``history = true`` (``subscription_token`` in
      liveliness_utils.cpp@3411fdec; rmw_context_impl_s.cpp 1.x index copy). ``ros2 node list``,
      ``ros2 topic list`` and the endpoint info are built from these tokens only (graph_cache.cpp).

Transient local (informational; the session code does the declaring)
    * Publisher: a zenoh-ext advanced publisher with a cache of ``depth`` samples and
      ``publisher_detection``; reliable ones add sample-miss detection with a 500 ms sporadic
      heartbeat. Congestion control is DROP, except reliable + keep-all: BLOCK.
      (rmw_publisher_data.cpp@3e19ec73.)
    * Subscriber: an advanced subscriber with ``history(detect_late_publishers, max_samples=depth)``,
      ``subscriber_detection``, and recovery with heartbeat when reliable
      (rmw_subscription_data.cpp@a72659a6).

rmw enum numbers (ros2/rmw ``rmw/include/rmw/types.h``, Jazzy): reliability 0 system default,
1 reliable, 2 best effort, 3 unknown, 4 best available; durability 0 system default, 1 transient
local, 2 volatile, 3 unknown, 4 best available; history 0 system default, 1 keep last, 2 keep all,
3 unknown; liveliness 0 system default, 1 automatic, 2 manual by node (deprecated), 3 manual by
topic, 4 unknown, 5 best available. Profiles: ``rmw_qos_profile_default`` and
``rmw_qos_profile_services_default`` (reliable, volatile, keep-last 10), ``rmw_qos_profile_sensor_data``
(best effort, volatile, keep-last 5) in ``rmw/qos_profiles.h``; rclcpp's ``ClockQoS`` is the sensor
data profile with keep-last 1 (rclcpp/src/rclcpp/qos.cpp); ``/robot_description``
(robot_state_publisher) and ``/tf_static`` (tf2_ros ``StaticBroadcasterQoS``) use keep-last 1,
transient local, reliable.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum
from typing import Final

import xxhash

# --------------------------------------------------------------------------- keys and type names

ADMIN_SPACE: Final = "@ros2_lv"
KINDS: Final = ("NN", "MP", "MS", "SS", "SC")
ENTITY_KINDS: Final = ("MP", "MS", "SS", "SC")


def strip_slashes(name: str) -> str:
    """One leading and one trailing ``/`` removed, as rmw_zenoh's ``strip_slashes``."""
    start = 1 if name.startswith("/") else 0
    end = len(name) - 1 if len(name) > start and name.endswith("/") else len(name)
    return name[start:end]


def topic_key(domain_id: int, topic: str, dds_type: str, type_hash: str) -> str:
    """The Zenoh key of a ROS 2 topic, e.g. ``0/arm/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_…``.

    Services use the same form (the queryable's key): pass the service name, the service's DDS type
    (``example_interfaces::srv::dds_::AddTwoInts_``) and the service type's hash."""
    name = strip_slashes(topic)
    if not name:
        raise ValueError(f"empty topic name: {topic!r}")
    return f"{int(domain_id)}/{name}/{dds_type}/{type_hash}"


service_key = topic_key
"""Alias of :func:`topic_key`: a service's queryable key has the same form."""


def domain_key(domain_id: int) -> str:
    """Every topic and service key of a domain: ``<domain>/**``."""
    return f"{int(domain_id)}/**"


def graph_key(domain_id: int) -> str:
    """Every liveliness token of a domain: ``@ros2_lv/<domain>/**`` (rmw_zenoh's ``subscription_token``)."""
    return f"{ADMIN_SPACE}/{int(domain_id)}/**"


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` → ``sensor_msgs::msg::dds_::JointState_`` (``srv`` and ``action`` alike)."""
    parts = ros_type.split("/")
    if len(parts) < 3 or not all(parts):
        raise ValueError(f"not a ROS 2 type name pkg/msg/Type: {ros_type!r}")
    return "::".join(parts[:-1]) + "::dds_::" + parts[-1] + "_"


def ros_type_name(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::JointState_`` → ``sensor_msgs/msg/JointState``; anything else unchanged
    (rmw_zenoh's ``_demangle_if_ros_type``)."""
    if not dds_type.endswith("_"):
        return dds_type
    pos = dds_type.find("dds_::")
    if pos < 0:
        return dds_type
    return dds_type[:pos].replace("::", "/") + dds_type[pos + 6 : -1]


# --------------------------------------------------------------------------- attachment

GID_SIZE: Final = 16
ATTACHMENT_SIZE: Final = 33
_ATTACHMENT: Final = struct.Struct("<qqB16s")
_pack = _ATTACHMENT.pack
_unpack = _ATTACHMENT.unpack


def encode_attachment(seq: int, source_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of a put, query or reply: seq, source timestamp (ns), gid."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a gid has {GID_SIZE} bytes, got {len(gid)}")
    return _pack(seq, source_ns, GID_SIZE, gid)


def decode_attachment(raw: bytes | bytearray | memoryview) -> tuple[int, int, bytes] | None:
    """``(seq, source_ns, gid)`` of an attachment, or ``None`` if it is not the 33-byte layout.

    Pass ``sample.attachment.to_bytes()`` (or anything bytes-like)."""
    if len(raw) != ATTACHMENT_SIZE:
        return None
    seq, ts, n, gid = _unpack(raw)
    if n != GID_SIZE:
        return None
    return seq, ts, gid


def reply_attachment(request: bytes | bytearray | memoryview, source_ns: int) -> bytes | None:
    """A service reply's attachment for a request's: the request's seq and client gid, a new timestamp.

    ``None`` if the request's attachment is not readable (rmw_zenoh's server rejects such a request)."""
    got = decode_attachment(request)
    if got is None:
        return None
    seq, _, gid = got
    return _pack(seq, source_ns, GID_SIZE, gid)


def request_id(raw: bytes | bytearray | memoryview) -> tuple[bytes, int] | None:
    """``(client gid, seq)`` of a request's or reply's attachment: what a client matches replies by."""
    got = decode_attachment(raw)
    return None if got is None else (got[2], got[0])


# --------------------------------------------------------------------------- QoS


class Reliability(IntEnum):
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(IntEnum):
    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_NODE = 2
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


Duration = tuple[int, int]
"""(seconds, nanoseconds), as ``rmw_time_t``."""

DURATION_UNSPECIFIED: Final[Duration] = (0, 0)
DURATION_INFINITE: Final[Duration] = (9223372036, 854775807)


@dataclass(frozen=True)
class Qos:
    """An ``rmw_qos_profile_t`` (enum fields as rmw numbers). The defaults are ``rmw_qos_profile_default``."""

    reliability: int = Reliability.RELIABLE
    durability: int = Durability.VOLATILE
    history: int = History.KEEP_LAST
    depth: int = 10
    deadline: Duration = DURATION_UNSPECIFIED
    lifespan: Duration = DURATION_UNSPECIFIED
    liveliness: int = Liveliness.SYSTEM_DEFAULT
    lease: Duration = DURATION_UNSPECIFIED

    def adapted(self) -> Qos:
        """The profile as rmw_zenoh stores it (``QoS::best_available_qos``)."""
        d = ZENOH_DEFAULT_QOS
        return Qos(
            reliability=d.reliability
            if self.reliability in (Reliability.SYSTEM_DEFAULT, Reliability.UNKNOWN)
            else self.reliability,
            durability=d.durability
            if self.durability in (Durability.SYSTEM_DEFAULT, Durability.UNKNOWN)
            else self.durability,
            history=d.history if self.history in (History.SYSTEM_DEFAULT, History.UNKNOWN) else self.history,
            depth=d.depth if self.depth == 0 else self.depth,
            deadline=d.deadline if tuple(self.deadline) == DURATION_UNSPECIFIED else tuple(self.deadline),
            lifespan=d.lifespan if tuple(self.lifespan) == DURATION_UNSPECIFIED else tuple(self.lifespan),
            liveliness=d.liveliness
            if self.liveliness in (Liveliness.SYSTEM_DEFAULT, Liveliness.UNKNOWN)
            else self.liveliness,
            lease=d.lease if tuple(self.lease) == DURATION_UNSPECIFIED else tuple(self.lease),
        )

    def encode(self) -> str:
        """The token's QoS chunk (``qos_to_keyexpr`` of the adapted profile), e.g. ``::,10:,:,:,,``."""
        q, d = self.adapted(), ZENOH_DEFAULT_QOS

        def f(value: int, default: int) -> str:
            return "" if value == default else str(int(value))

        return (
            f"{f(q.reliability, d.reliability)}:{f(q.durability, d.durability)}"
            f":{f(q.history, d.history)},{f(q.depth, d.depth)}"
            f":{f(q.deadline[0], d.deadline[0])},{f(q.deadline[1], d.deadline[1])}"
            f":{f(q.lifespan[0], d.lifespan[0])},{f(q.lifespan[1], d.lifespan[1])}"
            f":{f(q.liveliness, d.liveliness)},{f(q.lease[0], d.lease[0])},{f(q.lease[1], d.lease[1])}"
        )

    @classmethod
    def decode(cls, text: str) -> Qos:
        """A token's QoS chunk read back (``keyexpr_to_qos``): empty fields are rmw_zenoh's defaults."""
        parts = text.split(":")
        if len(parts) != 6:
            raise ValueError(f"QoS chunk needs 6 ':'-separated fields: {text!r}")
        hist, dl, ls, lv = (p.split(",") for p in parts[2:6])
        if len(hist) != 2 or len(dl) != 2 or len(ls) != 2 or len(lv) != 3:
            raise ValueError(f"malformed QoS chunk: {text!r}")
        d = ZENOH_DEFAULT_QOS

        def n(s: str, default: int) -> int:
            if s == "":
                return default
            if not s.isdigit():
                raise ValueError(f"not a number in QoS chunk {text!r}: {s!r}")
            return int(s)

        def e(enum: type[IntEnum], s: str, default: int) -> int:
            v = n(s, default)
            try:
                return enum(v)
            except ValueError:
                return v

        return cls(
            reliability=e(Reliability, parts[0], d.reliability),
            durability=e(Durability, parts[1], d.durability),
            history=e(History, hist[0], d.history),
            depth=n(hist[1], d.depth),
            deadline=(n(dl[0], d.deadline[0]), n(dl[1], d.deadline[1])),
            lifespan=(n(ls[0], d.lifespan[0]), n(ls[1], d.lifespan[1])),
            liveliness=e(Liveliness, lv[0], d.liveliness),
            lease=(n(lv[1], d.lease[0]), n(lv[2], d.lease[1])),
        )


ZENOH_DEFAULT_QOS: Final = Qos(
    Reliability.RELIABLE,
    Durability.VOLATILE,
    History.KEEP_LAST,
    42,
    DURATION_INFINITE,
    DURATION_INFINITE,
    Liveliness.AUTOMATIC,
    DURATION_INFINITE,
)
"""rmw_zenoh's default profile (qos.cpp): the fields a token's QoS chunk leaves empty."""

QOS_DEFAULT: Final = Qos()
"""``rmw_qos_profile_default``: reliable, volatile, keep-last 10 → ``::,10:,:,:,,``."""
QOS_SERVICES: Final = Qos()
"""``rmw_qos_profile_services_default`` (same values as the default profile)."""
QOS_SENSOR_DATA: Final = Qos(reliability=Reliability.BEST_EFFORT, depth=5)
"""``rmw_qos_profile_sensor_data``: best effort, volatile, keep-last 5 → ``2::,5:,:,:,,``."""
QOS_LATCHED: Final = Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)
"""``/robot_description``, ``/tf_static``: reliable, transient local, keep-last 1 → ``:1:,1:,:,:,,``."""
QOS_CLOCK: Final = Qos(reliability=Reliability.BEST_EFFORT, depth=1)
"""rclcpp ``ClockQoS`` (``/clock``): best effort, volatile, keep-last 1 → ``2::,1:,:,:,,``."""


# --------------------------------------------------------------------------- graph tokens


def mangle(name: str) -> str:
    """``/`` → ``%``; an empty name (no namespace, no enclave) is ``%`` like the root ``/``."""
    return name.replace("/", "%") if name else "%"


def demangle(text: str) -> str:
    """``%`` → ``/`` (rmw_zenoh's ``demangle_name``)."""
    return text.replace("%", "/")


def _node_prefix(
    domain: int, zid: str, node_id: int | str, entity_id: int | str, kind: str, enclave: str, namespace: str, name: str
) -> str:
    if not zid or not name:
        raise ValueError("a token needs a zid and a node name")
    return (
        f"{ADMIN_SPACE}/{int(domain)}/{zid}/{node_id}/{entity_id}/{kind}"
        f"/{mangle(enclave)}/{mangle(namespace)}/{mangle(name)}"
    )


def node_token(domain: int, zid: str, node_id: int | str, enclave: str, namespace: str, node_name: str) -> str:
    """A node's token (``NN``): the node id appears twice, as rmw_zenoh's ``NodeData::make`` writes it."""
    return _node_prefix(domain, zid, node_id, node_id, "NN", enclave, namespace, node_name)


def entity_token(
    kind: str,
    domain: int,
    zid: str,
    node_id: int | str,
    entity_id: int | str,
    enclave: str,
    namespace: str,
    node_name: str,
    topic: str,
    dds_type: str,
    type_hash: str,
    qos: Qos | str,
) -> str:
    """A publisher's (``MP``), subscription's (``MS``), service server's (``SS``) or client's (``SC``) token."""
    if kind not in ENTITY_KINDS:
        raise ValueError(f"entity kind must be one of {ENTITY_KINDS} (nodes: node_token), got {kind!r}")
    if not topic or not dds_type or not type_hash:
        raise ValueError("an entity token needs a topic, a type and a type hash")
    chunk = qos.encode() if isinstance(qos, Qos) else qos
    prefix = _node_prefix(domain, zid, node_id, entity_id, kind, enclave, namespace, node_name)
    return f"{prefix}/{mangle(topic)}/{mangle(dds_type)}/{mangle(type_hash)}/{chunk}"


def entity_gid(token_key: str) -> bytes:
    """The 16-byte gid rmw_zenoh derives from an entity's token (XXH3-128, low 64 then high 64 bits, LE)."""
    return xxhash.xxh3_128_intdigest(token_key.encode()).to_bytes(GID_SIZE, "little")


@dataclass(frozen=True)
class Token:
    """One liveliness token of the ROS 2 graph, read back (names demangled)."""

    key: str
    domain: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None

    @property
    def is_node(self) -> bool:
        return self.kind == "NN"

    @property
    def fq_node_name(self) -> str:
        """``/arm/joint_state_publisher`` (as ``ros2 node list`` prints it)."""
        ns = self.namespace.rstrip("/")
        return f"{ns}/{self.node_name}"

    @property
    def ros_type(self) -> str | None:
        """``sensor_msgs/msg/JointState`` (as ``ros2 topic list -t`` prints it)."""
        return None if self.dds_type is None else ros_type_name(self.dds_type)

    @property
    def gid(self) -> bytes:
        return entity_gid(self.key)


def parse_token(key: str) -> Token:
    """A liveliness token's key expression read back; ``ValueError`` if it is not one rmw_zenoh accepts."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE:
        raise ValueError(f"not an rmw_zenoh liveliness token: {key!r}")
    if any(p == "" for p in parts):
        raise ValueError(f"liveliness token with an empty chunk: {key!r}")
    kind = parts[5]
    if kind not in KINDS:
        raise ValueError(f"unknown entity kind {kind!r} in {key!r}")
    if not parts[1].isdigit():
        raise ValueError(f"domain is not a number in {key!r}")
    common = {
        "key": key,
        "domain": int(parts[1]),
        "zid": parts[2],
        "node_id": parts[3],
        "entity_id": parts[4],
        "kind": kind,
        "enclave": demangle(parts[6]),
        "namespace": demangle(parts[7]),
        "node_name": demangle(parts[8]),
    }
    if kind == "NN":
        if len(parts) != 9:
            raise ValueError(f"node token with extra chunks: {key!r}")
        return Token(**common)
    if len(parts) != 13:
        raise ValueError(f"{kind} token needs 13 chunks, has {len(parts)}: {key!r}")
    return Token(
        **common,
        topic=demangle(parts[9]),
        dds_type=demangle(parts[10]),
        type_hash=demangle(parts[11]),
        qos=Qos.decode(parts[12]),
    )


def list_nodes(tokens: Iterable[Token]) -> list[str]:
    """Fully qualified node names, sorted (what ``ros2 node list`` shows)."""
    return sorted({t.fq_node_name for t in tokens if t.is_node})


def list_topics(tokens: Iterable[Token]) -> dict[str, list[str]]:
    """Topic → ROS types of its publishers and subscriptions (what ``ros2 topic list -t`` shows)."""
    return _names_and_types(tokens, ("MP", "MS"))


def list_services(tokens: Iterable[Token]) -> dict[str, list[str]]:
    """Service → ROS types of its servers and clients (what ``ros2 service list -t`` shows)."""
    return _names_and_types(tokens, ("SS", "SC"))


def _names_and_types(tokens: Iterable[Token], kinds: tuple[str, ...]) -> dict[str, list[str]]:
    out: dict[str, set[str]] = {}
    for t in tokens:
        if t.kind in kinds and t.topic is not None and t.ros_type is not None:
            out.setdefault(t.topic, set()).add(t.ros_type)
    return {name: sorted(types) for name, types in sorted(out.items())}
