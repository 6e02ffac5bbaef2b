"""Foxglove, live (``hilsim up … --foxglove PORT``, hilsim.record.foxglove_live): a client written here to
Foxglove's WebSocket protocol spec (the ``websockets`` package; JSON ``advertise``/``subscribe``, binary
message-data frames) subscribes to ``/arm/joint_states``, ``/tf``, ``/tf_static`` and ``/arm/robot_description``
while the arm moves to a target. Each message is decoded twice, by the real ``mcap_ros2`` decoder built from
the schema the server advertised (``ros2msg``) and by ``rosbags``' own ROS 2 types, and compared with the
physics truth of the same step: ``truth/joint_states`` at the message's stamp, from the run's bag.
"""

from __future__ import annotations

import json
import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from hilsim.core import transport
from hilsim.core.scenario import load_scenario
from tests.util import LEAN, REPO, finish, foxglove_subscribe, up

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


@pytest.mark.e2e
@pytest.mark.timeout(1200)
def test_a_foxglove_client_sees_the_arm_as_the_physics_has_it(tmp_path: Path) -> None:
    import websockets.sync.client as ws_client
    from rosbags.typesys import Stores, get_typestore

    run = tmp_path / "run"
    port = transport.free_port()
    # the lean arm (half the rates), and a recording's loss said, not failed: a realtime run's recorder that
    # falls behind on 2 busy cores is the recording's matter (hilsim bench loss); this is the live feed's
    p = up(LEAN, "--interactive", "--allow-loss", "--foxglove", str(port), "--out", str(run), "--wait", "600")
    lines: list[str] = []
    url = ""
    assert p.stdout is not None
    rest: list[str] = []
    reader = threading.Thread(target=lambda: rest.extend(p.stdout), daemon=True)  # type: ignore[arg-type]
    try:
        for line in p.stdout:
            lines.append(line)
            if line.startswith("foxglove: "):
                url = line.split(" ", 1)[1].strip()
                break
        assert url == f"ws://127.0.0.1:{port}", "".join(lines)  # loopback by default
    except BaseException:
        os.killpg(p.pid, signal.SIGKILL)  # no run left behind by a failed start
        finish(p, 60)
        raise
    reader.start()
    target = load_scenario("arm").task.targets[0]
    got: dict[str, list[bytes]] = {t: [] for t in WANTED}
    channels: dict[str, dict[str, Any]] = {}
    goal: dict[str, Any] = {}
    try:
        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],  # type: ignore[list-item]
                               max_size=None, open_timeout=60) as ws:
            subs: dict[int, str] = {}
            near, jdec = False, None
            end = time.monotonic() + 400
            while time.monotonic() < end:
                msg = ws.recv(timeout=60)
                if isinstance(msg, str):
                    j = json.loads(msg)
                    if j.get("op") != "advertise":
                        continue
                    foxglove_subscribe(ws, j, WANTED, channels, subs)
                    if "/arm/joint_states" in channels and "goal" not in goal:  # the arm moves while we watch
                        def send() -> None:
                            goal["out"] = subprocess.run(
                                [sys.executable, "-m", "hilsim.cli", "goal", "arm", "--joints", *map(str, target),
                                 "--run", str(run)], capture_output=True, text=True, timeout=300, cwd=REPO)
                        goal["goal"] = threading.Thread(target=send, daemon=True)
                        goal["goal"].start()
                    continue
                assert msg[0] == 0x01, msg[:1]  # message data: opcode, subscription id, log time, payload
                sid, _log_ns = struct.unpack_from("<IQ", msg, 1)
                got[subs[sid]].append(bytes(msg[13:]))
                if subs[sid] == "/arm/joint_states":  # how far the client has seen the arm go
                    jdec = jdec or _decoders({"j": channels["/arm/joint_states"]})["j"]
                    near = abs(jdec(msg[13:]).position[0] - target[0]) < 0.02
                # the goal ended, and this client has watched the arm reach it (its stream may lag behind)
                if "goal" in goal and not goal["goal"].is_alive() and near and len(got["/tf"]) > 20:
                    break
            else:
                raise AssertionError(f"the goal did not end while watching: {goal}")
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
        try:  # the reader thread takes what it prints (one reader of the pipe, not two)
            p.wait(300)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(30)
            raise AssertionError("hilsim up still running 300 s after SIGINT; it printed:\n"
                                 + "".join(lines + rest)) from None
        reader.join(30)
    text = "".join(lines + rest)
    assert "result: OK" in text, text
    assert goal["out"].returncode == 0, goal["out"]
    assert not (run / "foxglove.json").exists()  # the server stopped with the run

    dec = _decoders(channels)
    assert channels["/arm/joint_states"]["schemaName"] == "sensor_msgs/msg/JointState"
    assert channels["/tf"]["schemaName"] == "tf2_msgs/msg/TFMessage"
    # latched topics: given to a subscriber that came after they were put, as a transient-local publisher does
    assert got["/tf_static"] and got["/arm/robot_description"], {t: len(v) for t, v in got.items()}
    urdf = dec["/arm/robot_description"](got["/arm/robot_description"][0]).data
    assert "<robot" in urdf and "joint_1" in urdf
    store = get_typestore(Stores.ROS2_JAZZY)
    truth = _truth(run)
    matched, moved = 0, []
    for payload in got["/arm/joint_states"]:
        m = dec["/arm/joint_states"](payload)
        other = store.deserialize_cdr(payload, "sensor_msgs/msg/JointState")  # another implementation, same bytes
        assert list(other.position) == list(m.position) and other.name == list(m.name)
        t = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if t not in truth:
            continue
        matched += 1
        err = max(abs(a - b) for a, b in zip(m.position, truth[t], strict=True))
        assert err < 1e-3, (t, list(m.position), truth[t])  # the encoder's resolution and noise, no more
        moved.append(truth[t][0])
    assert matched >= 100, (matched, len(got["/arm/joint_states"]))
    assert max(moved) - min(moved) > 0.1, "the arm did not move while the client watched"
    # /tf: the first joint's transform is a rotation about z by the true joint_1 of the same step
    checked = 0
    for payload in got["/tf"]:
        m = dec["/tf"](payload)
        other = store.deserialize_cdr(payload, "tf2_msgs/msg/TFMessage")
        assert [x.child_frame_id for x in other.transforms] == [x.child_frame_id for x in m.transforms]
        for x in m.transforms:
            if x.child_frame_id != "shoulder_link":
                continue
            t = x.header.stamp.sec * 1_000_000_000 + x.header.stamp.nanosec
            if t in truth:
                r = x.transform.rotation
                angle = 2 * math.atan2(r.z, r.w)
                d = (angle - truth[t][0] + math.pi) % (2 * math.pi) - math.pi
                assert abs(d) < 1e-6, (t, angle, truth[t][0])
                checked += 1
    assert checked >= 10, (checked, len(got["/tf"]))
    print(f"foxglove: {matched} joint states and {checked} transforms matched the truth of their step; "
          f"joint_1 moved over {max(moved) - min(moved):.3f} rad while watched")


def test_the_server_speaks_the_protocol_and_gives_latched_topics_to_late_subscribers() -> None:
    """FoxgloveLive alone, samples of the key table's types: a client written to the spec gets the channels
    advertised with their ros2msg schemas, a latched topic's last sample on subscribing, another's first sample
    (put with its advertisement, before anyone could subscribe) while it is its only one, then live ones."""
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
                    fox.add(js_key, msgs.encode(msgs.JointState(name=["joint_1"], position=[0.5], velocity=[0.0],
                                                                effort=[0.0])), 3)
                m = ws.recv(timeout=20)
                if isinstance(m, bytes) and m[0] == 1:
                    sid, _ = struct.unpack_from("<IQ", m, 1)
                    got.setdefault(sid, bytes(m[13:]))
        dec = _decoders(channels)
        assert dec["/arm/robot_description"](got[1]).data == "<robot name='r'/>"
        assert list(dec["/arm/joint_states"](got[2]).position) == [0.25]  # the first, not the next (0.5)
    finally:
        fox.close()
