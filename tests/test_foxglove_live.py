"""Foxglove, live (``hilsim up … --foxglove PORT``, hilsim.record.foxglove_live): a client written here to
Foxglove's WebSocket protocol spec (the ``websockets`` package; JSON ``advertise``/``subscribe``, binary
message-data frames) subscribes to ``/arm/joint_states``, ``/tf``, ``/tf_static`` and ``/arm/robot_description``
while the arm moves to a target. Each message is decoded twice, by the real ``mcap_ros2`` decoder built from
the schema the server advertised (``ros2msg``) and by ``rosbags``' own ROS 2 types, and compared with the
physics truth of the same step: ``truth/joint_states`` at the message's stamp, from the run's bag.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

WANTED = ("/arm/joint_states", "/tf", "/tf_static", "/arm/robot_description")


def _decoders(channels: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """mcap_ros2's CDR decoder per topic, from the schema the server advertised."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    out = {}
    for topic, c in channels.items():
        assert c["encoding"] == "cdr" and c["schemaEncoding"] == "ros2msg", c
        schema = Schema(id=1, name=c["schemaName"], encoding="ros2msg", data=c["schema"].encode())
        out[topic] = DecoderFactory().decoder_for("cdr", schema)
    return out


def _truth(run: Path) -> dict[int, list[float]]:
    """The arm's true joint positions per stamp [ns], from the run's bag (its rosbag2 MCAP files)."""
    from mcap_ros2.reader import read_ros2_messages

    out: dict[int, list[float]] = {}
    for f in sorted((run / "bag").glob("*.mcap")):
        for m in read_ros2_messages(str(f), topics=["/arm/truth/joint_states"]):
            s = m.ros_msg.header.stamp
            out[s.sec * 1_000_000_000 + s.nanosec] = list(m.ros_msg.position)
    return out


def test_the_server_speaks_the_protocol_and_gives_latched_topics_to_late_subscribers() -> None:
    """FoxgloveLive alone, samples of the key table's types: a client written to the spec gets the channels
    advertised with their ros2msg schemas, a latched topic's last sample on subscribing, then live ones."""
    import websockets.sync.client as ws_client

    from hilsim.core import msgs
    from hilsim.core.keys import Keys
    from hilsim.record.foxglove_live import FoxgloveLive

    keys = Keys("hilsim", "arm")
    js_key, urdf_key = keys.topic("joint_states"), keys.topic("robot_description")
    fox = FoxgloveLive("127.0.0.1", 0)
    try:
        js = msgs.JointState(name=["joint_1"], position=[0.25], velocity=[0.0], effort=[0.0])
        fox.add(urdf_key, msgs.encode(msgs.String(data="<robot name='r'/>")), 1)
        with ws_client.connect(fox.url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],  # type: ignore[list-item]
                               open_timeout=20) as ws:
            fox.add(js_key, msgs.encode(js), 2)
            channels: dict[str, dict[str, Any]] = {}
            while len(channels) < 2:
                m = ws.recv(timeout=20)
                if isinstance(m, str) and json.loads(m).get("op") == "advertise":
                    channels.update({c["topic"]: c for c in json.loads(m)["channels"]})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/arm/robot_description"]["id"]},
                {"id": 2, "channelId": channels["/arm/joint_states"]["id"]}]}))
            got: dict[int, bytes] = {}
            end = time.monotonic() + 20
            while 2 not in got and time.monotonic() < end:
                if 1 in got:
                    fox.add(js_key, msgs.encode(js), 3)
                m = ws.recv(timeout=20)
                if isinstance(m, bytes) and m[0] == 1:
                    sid, _ = struct.unpack_from("<IQ", m, 1)
                    got.setdefault(sid, bytes(m[13:]))
        dec = _decoders(channels)
        assert dec["/arm/robot_description"](got[1]).data == "<robot name='r'/>"
        assert list(dec["/arm/joint_states"](got[2]).position) == [0.25]
    finally:
        fox.close()
