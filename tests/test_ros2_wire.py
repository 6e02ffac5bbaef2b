"""hilsim.core.ros2.wire: the rmw_zenoh wire format (keys, attachment, liveliness tokens, QoS, gids).

The literal strings are derived by hand from rmw_zenoh's sources (see the module docstring) or
copied from its docs/design.md; the gids were computed with rmw_zenoh's own simplified_xxhash3.cpp."""

from __future__ import annotations

import socket
import threading
import time

import pytest
import zenoh
from zenoh.ext import Int64, z_deserialize, z_serialize

from hilsim.core.ros2 import wire
from hilsim.core.ros2.wire import (
    QOS_CLOCK,
    QOS_DEFAULT,
    QOS_LATCHED,
    QOS_SENSOR_DATA,
    ZENOH_DEFAULT_QOS,
    Durability,
    History,
    Liveliness,
    Qos,
    Reliability,
)

JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
ZID = "7ff19622fb2bef42842705c7b57a8532"
NODE_TOKEN = "@ros2_lv/0/7ff19622fb2bef42842705c7b57a8532/0/0/NN/%/%arm/joint_state_publisher"
PUB_TOKEN = (
    "@ros2_lv/0/7ff19622fb2bef42842705c7b57a8532/0/10/MP/%/%arm/joint_state_publisher/%arm%joint_states"
    "/sensor_msgs::msg::dds_::JointState_"
    "/RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
    "/::,10:,:,:,,"
)
JOINT_STATES_KEY = (
    "0/arm/joint_states/sensor_msgs::msg::dds_::JointState_"
    "/RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
)

# rmw_zenoh docs/design.md (Zenoh 1.x edition), verbatim
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
DESIGN_LISTENER = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
    + STRING_HASH
    + "/::,7:,:,:,,"
)
DESIGN_SERVER = (
    "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints"
    "/example_interfaces::srv::dds_::AddTwoInts_/" + ADD_TWO_INTS_HASH + "/::,10:,:,:,,"
)


# --------------------------------------------------------------------------- keys and types


def test_topic_key() -> None:
    dds = wire.dds_type_name("sensor_msgs/msg/JointState")
    assert dds == "sensor_msgs::msg::dds_::JointState_"
    assert wire.topic_key(0, "/arm/joint_states", dds, JOINT_STATE_HASH) == JOINT_STATES_KEY
    assert wire.topic_key(0, "arm/joint_states/", dds, JOINT_STATE_HASH) == JOINT_STATES_KEY
    assert (
        wire.topic_key(0, "/chatter", "std_msgs::msg::dds_::String_", STRING_HASH)
        == "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH
    )
    # design.md's service example: the service type without Request_/Response_, the service's hash
    srv = wire.dds_type_name("example_interfaces/srv/AddTwoInts")
    assert srv == "example_interfaces::srv::dds_::AddTwoInts_"
    assert (
        wire.service_key(2, "/add_two_ints", srv, ADD_TWO_INTS_HASH)
        == "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/" + ADD_TWO_INTS_HASH
    )
    assert wire.ros_type_name(srv) == "example_interfaces/srv/AddTwoInts"
    assert wire.ros_type_name("sensor_msgs::msg::dds_::JointState_") == "sensor_msgs/msg/JointState"
    assert wire.ros_type_name("not_a_ros_type") == "not_a_ros_type"
    assert wire.graph_key(0) == "@ros2_lv/0/**"
    assert wire.domain_key(3) == "3/**"
    with pytest.raises(ValueError):
        wire.topic_key(0, "/", dds, JOINT_STATE_HASH)
    with pytest.raises(ValueError):
        wire.dds_type_name("JointState")


# --------------------------------------------------------------------------- attachment


@pytest.mark.parametrize(
    ("seq", "ts"),
    [(1, 1_700_000_000_123_456_789), (2**63 - 1, 0), (-1, -(2**63)), (123456, 42)],
)
def test_attachment_matches_zenoh_ext_serialization(seq: int, ts: int) -> None:
    gid = bytes(range(0xA0, 0xB0))
    ours = wire.encode_attachment(seq, ts, gid)
    theirs = z_serialize((Int64(seq), Int64(ts), gid)).to_bytes()
    assert ours == theirs
    assert len(ours) == wire.ATTACHMENT_SIZE == 33
    assert ours[16] == 0x10
    assert z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(ours)) == (seq, ts, gid)
    assert wire.decode_attachment(theirs) == (seq, ts, gid)
    assert wire.decode_attachment(memoryview(theirs)) == (seq, ts, gid)
    assert wire.decode_attachment(bytearray(theirs)) == (seq, ts, gid)


def test_decode_attachment_rejects_other_layouts() -> None:
    gid = bytes(16)
    good = wire.encode_attachment(5, 6, gid)
    assert wire.decode_attachment(good[:-1]) is None
    assert wire.decode_attachment(good + b"\x00") is None
    assert wire.decode_attachment(good[:16] + b"\x0f" + good[17:]) is None
    assert wire.decode_attachment(b"") is None
    # the key/value layout of rmw_zenoh before #601/#605 (Jazzy <= 0.2.3)
    legacy = z_serialize(("sequence_number", Int64(5), "source_timestamp", Int64(6), "source_gid", gid)).to_bytes()
    assert wire.decode_attachment(legacy) is None
    with pytest.raises(ValueError):
        wire.encode_attachment(1, 2, bytes(15))


def test_service_reply_attachment() -> None:
    client_gid = bytes(range(16))
    request = wire.encode_attachment(7, 1_000, client_gid)
    reply = wire.reply_attachment(request, 2_000)
    assert reply is not None
    assert wire.decode_attachment(reply) == (7, 2_000, client_gid)
    assert wire.request_id(reply) == wire.request_id(request) == (client_gid, 7)
    assert wire.reply_attachment(b"junk", 1) is None
    assert wire.request_id(b"junk") is None


# --------------------------------------------------------------------------- tokens


def test_node_and_publisher_tokens() -> None:
    assert wire.node_token(0, ZID, 0, "/", "/arm", "joint_state_publisher") == NODE_TOKEN
    assert wire.node_token(0, ZID, 0, "", "/arm", "joint_state_publisher") == NODE_TOKEN
    pub = wire.entity_token(
        "MP", 0, ZID, 0, 10, "/", "/arm", "joint_state_publisher", "/arm/joint_states",
        wire.dds_type_name("sensor_msgs/msg/JointState"), JOINT_STATE_HASH, QOS_DEFAULT,
    )  # fmt: skip
    assert pub == PUB_TOKEN
    with pytest.raises(ValueError):
        wire.entity_token("NN", 0, ZID, 0, 0, "/", "/", "n", "/t", "a::b", "h", QOS_DEFAULT)


def test_design_doc_examples_rebuild() -> None:
    assert wire.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "", "", "listener") == DESIGN_LISTENER
    talker = wire.entity_token(
        "MP", 2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "", "", "talker", "/chatter",
        "std_msgs::msg::dds_::String_", STRING_HASH, Qos(depth=7),
    )  # fmt: skip
    assert talker == DESIGN_TALKER_PUB
    server = wire.entity_token(
        "SS", 2, "f9980ee0495eaafb3e38f0d19e2eae12", 0, 10, "/", "/", "add_two_ints_server", "/add_two_ints",
        "example_interfaces::srv::dds_::AddTwoInts_", ADD_TWO_INTS_HASH, wire.QOS_SERVICES,
    )  # fmt: skip
    assert server == DESIGN_SERVER


def test_parse_token_round_trip() -> None:
    node = wire.parse_token(NODE_TOKEN)
    assert node.is_node and node.kind == "NN"
    assert (node.domain, node.zid, node.node_id, node.entity_id) == (0, ZID, "0", "0")
    assert (node.enclave, node.namespace, node.node_name) == ("/", "/arm", "joint_state_publisher")
    assert node.fq_node_name == "/arm/joint_state_publisher"
    assert node.topic is None and node.qos is None
    assert wire.node_token(node.domain, node.zid, node.node_id, node.enclave, node.namespace, node.node_name) == (
        NODE_TOKEN
    )

    pub = wire.parse_token(PUB_TOKEN)
    assert pub.kind == "MP" and pub.entity_id == "10"
    assert pub.topic == "/arm/joint_states"
    assert pub.dds_type == "sensor_msgs::msg::dds_::JointState_"
    assert pub.ros_type == "sensor_msgs/msg/JointState"
    assert pub.type_hash == JOINT_STATE_HASH
    assert pub.qos == QOS_DEFAULT.adapted()
    assert pub.qos is not None and pub.qos.depth == 10
    again = wire.entity_token(
        pub.kind, pub.domain, pub.zid, pub.node_id, pub.entity_id, pub.enclave, pub.namespace, pub.node_name,
        pub.topic, pub.dds_type, pub.type_hash, pub.qos,
    )  # fmt: skip
    assert again == PUB_TOKEN

    for key in (DESIGN_LISTENER, DESIGN_TALKER_PUB, DESIGN_SERVER):
        t = wire.parse_token(key)
        assert t.key == key
    talker = wire.parse_token(DESIGN_TALKER_PUB)
    assert talker.fq_node_name == "/talker" and talker.topic == "/chatter"

    tokens = [wire.parse_token(k) for k in (NODE_TOKEN, PUB_TOKEN, DESIGN_LISTENER, DESIGN_TALKER_PUB, DESIGN_SERVER)]
    assert wire.list_nodes(tokens) == ["/arm/joint_state_publisher", "/listener"]
    assert wire.list_topics(tokens) == {
        "/arm/joint_states": ["sensor_msgs/msg/JointState"],
        "/chatter": ["std_msgs/msg/String"],
    }
    assert wire.list_services(tokens) == {"/add_two_ints": ["example_interfaces/srv/AddTwoInts"]}


@pytest.mark.parametrize(
    "bad",
    [
        "0/arm/joint_states/x/y",
        "@ros2_lv/0/zid/0/0/NN/%/%",
        "@ros2_lv/0/zid/0/0/XX/%/%/n",
        "@ros2_lv/0/zid/0/0/NN/%//n",
        "@ros2_lv/x/zid/0/0/NN/%/%/n",
        "@ros2_lv/0/zid/0/1/MP/%/%/n/%t/a::b_/h",
        "@ros2_lv/0/zid/0/1/MP/%/%/n/%t/a::b_/h/1:2",
    ],
)
def test_parse_token_rejects(bad: str) -> None:
    with pytest.raises(ValueError):
        wire.parse_token(bad)


def test_mangle() -> None:
    assert wire.mangle("/arm/joint_states") == "%arm%joint_states"
    assert wire.mangle("/") == "%"
    assert wire.mangle("") == "%"
    assert wire.demangle("%arm%joint_states") == "/arm/joint_states"


# --------------------------------------------------------------------------- QoS


def test_qos_profiles_encode() -> None:
    assert QOS_DEFAULT.encode() == "::,10:,:,:,,"
    assert QOS_SENSOR_DATA.encode() == "2::,5:,:,:,,"
    assert QOS_LATCHED.encode() == ":1:,1:,:,:,,"
    assert QOS_CLOCK.encode() == "2::,1:,:,:,,"
    # every field equal to rmw_zenoh's default is left empty
    assert ZENOH_DEFAULT_QOS.encode() == "::,:,:,:,,"
    assert Qos(depth=42).encode() == "::,:,:,:,,"
    assert Qos(depth=0, history=History.SYSTEM_DEFAULT, reliability=Reliability.SYSTEM_DEFAULT).encode() == (
        "::,:,:,:,,"
    )
    assert Qos(history=History.KEEP_ALL, depth=1000).encode() == "::2,1000:,:,:,,"
    assert Qos(deadline=(0, 100_000_000), liveliness=Liveliness.MANUAL_BY_TOPIC, lease=(2, 0)).encode() == (
        "::,10:0,100000000:,:3,2,0"
    )
    # same seconds as the infinite default: only the nanoseconds are written
    assert Qos(lifespan=(9223372036, 5)).encode() == "::,10:,:,5:,,"


@pytest.mark.parametrize(
    "q",
    [
        QOS_DEFAULT,
        QOS_SENSOR_DATA,
        QOS_LATCHED,
        QOS_CLOCK,
        ZENOH_DEFAULT_QOS,
        Qos(history=History.KEEP_ALL, depth=0),
        Qos(durability=Durability.BEST_AVAILABLE, reliability=Reliability.BEST_AVAILABLE),
        Qos(deadline=(1, 2), lifespan=(3, 4), liveliness=Liveliness.MANUAL_BY_TOPIC, lease=(5, 6)),
    ],
)
def test_qos_round_trip(q: Qos) -> None:
    decoded = Qos.decode(q.encode())
    assert decoded == q.adapted()
    assert decoded.encode() == q.encode()


def test_qos_decode() -> None:
    q = Qos.decode("::,10:,:,:,,")
    assert q == Qos(
        Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 10,
        wire.DURATION_INFINITE, wire.DURATION_INFINITE, Liveliness.AUTOMATIC, wire.DURATION_INFINITE,
    )  # fmt: skip
    assert isinstance(q.reliability, Reliability)
    assert Qos.decode("2:1:,1:,:,:,,") == Qos(
        Reliability.BEST_EFFORT, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1,
        wire.DURATION_INFINITE, wire.DURATION_INFINITE, Liveliness.AUTOMATIC, wire.DURATION_INFINITE,
    )  # fmt: skip
    for bad in ("", "1:2:1,10", "::,10:,:,:,", "::,10:,:,:,,:", "x::,10:,:,:,,", "::,-1:,:,:,,"):
        with pytest.raises(ValueError):
            Qos.decode(bad)


# --------------------------------------------------------------------------- gid


def test_entity_gid() -> None:
    # computed with rmw_zenoh's simplified_xxhash3.cpp (low64 then high64, little endian)
    assert wire.entity_gid(DESIGN_LISTENER).hex() == "49877999dacb858702d11ac823785912"
    assert wire.entity_gid(DESIGN_TALKER_PUB).hex() == "ac170f31eadcd9ff0cd86d7a17907d1c"
    gid = wire.entity_gid(PUB_TOKEN)
    assert len(gid) == 16 and wire.parse_token(PUB_TOKEN).gid == gid
    assert wire.entity_gid(NODE_TOKEN) != gid


# --------------------------------------------------------------------------- live


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _peer(listen: list[str], connect: list[str]) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", str(listen).replace("'", '"'))
    c.insert_json5("connect/endpoints", str(connect).replace("'", '"'))
    return zenoh.open(c)


def test_live_token_and_attachment() -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    a = _peer([endpoint], [])
    b: zenoh.Session | None = None
    try:
        zid = str(a.info.zid())
        dds = wire.dds_type_name("sensor_msgs/msg/JointState")
        node_key = wire.node_token(0, zid, 0, "/", "/arm", "joint_state_publisher")
        pub_key = wire.entity_token(
            "MP", 0, zid, 0, 1, "/", "/arm", "joint_state_publisher", "/arm/joint_states", dds,
            JOINT_STATE_HASH, QOS_DEFAULT,
        )  # fmt: skip
        gid = wire.entity_gid(pub_key)
        node_tok = a.liveliness().declare_token(node_key)
        pub_tok = a.liveliness().declare_token(pub_key)
        publisher = a.declare_publisher(wire.topic_key(0, "/arm/joint_states", dds, JOINT_STATE_HASH))

        b = _peer([], [endpoint])
        lock = threading.Lock()
        tokens: list[wire.Token] = []
        samples: list[tuple[str, bytes, tuple[int, int, bytes] | None]] = []

        def on_token(s: zenoh.Sample) -> None:
            if s.kind == zenoh.SampleKind.PUT:
                with lock:
                    tokens.append(wire.parse_token(str(s.key_expr)))

        def on_sample(s: zenoh.Sample) -> None:
            att = s.attachment
            decoded = None if att is None else wire.decode_attachment(att.to_bytes())
            with lock:
                samples.append((str(s.key_expr), s.payload.to_bytes(), decoded))

        lsub = b.liveliness().declare_subscriber(wire.graph_key(0), on_token, history=True)
        sub = b.declare_subscriber(wire.domain_key(0), on_sample)

        payload = b"\x00\x01\x00\x00" + bytes(8)
        deadline = time.monotonic() + 10.0
        seq = 0
        while time.monotonic() < deadline:
            seq += 1
            publisher.put(payload, attachment=wire.encode_attachment(seq, time.time_ns(), gid))
            with lock:
                if len(tokens) >= 2 and samples:
                    break
            time.sleep(0.05)

        with lock:
            got_tokens, got_samples = list(tokens), list(samples)
        assert {t.key for t in got_tokens} == {node_key, pub_key}
        assert wire.list_nodes(got_tokens) == ["/arm/joint_state_publisher"]
        assert wire.list_topics(got_tokens) == {"/arm/joint_states": ["sensor_msgs/msg/JointState"]}
        pub_token = next(t for t in got_tokens if t.kind == "MP")
        assert pub_token.zid == zid and pub_token.gid == gid
        key, body, att = got_samples[0]
        assert key == JOINT_STATES_KEY and body == payload
        assert att is not None
        assert att[0] >= 1 and att[2] == gid
        assert abs(att[1] - time.time_ns()) < 30 * 10**9
        sub.undeclare()
        lsub.undeclare()
        publisher.undeclare()
        pub_tok.undeclare()
        node_tok.undeclare()
    finally:
        if b is not None:
            b.close()
        a.close()
