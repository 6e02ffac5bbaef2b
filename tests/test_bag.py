"""The recorder's rosbag2 bag (MCAP), ``hilsim play``, ``hilsim bag info|recover`` and ``hilsim export``.

Unit: a bag of synthetic samples read back by two independent readers (rosbags, mcap_ros2) and ours;
a killed writer's bag recovered; the logger's bag holding exactly what it recorded (clean, lossy,
composed, off); the run summary's bag line. End to end: a short arm run and a short rover run through
``hilsim up`` read back by both readers and compared with the ``.rrd``; the arm's sensor stream
played into its controller alone gives the same commands bit for bit; export of the run's ``.rrd``."""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
import warnings
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg
from util import finish, up

from hilsim.cli import main as cli
from hilsim.core import msgs, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.recording import contents, disable_analytics, recording_files
from hilsim.core.ros2 import wire
from hilsim.core.scenario import load_scenario
from hilsim.record.bag import BagError, BagWriter, qos_profiles
from hilsim.record.bag_read import key_counts, open_bag, read_file, recover_bag, write_metadata

with warnings.catch_warnings():  # mcap_ros2.reader warns on import that it will move
    warnings.simplefilter("ignore")
    from mcap_ros2.reader import read_ros2_messages

REPO = Path(__file__).resolve().parent.parent
JOINTS = [f"joint_{i}" for i in range(1, 7)]
KEYS = Keys()
T0 = 1_700_000_000_000_000_000  # a receive time (ns since the epoch)


def _js(t: int, k: int) -> msgs.JointState:
    return msgs.JointState(header=msgs.header(t, "world"), name=list(JOINTS), position=[0.01 * k + i for i in range(6)],
                           velocity=[0.5] * 6, effort=[-0.25 * k] * 6)


def _plain(x: Any) -> Any:
    """A decoded message of either reader as plain data (rosbags: dataclasses and numpy arrays;
    mcap_ros2: namespaces with __slots__)."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, bytes | bytearray):
        return list(x)
    if hasattr(x, "__dataclass_fields__"):
        return {f: _plain(getattr(x, f)) for f in x.__dataclass_fields__ if f != "__msgtype__" and not f.isupper()}
    if hasattr(x, "__slots__") and not isinstance(x, int | float | str | bool):  # constants (OK, WARN…) aside
        return {f: _plain(getattr(x, f)) for f in x.__slots__ if not f.isupper()}
    return x


def _rosbags_read(bag: Path) -> list[tuple[str, str, int, Any]]:
    """Every message of a bag through rosbags' Reader and its typestore: (topic, type, log time, value)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    out = []
    with Reader(bag) as r:
        for c in r.connections:  # hilsim's own types, from the bag's schemas
            if c.msgtype not in store.fielddefs:
                store.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        for c, t, raw in r.messages():
            out.append((c.topic, c.msgtype, t, store.deserialize_cdr(raw, c.msgtype)))
    return out


def _mcap_read(path: Path) -> list[Any]:
    return list(read_ros2_messages(str(path)))


# ---------------------------------------------------------------------------------------- unit
def _write_synthetic(d: Path) -> list[dict[str, Any]]:
    """A bag of 2 flushes: joint states from two writers, clock without attachment, cmd_vel (no
    stamp), tf (stamped, and one without transforms), and one garbage payload on imu."""
    w = BagWriter(d)
    a, b, c = transport.new_gid(), transport.new_gid(), transport.new_gid()
    sent: list[dict[str, Any]] = []

    def add(key: str, data: bytes, log: int, stamp: int | None, seq: int = 0, gid: bytes | None = None) -> None:
        w.add(key, data, log, seq, gid)
        sent.append({"key": key, "data": data, "log": log, "pub": log if stamp is None else stamp, "seq": seq,
                     "gid": gid})

    for k in range(120):
        t, log = k * 1_000_000, T0 + k * 10_000
        add(KEYS.topic("joint_states"), msgs.encode(_js(t, k)), log, t, k // 2 + 1, a if k % 2 else b)
        add(KEYS.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(t))), log + 1, t)
        add(KEYS.topic("cmd_vel"), msgs.encode(msgs.Twist(linear=msgs.Vector3(x=0.1 * k))), log + 2, None, k + 1, c)
        if k % 10 == 0:
            tf = msgs.TFMessage(transforms=[msgs.TransformStamped(header=msgs.header(t + 7, "world"),
                                                                  child_frame_id="base_link")])
            add(KEYS.tf, msgs.encode(tf), log + 3, t + 7, k + 1, c)
            add(KEYS.tf, msgs.encode(msgs.TFMessage()), log + 4, None, k + 2, c)
        if k == 60:
            w.flush()
            add(KEYS.topic("imu"), b"\x00\x01\x00\x00garbage", log + 5, None, 999, a)
    w.close()
    write_metadata(d)
    return sent


def test_a_bag_reads_back_with_rosbags_mcap_ros2_and_ours(tmp_path: Path) -> None:
    """Raw bytes kept; channels, schemas, QoS, times, sequence numbers and writers as documented."""
    bag = tmp_path / "bag"
    sent = _write_synthetic(bag)
    garbage = next(s for s in sent if s["data"].endswith(b"garbage"))
    # ours: every message in order with its bytes, times, sequence number and writer's gid
    got = list(open_bag(bag).messages())
    assert len(got) == len(sent)
    for m, s in zip(got, sent, strict=True):
        assert (m.key, m.data, m.log_ns, m.pub_ns, m.seq, m.gid) == (s["key"], s["data"], s["log"], s["pub"],
                                                                        s["seq"], s["gid"])
    # metadata.yaml as rosbag2 (version 9) writes it
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    logs = [s["log"] for s in sent]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["bag_0.mcap"] and meta["message_count"] == len(sent)
    assert meta["starting_time"]["nanoseconds_since_epoch"] == min(logs)
    assert meta["duration"]["nanoseconds"] == max(logs) - min(logs)
    assert meta["compression_format"] == "" and meta["compression_mode"] == ""
    by_topic = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert by_topic["/arm/joint_states"]["message_count"] == 120 and by_topic["/arm/imu"]["message_count"] == 1
    assert by_topic["/tf"]["topic_metadata"]["type"] == "tf2_msgs/msg/TFMessage"
    # rosbags: opens the directory, agrees on types, hashes and QoS, decodes every valid message
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as r:
        assert r.message_count == len(sent)
        conns = {c.topic: c for c in r.connections}
        for c in conns.values():
            assert c.digest == store.hash_rihs01(c.msgtype), c.topic
            assert c.ext.serialization_format == "cdr"
        assert conns["/clock"].ext.offered_qos_profiles[0].reliability.name == "BEST_EFFORT"
        assert conns["/arm/joint_states"].ext.offered_qos_profiles[0].reliability.name == "RELIABLE"
        assert conns["/arm/joint_states"].ext.offered_qos_profiles[0].depth == 10
        decoded = Counter()
        for c, t, raw in r.messages(connections=[x for x in r.connections if x.topic != "/arm/imu"]):
            decoded[c.topic] += 1
            m = store.deserialize_cdr(raw, c.msgtype)
            if c.topic == "/arm/cmd_vel":
                assert m.linear.x == pytest.approx(0.1 * ((t - T0 - 2) // 10_000))
            if c.topic == "/arm/joint_states":
                last = m
        assert decoded == {"/clock": 120, "/arm/cmd_vel": 120, "/tf": 24, "/arm/joint_states": 120}
        assert last.position.tolist() == _js(0, 119).position and last.header.stamp.nanosec == 119_000_000
        # the payload that decodes as nothing: kept as it arrived
        assert [raw for _, _, raw in r.messages(connections=[conns["/arm/imu"]])] == [garbage["data"]]
    # mcap_ros2: the ros2 profile, schemas and channel metadata as rosbag2 writes them
    valid = [s for s in sent if s is not garbage]
    seen = list(read_ros2_messages(str(bag / "bag_0.mcap"), topics=["/arm/joint_states", "/clock", "/arm/cmd_vel",
                                                                      "/tf"]))
    assert len(seen) == len(valid)
    for m, s in zip(seen, valid, strict=True):
        assert m.schema.encoding == "ros2msg" and m.channel.message_encoding == "cdr"
        assert m.channel.metadata["hilsim_key"] == s["key"]
        assert m.channel.metadata["topic_type_hash"] == s["key"].rsplit("/", 1)[1]
        assert isinstance(yaml.safe_load(m.channel.metadata["offered_qos_profiles"]), list)
        assert (m.log_time_ns, m.publish_time_ns, m.sequence_count) == (s["log"], s["pub"], s["seq"])
    assert {m.schema.name for m in seen} == {"sensor_msgs/msg/JointState", "rosgraph_msgs/msg/Clock",
                                              "geometry_msgs/msg/Twist", "tf2_msgs/msg/TFMessage"}
    # the QoS of the latched topics; chunks of at most chunk_bytes
    assert [qos_profiles(t)[0]["durability"] for t in ("/tf_static", "/arm/robot_description", "/tf")] == [
        "transient_local", "transient_local", "volatile"]
    small = BagWriter(tmp_path / "small", chunk_bytes=2000)
    for k in range(50):
        small.add(KEYS.topic("joint_states"), msgs.encode(_js(k, k)), T0 + k)
    small.close()
    from mcap.reader import make_reader

    with open(small.path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 5 and all(c.uncompressed_size <= 2000 for c in chunks)


def test_play_orders_by_sim_time_as_the_samples_appeared(tmp_path: Path) -> None:
    """Stamped samples at their stamp; cmd_vel (no stamp) and a trajectory (stamped with its future
    start) at the latest stamp received before them, a trajectory no later than 20 ms before its start;
    --clock skips the recorded /clock; --keys by topic glob or key expression; --domain moves the keys."""
    from hilsim.tools.recording.play import Selector, schedule

    w = BagWriter(tmp_path / "bag")
    js, traj, cmd = KEYS.topic("joint_states"), KEYS.topic("joint_trajectory"), KEYS.topic("cmd_vel")
    for k in range(30):
        t = k * 1_000_000
        w.add(KEYS.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(t))), T0 + 3 * k)
        w.add(js, msgs.encode(_js(t, k)), T0 + 3 * k + 1)
        if k == 10:  # planned at 10 ms to start at 30 ms (the planner's lead)
            w.add(traj, msgs.encode(msgs.JointTrajectory(header=msgs.header(30_000_000), joint_names=JOINTS)),
                  T0 + 3 * k + 2)
        if k == 15:
            w.add(cmd, msgs.encode(msgs.Twist()), T0 + 3 * k + 2)
        if k == 27:  # planned at 5 ms to start at 25 ms, received by a busy recorder only after 27 ms
            w.add(traj, msgs.encode(msgs.JointTrajectory(header=msgs.header(25_000_000), joint_names=JOINTS)),
                  T0 + 3 * k + 2)
    w.close()
    bag = open_bag(tmp_path / "bag")
    items = schedule(bag, Selector(None), None, skip_clock=False)
    order = [(it.topic, it.sim_ns) for it in items]
    assert order.index(("/arm/joint_trajectory", 10_000_000)) == order.index(("/arm/joint_states", 10_000_000)) + 1
    assert order.index(("/arm/cmd_vel", 15_000_000)) == order.index(("/arm/joint_states", 15_000_000)) + 1
    # …but never later than the planner's lead (20 ms) before its start
    assert order.index(("/arm/joint_trajectory", 5_000_000)) == order.index(("/arm/joint_states", 5_000_000)) + 1
    assert [s for _, s in order] == sorted(s for _, s in order) and len(items) == 63
    only = schedule(bag, Selector("/arm/joint_*,0/clock/**"), 7, skip_clock=True)
    assert {it.topic for it in only} == {"/arm/joint_states", "/arm/joint_trajectory"}
    assert {it.key.split("/")[0] for it in only} == {"7"} and len(only) == 32
    assert {it.topic for it in schedule(bag, Selector("0/clock/**"), None, skip_clock=False)} == {"/clock"}


# a process that writes 5 batches of 300 samples, flushing each to the file as the recorder does,
# then is killed with SIGKILL: no summary, no footer, no metadata.yaml
KILLED = """
import os, signal, sys
from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.record.bag import BagWriter
keys, gid = Keys(), bytes(range(16))
w = BagWriter(sys.argv[1])
n = 0
for b in range(5):
    for k in range(300):
        n += 1
        w.add(keys.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(n * 1000))), 10**18 + n, n, gid)
    w.flush()
os.kill(os.getpid(), signal.SIGKILL)
"""


def _killed_bag(d: Path) -> None:
    p = subprocess.run([sys.executable, "-c", KILLED, str(d)], capture_output=True, text=True, timeout=60)
    assert p.returncode == -signal.SIGKILL, p.stderr


def _last_chunk_at(path: Path) -> int:
    """The offset of the last chunk record of an MCAP file (walking its records)."""
    raw, pos, last = path.read_bytes(), 8, -1
    while pos + 9 <= len(raw):
        op, length = struct.unpack_from("<BQ", raw, pos)
        last = pos if op == 0x06 else last
        pos += 9 + length
    return last


def test_a_killed_writers_bag_is_recovered(tmp_path: Path, capsys: Any) -> None:
    bag = tmp_path / "bag"
    _killed_bag(bag)
    f = bag / "bag_0.mcap"
    assert not (bag / "metadata.yaml").exists() and not read_file(f).complete
    with pytest.raises((FileNotFoundError, ReaderError)):  # no metadata.yaml: rosbag2 readers refuse it
        Reader(bag).open()
    cut = tmp_path / "cut"
    shutil.copytree(bag, cut)
    os.truncate(cut / "bag_0.mcap", _last_chunk_at(cut / "bag_0.mcap") + 100)  # into its last chunk
    # whole: every message, with its sequence number and writer, and a metadata.yaml rosbags reads
    (r,) = recover_bag(bag)
    assert r.rewritten and r.messages == 1500
    again = read_file(f)
    assert again.complete
    ms = list(again.messages())
    assert [m.seq for m in ms] == list(range(1, 1501)) and {m.gid for m in ms} == {bytes(range(16))}
    assert [m.pub_ns for m in ms] == [n * 1000 for n in range(1, 1501)]
    with Reader(bag) as rd:
        assert rd.message_count == 1500 and sum(1 for _ in rd.messages()) == 1500
    before = f.read_bytes()
    assert recover_bag(bag)[0].rewritten is False and f.read_bytes() == before  # complete: left alone
    # cut in its last chunk: the four whole chunks, by the command
    assert cli(["bag", "recover", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "recovered, 1200 messages" in out and "metadata.yaml: written" in out
    with Reader(cut) as rd:
        assert sum(1 for _ in rd.messages()) == 1200
    # not a bag: refused, left as it was
    junk = tmp_path / "junk" / "bag_0.mcap"
    junk.parent.mkdir()
    junk.write_bytes(b"\x00" * 4096)
    with pytest.raises(BagError, match="not an MCAP file"):
        recover_bag(junk.parent)
    assert junk.read_bytes() == b"\x00" * 4096


def test_bag_tools_say_what_is_wrong_in_one_line(tmp_path: Path, capsys: Any, router: str) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a bag")
    for argv in (["bag", "info", str(tmp_path / "nope")], ["bag", "recover", str(tmp_path / "nope")],
                 ["play", str(tmp_path / "nope")], ["play", str(junk)], ["bag", "info", str(junk)],
                 ["export", str(tmp_path / "nope"), "--to", "csv"]):
        assert cli(argv) == 1, argv
        err = capsys.readouterr().err
        assert err.startswith(f"hilsim {argv[0]}") and err.count("\n") == 1, (argv, err)
    # an incomplete bag: shown as far as it is whole, and said so
    _killed_bag(tmp_path / "killed")
    assert cli(["bag", "info", str(tmp_path / "killed")]) == 0
    out = capsys.readouterr().out
    assert "Messages:          1500" in out and "INCOMPLETE:" in out and "hilsim bag recover" in out
    assert cli(["play", str(tmp_path / "killed"), "--rate", "0", "--delay", "0", "--connect", router]) == 0
    err = capsys.readouterr().err
    assert "incomplete (its recorder was killed?): playing the 1500 messages that are whole" in err, err
    assert "played 1500 messages" in err


def test_a_restarted_recorder_makes_the_killed_ones_bag_whole_and_goes_on_in_the_next_file(
        scenario: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from hilsim.services.logger import LoggerService

    run = tmp_path / "run"
    _killed_bag(run / "bag")
    monkeypatch.setenv("HILSIM_RESTART", "1")
    svc = LoggerService(scenario("arm", {"logger.run_dir": str(run)}))
    w = svc._open_bag()
    assert w.path == run / "bag" / "bag_1.mcap" and read_file(run / "bag" / "bag_0.mcap").complete
    w.add(KEYS.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(1))), T0)
    w.close()
    write_metadata(run / "bag")
    with Reader(run / "bag") as r:  # one bag of two files
        assert r.message_count == 1501 and sum(1 for _ in r.messages()) == 1501


def test_a_failing_bag_is_a_fault_and_the_recording_goes_on(scenario: Any, session: Any, run_service: Any,
                                                             tmp_path: Path) -> None:
    """The bag's disk full: a fault said once, the .rrd goes on, the summary shows bagged < recorded."""
    key = KEYS.clock

    def body(svc: Any) -> None:
        def full(*_: Any) -> Any:
            raise OSError(28, "No space left on device")

        svc.bag.flush = full
        pub = session.declare_publisher(key)
        try:
            end = time.monotonic() + 10
            while not pub.matching_status.matching:
                assert time.monotonic() < end
                time.sleep(0.01)
            for k in range(5):
                pub.put(msgs.encode(msgs.Clock(clock=msgs.stamp(k))), attachment=transport.attachment_bytes(k + 1, gid))
            end = time.monotonic() + 10
            while svc.counts_in[key] < 5:
                assert time.monotonic() < end
                time.sleep(0.01)
        finally:
            pub.undeclare()

    gid = transport.new_gid()
    run = tmp_path / "run"
    svc = _logger_run(scenario, session, run_service, run, {}, body)
    c = json.loads((run / "record_summary.json").read_text())[key]
    assert c["received"] == c["recorded"] == 5 and c["bagged"] == 0
    # two faults: the bag stopped (once, at the first batch), and the counts at exit
    assert svc.errors == 2 and svc.last_error == "recorded 5 messages but bagged 0", (svc.errors, svc.last_error)


def _logger_run(scenario: Any, session: Any, run_service: Any, run_dir: Path, overrides: dict[str, Any],
                body: Any) -> Any:
    from hilsim.services.logger import LoggerService

    # the unbatched path: the test's own publishers announce nothing, so only `**` takes them
    svc = LoggerService(scenario("arm", {"logger.run_dir": str(run_dir), "logger.batch": 0, **overrides}))
    st = run_service(svc)
    with st:
        body(svc)
    assert st.rc == 0
    return svc


def test_the_logger_bags_exactly_what_it_records(scenario: Any, session: Any, run_service: Any,
                                                 tmp_path: Path) -> None:
    """Realtime, with losses (a full queue): per key, received == recorded == bagged == messages in
    the .mcap; payloads as they arrived (garbage too); each sample's sequence number and writer;
    a composed service's message object bagged as msgs.encode's bytes."""
    keys = KEYS
    js_key, clock_key = keys.topic("joint_states"), keys.clock
    gid = transport.new_gid()
    sent: dict[int, bytes] = {}

    def body(svc: Any) -> None:
        pub = session.declare_publisher(js_key)
        pub_clock = session.declare_publisher(clock_key)
        try:
            end = time.monotonic() + 10
            while not (pub.matching_status.matching and pub_clock.matching_status.matching):
                assert time.monotonic() < end, "the logger's subscriber"
                time.sleep(0.01)
            for seq in range(1, 41):
                data = msgs.encode(_js(seq * 1_000_000, seq)) if seq != 7 else b"\x00\x01\x00\x00junk"
                sent[seq] = data
                pub.put(data, attachment=transport.attachment_bytes(seq, gid))
            pub_clock.put(msgs.encode(msgs.Clock(clock=msgs.stamp(5))))  # no attachment
            local = msgs.Clock(clock=msgs.stamp(123))
            svc._on_local(keys.sync("controller"), local, transport.Attachment(3, 0, gid))
            end = time.monotonic() + 10
            # the clock too: it comes from another publisher, so it may arrive after the 40th joint
            # state, and once the queue is cut to 3 below it would be dropped
            while svc.counts_in[js_key] < 40 or svc.counts_in[clock_key] < 1:
                assert time.monotonic() < end, "the samples"
                time.sleep(0.01)
            svc.queue_limit = 3  # a stalled worker and a full queue: the rest is lost (dropped)
            with svc._codec_lock:
                for seq in range(41, 61):
                    pub.put(msgs.encode(_js(seq * 1_000_000, seq)), attachment=transport.attachment_bytes(seq, gid))
                end = time.monotonic() + 10
                while svc.counts_in[js_key] + svc.dropped[js_key] < 60:
                    assert time.monotonic() < end, "the last samples"
                    time.sleep(0.01)
        finally:
            pub.undeclare()
            pub_clock.undeclare()

    run = tmp_path / "run"
    _logger_run(scenario, session, run_service, run, {"clock.mode": "realtime"}, body)
    summary = json.loads((run / "record_summary.json").read_text())
    held = key_counts(run / "bag")
    for key, c in summary.items():
        assert c["received"] == c["recorded"] == c["bagged"] == held[key], (key, c, held[key])
    assert summary[js_key]["lost"] >= 10 and summary[js_key]["rejected"] == 1
    ms = [m for m in open_bag(run / "bag").messages() if m.key == js_key]
    assert [m.seq for m in ms[:40]] == list(range(1, 41)) and {m.gid for m in ms} == {gid}
    assert [m.data for m in ms[:40]] == [sent[s] for s in range(1, 41)]
    assert [m.pub_ns for m in ms[:3]] == [1_000_000, 2_000_000, 3_000_000]
    (clock,) = [m for m in open_bag(run / "bag").messages() if m.key == clock_key]
    assert clock.gid is None and clock.seq == 0 and clock.pub_ns == 5
    (local,) = [m for m in open_bag(run / "bag").messages() if m.key == keys.sync("controller")]
    assert local.data == msgs.encode(msgs.Clock(clock=msgs.stamp(123))) and local.seq == 3 and local.gid == gid
    with Reader(run / "bag") as r:
        assert r.message_count == sum(held.values())


def test_logger_bag_false_writes_no_bag(scenario: Any, session: Any, run_service: Any, tmp_path: Path,
                                        capsys: Any) -> None:
    run = tmp_path / "run"
    _logger_run(scenario, session, run_service, run, {"logger.bag": False}, lambda svc: time.sleep(0.3))
    assert not (run / "bag").exists() and (run / "recording.rrd").is_file()
    assert all("bagged" not in c for c in json.loads((run / "record_summary.json").read_text()).values())
    assert " bagged " not in capsys.readouterr().out


def test_the_run_summary_counts_the_bag_and_recovers_a_killed_one(scenario: Any, tmp_path: Path,
                                                                  capsys: Any) -> None:
    from hilsim.launch.launcher import Launcher, summarise
    from hilsim.launch.summary import _recover_recordings

    sc = scenario("arm", {"duration": 1.0, "task.targets": []})
    la = Launcher(sc, tmp_path)
    la.outcome.physics_done = True
    w = BagWriter(tmp_path / "bag")
    for k in range(30):
        w.add(KEYS.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(k))), T0 + k)
        w.add(KEYS.topic("joint_states"), msgs.encode(_js(k, k)), T0 + k)
    w.close()
    counts = {k: {"received": 30, "recorded": 30, "bagged": 30, "rejected": 0, "lost": 0}
              for k in (KEYS.clock, KEYS.topic("joint_states"))}
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    assert summarise(la) == 0
    assert "bag: recorded 60 of 60 received messages on 2 topics" in capsys.readouterr().out
    # the recorder says it received one more than the bag holds: FAILED
    counts[KEYS.clock].update(received=31, recorded=31, bagged=31)
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    assert summarise(la) == 1
    assert "MISMATCH (bag against received) on clock 30 of 31" in capsys.readouterr().out
    # a recorder killed with SIGKILL: its bag made whole where hilsim up recovers the recording
    shutil.rmtree(tmp_path / "bag")
    _killed_bag(tmp_path / "bag")
    assert _recover_recordings(tmp_path)
    assert "bag_0.mcap: 1500 messages (the recorder was killed: recovered)" in capsys.readouterr().out
    assert (tmp_path / "bag" / "metadata.yaml").is_file() and read_file(tmp_path / "bag" / "bag_0.mcap").complete


@pytest.mark.serial
def test_the_bench_measures_the_bags_cost() -> None:
    from hilsim.tools.bench.bag import worker_cost
    from hilsim.tools.bench.pipeline import _recorder_line

    r = worker_cost(steps=300, repeat=1)
    assert r["samples"] == 300 * 6 + 60 + 30 and r["without_bag_us"] > 0 and r["with_bag_us"] > 0
    line = _recorder_line({"process_without_bag_us": 20.0, "process_with_bag_us": 21.0,
                           **{f"worker_{k}": v for k, v in r.items()}})
    assert line.startswith("20.0 µs of CPU per recorded sample without the bag, 21.0 µs with it (+5 %")


# ---------------------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def arm_run(tmp_path_factory: Any) -> Iterator[tuple[Path, str]]:
    """``hilsim up arm --duration 1`` (lockstep, the default recorder): its run directory and output."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    run = tmp_path_factory.mktemp("arm") / "run"
    try:
        out = finish(up("arm", "--duration", "1", "--router", ep, "--out", str(run)), 300)
    finally:
        router.close()
    assert "result: " in out and "FAILED" not in out, out  # the task is cut short by --duration: not a failure
    yield run, out


def _rrd_last(rrd: Path, entity: str) -> float:
    """The value of an entity's Scalars row with the latest sim time, read from the run's .rrd (every
    file of it, if split: hilsim.core.recording.recording_files)."""
    disable_analytics()
    from rerun.chunk import RrdReader

    best: tuple[int, float] | None = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in (c for f in recording_files(rrd) for c in RrdReader(f).stream().to_chunks()):
            if chunk.entity_path != entity:
                continue
            rb = chunk.to_record_batch()
            for t, v in zip(rb.column("sim_time").cast("int64").to_pylist(), rb.column("Scalars:scalars").to_pylist(),
                            strict=True):
                if best is None or t >= best[0]:
                    best = (t, v[0])
    assert best is not None, entity
    return best[1]


def _read_back(run: Path, out: str) -> tuple[Counter[str], dict[str, Any]]:
    """Both readers over the run's bag: every topic decoded, the same values; counts per topic as
    the recorder counted them. Returns counts per topic and the last message of each (rosbags)."""
    summary = json.loads((run / "record_summary.json").read_text())
    held = key_counts(run / "bag")
    for key, c in summary.items():
        assert c["received"] == c["recorded"] == c["bagged"] == held[key], (key, c)
    total = sum(held.values())
    assert f"bag: recorded {total} of {total} received messages on {len(held)} topics" in out, out
    rb_all = _rosbags_read(run / "bag")
    mc = _mcap_read(run / "bag" / "bag_0.mcap")
    assert len(rb_all) == len(mc) == total
    meta = yaml.safe_load((run / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = Counter(t for t, *_ in rb_all)
    assert counts == {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == Counter(m.channel.topic for m in mc)
    # the same values from both readers, message by message (mcap_ros2 in file order, rosbags by time)
    by_rb: dict[tuple[str, int], list[Any]] = {}
    for topic, _, t, m in rb_all:
        by_rb.setdefault((topic, t), []).append(_plain(m))
    for m in mc:
        assert _plain(m.ros_msg) in by_rb[(m.channel.topic, m.log_time_ns)], m.channel.topic
    types = {ty for _, ty, _, _ in rb_all}
    assert types == {m.schema.name for m in mc}
    last = {topic: m for topic, _, _, m in rb_all}
    return counts, last


@pytest.mark.e2e
def test_an_arm_run_bag_reads_back_and_matches_the_rrd(arm_run: tuple[Path, str]) -> None:
    run, out = arm_run
    counts, last = _read_back(run, out)
    custom = yaml.safe_load((run / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert custom["scenario"] == "arm" and custom["robot"] == "arm" and "log_time" in custom["times"]
    rrd = contents(run).rows
    assert {"sensor_msgs/msg/JointState", "sensor_msgs/msg/Imu", "rosgraph_msgs/msg/Clock",
            "diagnostic_msgs/msg/DiagnosticArray", "trajectory_msgs/msg/JointTrajectory",
            "hilsim_msgs/action/Move_Feedback", "hilsim_msgs/msg/Contacts"} <= set(_types(run))
    assert counts["/clock"] == rrd["/clock"] == 1001
    # the latched topics a ROS 2 user's rviz needs from the bag: each put once at the start, often before
    # the recorder's `**` reached its publisher (the recorder's late-joiner subscription asks the cache)
    assert counts["/tf_static"] == counts["/arm/robot_description"] == 1, counts
    summary = json.loads((run / "record_summary.json").read_text())
    for k in (KEYS.tf_static, KEYS.topic("robot_description")):
        assert summary[k]["received"] == summary[k]["recorded"] == summary[k]["bagged"] == 1, (k, summary[k])
    assert counts["/arm/joint_states"] == rrd["/joints/joint_1/position/measured"]
    assert counts["/arm/truth/joint_states"] == rrd["/joints/joint_1/position/truth"]
    assert counts["/arm/joint_commands"] == rrd["/joints/joint_1/effort/command"]
    assert counts["/arm/imu"] == rrd["/imu/measured/orientation/x"]
    for i, j in enumerate(JOINTS):
        want = _rrd_last(run / "recording.rrd", f"/joints/{j}/position/measured")
        assert last["/arm/joint_states"].position[i] == want
    assert last["/arm/truth/imu"].linear_acceleration.z == _rrd_last(run / "recording.rrd",
                                                                     "/imu/truth/linear_acceleration/z")


@pytest.mark.e2e
def test_the_planner_ticks_are_the_joint_states_of_its_steps(arm_run: tuple[Path, str]) -> None:
    """``joint_states_throttle`` (the planner's only input) carries exactly the sensors' joint states
    of the planner's decision steps (every 10th at 100 Hz), not the 1 kHz stream."""
    run, _ = arm_run
    by_topic: dict[str, dict[int, Any]] = {"/arm/joint_states": {}, "/arm/joint_states_throttle": {}}
    for topic, _, _, m in _rosbags_read(run / "bag"):
        if topic in by_topic:
            by_topic[topic][m.header.stamp.sec * 10**9 + m.header.stamp.nanosec] = _plain(m)
    every, ticks = by_topic["/arm/joint_states"], by_topic["/arm/joint_states_throttle"]
    due = {t for t in every if (t // 1_000_000) % 10 == 0}
    assert len(every) > 900 and set(ticks) == due and len(ticks) == len(due) > 90, (len(every), sorted(ticks)[:5])
    assert all(ticks[t] == every[t] for t in ticks)


def _types(run: Path) -> list[str]:
    with Reader(run / "bag") as r:
        return [c.msgtype for c in r.connections]


@pytest.mark.e2e
def test_a_rover_run_bag_reads_back_and_matches_the_rrd(tmp_path: Path) -> None:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    run = tmp_path / "run"
    try:
        out = finish(up("config/rover-outdoor.yaml", "--duration", "1", "--router", ep, "--out", str(run)), 300)
    finally:
        router.close()
    assert "result: " in out and "FAILED" not in out, out
    counts, last = _read_back(run, out)
    assert {"nav_msgs/msg/Odometry", "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/NavSatFix", "tf2_msgs/msg/TFMessage",
            "geometry_msgs/msg/Twist", "nav_msgs/msg/OccupancyGrid", "nav_msgs/msg/Path"} <= set(_types(run))
    rrd = contents(run).rows
    assert counts["/clock"] == rrd["/clock"]
    assert counts["/rover/odom"] == rrd["/odometry/x/odom"] and counts["/rover/truth/odom"] == rrd["/odometry/x/truth"]
    assert counts["/rover/gps/fix"] == rrd["/gps/fix/altitude"]
    assert counts["/rover/joint_states"] == rrd["/joints/fl_traction/velocity/measured"]
    assert last["/rover/odom"].pose.pose.position.x == _rrd_last(run / "recording.rrd", "/odometry/x/odom")
    assert last["/rover/truth/odom"].pose.pose.position.y == _rrd_last(run / "recording.rrd", "/odometry/y/truth")
    assert last["/rover/gps/fix"].latitude == _rrd_last(run / "recording.rrd", "/gps/fix/latitude")


@pytest.mark.serial  # wall-clock timing: failed two tests at a time
@pytest.mark.e2e
def test_the_played_sensor_stream_gives_the_controllers_commands_bit_for_bit(arm_run: tuple[Path, str],
                                                                            run_service: Any) -> None:
    """The arm's joint states and trajectory, played from the bag (``hilsim play``) into its controller
    alone (its run's scenario.yaml): every joint_commands is the recorded one, byte for byte."""
    from hilsim.core.service import instantiate

    run, _ = arm_run
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    s = transport.open_session(ZenohConfig(connect=[ep]))
    got: dict[int, bytes] = {}
    sc = load_scenario(run / "scenario.yaml", {"zenoh.connect": [ep]})

    def on(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        got[msgs.ns_of(msgs.decode(msgs.JointState, data).header.stamp)] = data

    sub = s.declare_subscriber(Keys.of(sc).topic("joint_commands"), on)
    traj_key = Keys.of(sc).topic("planner/joint_trajectory")  # the planner's, recorded
    try:
        with run_service(instantiate("controller", sc)) as ctl:
            p = subprocess.run([sys.executable, "-m", "hilsim.cli", "play", str(run), "--rate", "0.1", "--keys",
                                "/arm/joint_states,/arm/planner/joint_trajectory", "--connect", ep],
                               capture_output=True, text=True, timeout=120, cwd=REPO)
            assert p.returncode == 0, p.stderr
            end = time.monotonic() + 10
            while len(got) < 1001 and time.monotonic() < end:
                time.sleep(0.05)
            # what the controller made of the trajectory, said should the commands differ
            seen = (f"trajectory: {ctl.counts_in[traj_key]} in, {ctl.rejected[traj_key]} rejected, taken "
                    f"{dict(ctl._taken)}; last error {ctl.last_error!r}; play said {p.stderr[-600:]!r}")
    finally:
        sub.undeclare()
        s.close()
        router.close()
    recorded = {m.pub_ns: m.data for m in open_bag(run).messages() if m.topic == "/arm/joint_commands"}
    assert len(recorded) == 1001
    (traj,) = [m for m in open_bag(run).messages() if m.topic == "/arm/planner/joint_trajectory"]
    assert 0 < traj.pub_ns < 1_000_000_000  # the trajectory starts within the run: the commands follow it
    assert sorted(got) == sorted(recorded)
    differ = [t for t in sorted(recorded) if got[t] != recorded[t]]
    assert not differ, f"{len(differ)} commands differ, the first at {differ[0] / 1e9:.3f} s; {seen}"


@pytest.mark.e2e
def test_play_publishes_like_a_ros2_node_with_its_own_clock(arm_run: tuple[Path, str]) -> None:
    """--clock: /clock from the stamps (the recorded one not played); each key with its own MP token,
    gid and sequence numbers from 1; the recorded bytes; a progress line; --loop until interrupted."""
    run, _ = arm_run
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    s = transport.open_session(ZenohConfig(connect=[ep]))
    lock = threading.Lock()
    seen: dict[str, list[tuple[bytes, transport.Attachment | None]]] = {"js": [], "clock": []}

    def rec(name: str) -> Any:
        def on(sample: zenoh.Sample) -> None:
            with lock:
                seen[name].append((sample.payload.to_bytes(), transport.read_attachment(sample)))
        return on

    subs = [s.declare_subscriber(KEYS.topic("joint_states"), rec("js")), s.declare_subscriber(KEYS.clock, rec("clock"))]
    tokens: list[str] = []
    subs.append(s.liveliness().declare_subscriber(
        KEYS.all_writers, lambda t: tokens.append(str(t.key_expr)) if t.kind == zenoh.SampleKind.PUT else None))
    try:
        p = subprocess.run([sys.executable, "-m", "hilsim.cli", "play", str(run / "bag"), "--rate", "0", "--clock",
                            "--keys", "/arm/joint_states", "--connect", ep], capture_output=True, text=True,
                           timeout=120, cwd=REPO)
        assert p.returncode == 0, p.stderr
        assert "playing: sim    1.000 / 1.000 s, 1001/1001 messages" in p.stderr, p.stderr
        assert "played 1001 messages on 1 keys, 1.000 s of sim time" in p.stderr, p.stderr
        end = time.monotonic() + 10
        while (len(seen["js"]) < 1001 or len(seen["clock"]) < 1001) and time.monotonic() < end:
            time.sleep(0.05)
        recorded = [m.data for m in open_bag(run).messages() if m.topic == "/arm/joint_states"]
        with lock:
            js, clock = list(seen["js"]), list(seen["clock"])
        assert [d for d, _ in js] == recorded
        assert [msgs.ns_of(msgs.decode(msgs.Clock, d).clock) for d, _ in clock] == [k * 1_000_000 for k in range(1001)]
        for samples, topic in ((js, "%arm%joint_states"), (clock, "%clock")):
            atts = [a for _, a in samples]
            assert all(a is not None for a in atts) and [a.seq for a in atts] == list(range(1, 1002))
            (gid,) = {a.gid for a in atts}
            (token,) = [t for t in tokens if f"/MP/%/%/hilsim_play/{topic}/" in t]
            assert wire.entity_gid(token) == gid
        assert any("/NN/%/%/hilsim_play" in t for t in tokens), tokens  # the node itself
        # --loop: again from the start, sequence numbers going on, until interrupted. Started with SIGINT
        # ignored, as a script's background job is: Ctrl-C (SIGINT) still ends it
        with lock:
            seen["js"].clear()
        argv = [sys.executable, "-m", "hilsim.cli", "play", str(run), "--rate", "0", "--loop", "--keys",
                "/arm/joint_states", "--connect", ep]
        ignoring = f"import os, signal; signal.signal(signal.SIGINT, signal.SIG_IGN); os.execv({argv[0]!r}, {argv!r})"
        lp = subprocess.Popen([sys.executable, "-c", ignoring], stderr=subprocess.PIPE, text=True, cwd=REPO)
        end = time.monotonic() + 30
        while len(seen["js"]) < 2500 and time.monotonic() < end:
            time.sleep(0.05)
        lp.send_signal(signal.SIGINT)
        _, err = lp.communicate(timeout=20)
        assert lp.returncode == 130, err
        with lock:
            seqs = [a.seq for _, a in seen["js"] if a is not None]
        assert len(seqs) >= 2500 and seqs[:2500] == list(range(1, 2501)) and "(loop 2)" in err
        assert "(stopped by SIGINT)" in err, err
    finally:
        for x in subs:
            x.undeclare()
        s.close()
        router.close()


@pytest.mark.e2e
def test_export_of_the_rrd_gives_the_bags_values(arm_run: tuple[Path, str], tmp_path: Path, capsys: Any) -> None:
    """For runs recorded before the bag: the .rrd as a bag of re-encoded messages (the values the rows
    hold) with the other rows as JSON, and as CSV files."""
    run, _ = arm_run
    assert cli(["export", str(run), "--to", "mcap", "--out", str(tmp_path / "mcap")]) == 0
    assert cli(["export", str(run), "--to", "csv", "--out", str(tmp_path / "csv")]) == 0
    assert cli(["export", str(run), "--to", "csv"]) == 0 and (run / "export-csv" / "clock").is_dir()
    assert cli(["export", str(run), "--to", "csv"]) == 1  # not over an earlier export
    # no run named: the latest under --runs
    assert cli(["export", "--runs", str(run.parent), "--to", "csv", "--out", str(tmp_path / "latest")]) == 0
    assert (tmp_path / "latest" / "clock").is_dir() and f"the latest run, {run}" in capsys.readouterr().err
    capsys.readouterr()
    orig = {(m.topic, m.pub_ns): m.data for m in open_bag(run).messages()}
    exported = _rosbags_read(tmp_path / "mcap")
    counts = Counter(t for t, *_ in exported)
    assert set(counts) == {"/clock", "/arm/joint_states", "/arm/truth/joint_states", "/arm/joint_commands",
                           "/arm/controller/reference", "/arm/imu", "/arm/truth/imu"}
    for topic, n in counts.items():
        assert n == sum(1 for t, _ in orig if t == topic), topic
    for topic, ty, t, m in exported:
        was = msgs.decode(msgs.JointState if ty.endswith("JointState") else msgs.Imu if ty.endswith("Imu")
                          else msgs.Clock, orig[(topic, t)])
        if ty.endswith("JointState"):
            assert list(m.name) == list(was.name) and m.position.tolist() == list(was.position), topic
            assert m.velocity.tolist() == list(was.velocity) and m.effort.tolist() == list(was.effort), topic
        elif ty.endswith("Imu"):
            assert (m.linear_acceleration.x, m.orientation.w) == (was.linear_acceleration.x, was.orientation.w)
    rows = {c.topic for c in _json_channels(tmp_path / "mcap" / "rrd_rows.mcap") if c.message_encoding == "json"}
    assert "/rrd/health/physics/level" in rows and "/rrd/planner/feedback" in rows
    csv_file = tmp_path / "csv" / "joints" / "joint_1" / "position" / "measured" / "Scalars.scalars.csv"
    lines = csv_file.read_text().splitlines()
    assert lines[0] == "sim_time_ns,value" and len(lines) == 1 + counts["/arm/joint_states"]
    last_js = msgs.decode(msgs.JointState, orig[("/arm/joint_states", 1_000_000_000)])
    assert lines[-1] == f"1000000000,{last_js.position[0]!r}"
    # every joints/* file in sim-time order, the time-0 row first (it had come after the 10 ms one)
    for f in (tmp_path / "csv" / "joints").rglob("*.csv"):
        times = [int(ln.split(",")[0]) for ln in f.read_text().splitlines()[1:] if ln.split(",")[0]]
        assert times == sorted(times) and (times[0] == 0 or "planned" in f.parts), (f, times[:3])


def _json_channels(path: Path) -> list[Any]:
    """The channel of every message of an MCAP file (mcap's own reader)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [c for _, c, _ in make_reader(f).iter_messages()]


@pytest.mark.e2e
def test_bag_info_lists_topics_like_ros2_bag_info(arm_run: tuple[Path, str], capsys: Any) -> None:
    run, _ = arm_run
    assert cli(["bag", "info", str(run)]) == 0
    out = capsys.readouterr().out
    assert "Storage id:        mcap" in out and "Files:             bag_0.mcap" in out
    assert "Topic: /clock | Type: rosgraph_msgs/msg/Clock | Count: 1001 | Serialization Format: cdr" in out
    assert "Sim time:          0.000000 s to 1.000000 s (publish times)" in out
    n = sum(json.loads((run / "record_summary.json").read_text())[k]["bagged"]
            for k in json.loads((run / "record_summary.json").read_text()))
    assert f"Messages:          {n}\n" in out and "INCOMPLETE" not in out
    # no bag named: the latest run under --runs (as hilsim view takes it), said on standard error
    assert cli(["bag", "info", "--runs", str(run.parent)]) == 0
    latest = capsys.readouterr()
    assert latest.out == out and f"the latest run, {run}" in latest.err
    assert cli(["bag", "info", "--runs", str(run.parent / "none")]) == 1
    assert "no recordings" in capsys.readouterr().err
    # a bag against itself: the same; against nothing readable: 2, as diff(1) says trouble
    assert cli(["bag", "diff", str(run), str(run)]) == 0
    assert "the bags hold the same messages" in capsys.readouterr().out
    assert cli(["bag", "diff", str(run), str(run.parent / "none")]) == 2
