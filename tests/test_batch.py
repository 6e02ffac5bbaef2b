"""The recorder takes batches (``logger.batch``): the frame, the batcher, the recorder's duplicate
accounting, and two real arm runs, one with batches and one without, recording the same."""

from __future__ import annotations

import json
import struct
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
import zenoh
from ros2_node import Ros2Node
from ros2_node import msg as ros_msg
from util import finish, until_ready, up, wait_until

from hilsim.core import batch, msgs, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.transport import Attachment

GID_A, GID_B = bytes(range(16)), bytes(range(16, 32))
WRITERS = [("0/arm/joint_states/x/RIHS01_1", GID_A), ("0/clock/y/RIHS01_2", GID_B)]
RECORDS = [(0, 1, 10, b"abc"), (1, 7, 11, b""), (0, 2, -5, bytes(300))]


# ---------------------------------------------------------------------------------- the frame
def test_a_frame_round_trips() -> None:
    got = batch.decode(batch.encode(WRITERS, RECORDS))
    assert got == [batch.Record(WRITERS[w][0], s, t, WRITERS[w][1], p) for w, s, t, p in RECORDS]
    assert batch.decode(batch.encode(WRITERS, [])) == []
    assert batch.decode(bytearray(batch.encode([], []))) == []


def test_every_truncation_is_a_clear_error() -> None:
    frame = batch.encode(WRITERS, RECORDS)
    for n in range(len(frame)):
        with pytest.raises(batch.BatchError):
            batch.decode(frame[:n])


def test_lying_frames_are_clear_errors() -> None:
    frame = bytearray(batch.encode(WRITERS, RECORDS))
    head = struct.calcsize("<3sBHI")

    def bad(mutated: bytes | bytearray, words: str) -> None:
        with pytest.raises(batch.BatchError, match=words):
            batch.decode(mutated)

    bad(b"XYZ" + frame[3:], "not a batch")
    bad(frame[:3] + bytes([2]) + frame[4:], "version 2")
    bad(frame + b"\0", "1 bytes after the last record")
    more = bytearray(frame)
    struct.pack_into("<I", more, 6, 1_000_000)  # more records than can fit
    bad(more, "cannot fit")
    writers = bytearray(frame)
    struct.pack_into("<H", writers, 4, 3)  # a third writer: the records' bytes are read as its key
    bad(writers, "writer 2|record|cut short")
    key = bytearray(frame)
    struct.pack_into("<H", key, head, 60_000)  # the first key's length goes past the end
    bad(key, "writer 0: key of 60000 bytes")
    utf = bytearray(frame)
    utf[head + 2] = 0xFF
    bad(utf, "not UTF-8")
    records_at = head + sum(2 + len(k) + 16 for k, _ in WRITERS)
    index = bytearray(frame)
    struct.pack_into("<H", index, records_at, 5)
    bad(index, "record 0: writer 5, but the batch has 2")
    plen = bytearray(frame)
    struct.pack_into("<I", plen, records_at + 18, 10_000)
    bad(plen, "record 0: payload of 10000 bytes goes past the end")


# ---------------------------------------------------------------------------------- the batcher
class _Put:
    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self.undeclared = False

    def put(self, data: bytes) -> None:
        self.frames.append(data)

    def undeclare(self) -> None:
        self.undeclared = True


def test_a_batch_is_sent_full_old_or_at_the_end() -> None:
    pub, token = _Put(), _Put()
    b = batch.Batcher(pub, token, size=3, max_age_s=0.2)
    w = b.writer("0/a/x/RIHS01_1", GID_A)
    assert [b.add(w, i, i, b"%d" % i) for i in (1, 2, 3)] == [False, False, True]
    b.flush()
    assert [r.seq for r in batch.decode(pub.frames[0])] == [1, 2, 3]
    t0 = time.monotonic()
    b.add(w, 4, 4, b"4")  # not full: sent by the flusher once 0.2 s old, not before
    assert wait_until(lambda: len(pub.frames) == 2, 3.0)
    assert time.monotonic() - t0 >= 0.19
    assert [r.seq for r in batch.decode(pub.frames[1])] == [4]
    b.add(w, 5, 5, b"5")
    b.undeclare()  # the service stopping: what is held goes out before the token and the publisher
    assert [r.seq for r in batch.decode(pub.frames[2])] == [5]
    assert pub.undeclared and token.undeclared
    assert (b.batches, b.samples) == (3, 5)


def test_a_frame_stays_below_zenohs_transport_batch() -> None:
    """Frames are never sent in fragments (a congested link loses fragments, and with them whole frames):
    one that would pass MAX_FRAME goes first; a sample larger than that alone, in its own frame."""
    pub, token = _Put(), _Put()
    b = batch.Batcher(pub, token, size=1000, max_age_s=60)
    w = b.writer("0/a/x/RIHS01_1", GID_A)
    sample = bytes(7000)
    for i in range(1, 20):
        b.add(w, i, i, sample)
    big = bytes(batch.MAX_FRAME + 5)
    b.add(w, 20, 20, big)
    b.add(w, 21, 21, b"x")
    b.undeclare()
    sizes = [len(f) for f in pub.frames]
    assert all(n <= batch.MAX_FRAME for n in sizes[:-2]) and len(sizes) >= 4, sizes
    seqs = [[r.seq for r in batch.decode(f)] for f in pub.frames]
    assert [s for frame in seqs for s in frame] == list(range(1, 22)), seqs  # none lost, in order
    assert seqs[-2:] == [[20], [21]], seqs  # the large one alone; the next after it
    assert all(len(frame) == 8 for frame in seqs[:2]), seqs  # 8 × 7 kB fill a frame below 60 kB


# ---------------------------------------------------------------------------------- the recorder's counting
def test_a_sample_that_comes_twice_is_taken_once(scenario: Any, tmp_path: Path) -> None:
    from hilsim.services.logger import LoggerService

    svc = LoggerService(scenario("arm", {"logger.run_dir": str(tmp_path / "run"), "logger.batch": 8}))
    key = Keys().clock

    def take(*seqs: int) -> list[bool]:
        return [svc.accounts.sequence(key, Attachment(s, 0, GID_A), None) for s in seqs]

    # first seen on the key at 5 (the batch with 1..4 comes later): those fill "before the first"
    assert take(5, 6, 1, 2, 3, 4) == [True] * 6
    assert svc.before_first[key] == 0
    assert take(1, 5, 6) == [False] * 3  # and again, from the other way: duplicates
    assert take(9) == [True] and svc.gaps[key] == 2  # 7 and 8 missing
    assert take(8, 8, 7, 9, 10) == [True, False, True, False, True]
    assert svc.gaps[key] == 0 and svc.before_first[key] == 0
    assert svc.accounts.sequence(key, Attachment(3, 0, GID_B), None)  # another writer counts on its own
    assert svc.before_first[key] == 2
    # a writer whose token comes after its first samples (unannounced then): taken once all the same,
    # and what it missed before it was announced is neither a loss nor "before the first"
    tf = Keys().tf
    assert [svc.accounts.sequence(tf, Attachment(s, 0, GID_A), None, counted=False) for s in (3, 6)] == [True, True]
    assert svc.before_first[tf] == svc.gaps[tf] == 0
    assert take_on(svc, tf, 1, 2, 3, 4, 5, 6, 7) == [True, True, False, True, True, False, True]
    assert svc.before_first[tf] == svc.gaps[tf] == 0
    assert take_on(svc, tf, 9) == [True] and svc.gaps[tf] == 1  # announced now: a gap is a loss


def test_a_batched_sample_from_a_writer_announced_late_is_recorded_once(scenario: Any, tmp_path: Path) -> None:
    """The race behind a flaky count: a key with one announced writer (a ROS 2 node) gets a batching
    service's samples on the key before that service's token is known, and again in its batch after."""
    from hilsim.services.logger import LoggerService

    svc = LoggerService(scenario("arm", {"logger.run_dir": str(tmp_path / "run"), "logger.batch": 8}))
    tf = Keys().tf
    svc.provenance.writers[tf] = {GID_B}  # the node's writer, announced
    svc.provenance.restricted.add(tf)
    svc._take(tf, Attachment(1, 0, GID_A), b"x")  # physics' first, on the key: not announced yet
    svc.provenance.writers[tf].add(GID_A)  # its token arrives
    for seq in (1, 2):  # and its batch
        svc._take(tf, Attachment(seq, 0, GID_A), b"x")
    assert (svc.counts_in[tf], svc.duplicates[tf], svc.unannounced[tf]) == (2, 1, 1)
    assert svc.gaps[tf] == svc.before_first[tf] == 0


def take_on(svc: Any, key: str, *seqs: int) -> list[bool]:
    return [svc.accounts.sequence(key, Attachment(s, 0, GID_A), None) for s in seqs]


def test_a_batch_is_taken_only_for_keys_its_service_may_write(scenario: Any, tmp_path: Path) -> None:
    """The service named in the batch key may write truth and the clock (physics), not cmd_vel: the rest of
    its batch is taken, that sample is counted as batch_refused and said once; a name nobody has: nothing."""
    from hilsim.services.logger import LoggerService

    svc = LoggerService(scenario("arm", {"logger.run_dir": str(tmp_path / "run"), "logger.batch": 8}))
    keys = Keys()
    taken: list[str] = []
    said: list[str] = []
    svc._take = lambda k, att, payload: taken.append(k)  # type: ignore[method-assign]
    svc.warn = said.append  # type: ignore[method-assign]

    class _Sample:
        def __init__(self, key: str, data: bytes) -> None:
            self.key_expr, self.payload = key, zenoh.ZBytes(data)

    writers = [(keys.clock, GID_A), (keys.topic("cmd_vel"), GID_B), (keys.truth("joint_states"), GID_A)]
    frame = batch.encode(writers, [(0, 1, 0, b"c"), (1, 1, 0, b"v"), (2, 1, 0, b"t"), (1, 2, 0, b"v")])
    svc._on_batch(_Sample(keys.batch("feedbeef", 1, "physics"), frame))
    assert taken == [keys.clock, keys.truth("joint_states")], taken
    assert svc.batch_refused == {keys.topic("cmd_vel"): 2}
    assert len(said) == 1 and "a batch of physics holds a sample of 0/arm/cmd_vel/" in said[0], said
    taken.clear()
    svc._on_batch(_Sample(keys.batch("feedbeef", 2, "nobody"), frame))  # no service of that name: nobody's batch
    assert taken == [] and sum(svc.batch_refused.values()) == 2 + 4, svc.batch_refused
    assert svc.health_values()["batch_refused"] == 6


def test_batches_are_recorded_within_logger_record(scenario: Any, tmp_path: Path) -> None:
    from hilsim.services.logger import LoggerService

    svc = LoggerService(scenario("arm", {"logger.run_dir": str(tmp_path / "run"), "logger.batch": 8,
                                         "logger.record": ["arm/**"]}))
    keys = Keys()
    assert svc.routes.covers(keys.topic("joint_states")) and svc.routes.covers(keys.health("physics"))
    assert not svc.routes.covers(keys.clock) and not svc.routes.covers(keys.for_robot("arm2").topic("imu"))


# ---------------------------------------------------------------------------------- real runs
DURATION = "4"  # sim seconds: long enough for the mid-run actors below
N_ROS = 20
N_BURST = 100
N_EARLY = 3  # of the burst, sent at once (before the recorder can have subscribed)


def _bag(run: Path) -> dict[str, list[tuple[bytes | None, int, bytes]]]:
    from hilsim.record.bag_read import open_bag

    out: dict[str, list[tuple[bytes | None, int, bytes]]] = defaultdict(list)
    for m in open_bag(run / "bag").messages():
        out[m.key].append((m.gid, m.seq, m.data))
    return out


def _finals(bag: dict[str, list[tuple[bytes | None, int, bytes]]], service: str, final: bool = True) -> dict[str, str]:
    """The values of ``service``'s last health message in the bag (``final``: its final one, sent at its stop)."""
    last = msgs.decode(msgs.DiagnosticArray, bag[Keys().health(service)][-1][2])
    values = {kv.key: kv.value for kv in last.status[0].values}
    assert not final or values.get("final") == "1", values
    return values


def _run(tmp_path: Path, name: str, batch_size: int, during: Any = None, compose: str | None = None) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    out = tmp_path / name
    lines: list[str] = []
    extra: dict[str, Any] = {}
    try:
        p = up("arm", "--router", ep, "--duration", DURATION, "--seed", "7", "--out", str(out),
               "--set", f"logger.batch={batch_size}", *(["--compose", compose] if compose else []))
        try:
            until_ready(p, lines)
            if during is not None:
                extra = during(ep)
        finally:
            text = "".join(lines) + finish(p, 240)
        assert p.returncode == 3 and "result: STOPPED (duration)" in text, text
    finally:
        router.close()
    if "close" in extra:
        extra.pop("close")()
    return {"out": out, "text": text, "summary": json.loads((out / "record_summary.json").read_text()),
            "bag": _bag(out), **extra}


def _actors(ep: str) -> dict[str, Any]:
    """While the batching run runs: a plain subscriber appears on /tf (physics', read by the recorder
    only from batches); a ROS 2 node writes /tf too (so the recorder subscribes the key and gets
    physics' samples both ways) and a topic of its own; someone puts garbage on a batch key."""
    keys = Keys()
    ses = transport.open_session(ZenohConfig(connect=[ep]))
    got: list[float] = []
    lock = threading.Lock()
    node = Ros2Node(ep, name="lab_node", namespace="/lab")
    subs: list[Any] = []

    def close() -> None:
        for sub in subs:
            sub.undeclare()
        ses.close()
        node.close()

    try:
        return _act(ses, node, subs, keys, got, lock) | {"close": close}
    except BaseException:
        close()  # no session may outlive the test, even a failing one
        raise


def _act(ses: zenoh.Session, node: Ros2Node, subs: list[Any], keys: Keys, got: list[float],
         lock: threading.Lock) -> dict[str, Any]:
    def on_tf(s: zenoh.Sample) -> None:
        with lock:
            got.append(time.monotonic())

    # mid-run for sure: once sim time passed 0.5 s ("ready" comes before physics' first step)
    sim_ns = [0]
    clock = ses.declare_subscriber(keys.clock, lambda s: sim_ns.__setitem__(
        0, msgs.ns_of(msgs.decode(msgs.Clock, s.payload.to_bytes()).clock)))
    assert wait_until(lambda: sim_ns[0] >= 500_000_000, 20), sim_ns
    clock.undeclare()
    t_sub = time.monotonic()
    subs.append(ses.declare_subscriber(keys.tf, on_tf))
    chatter = node.publisher("/lab/chatter", "std_msgs/msg/String", keep_all=True)
    chatter_pub = node._decl[-1]
    tf = node.publisher("/tf", "tf2_msgs/msg/TFMessage", keep_all=True)
    # the recorder subscribes to the node's keys once it sees their publisher tokens
    # (if it never does, the chatter test says so)
    wait_until(lambda: chatter_pub.matching_status.matching, 10)
    time.sleep(0.5)  # /tf's token came with chatter's; give its subscription the same time
    for i in range(N_ROS):
        chatter(ros_msg("std_msgs/msg/String", data=f"hello {i}"))
        tf(ros_msg("tf2_msgs/msg/TFMessage", transforms=[]))
    # (keep-all: reliable and never dropped on a congested link, as rmw_zenoh sends such a writer's samples: the
    # recorder's promise is about what reaches it; a keep-last writer's drops on a loaded link are its own)
    # a publisher that sends at once, before the recorder can have subscribed to its key; the rest once it
    # has (on a loaded machine the subscription can take longer than the whole burst: nothing would be
    # received, and a key never received is in no summary). The rest waits for the route to settle too:
    # samples put while the recorder's subscription was still reaching the writer went missing in the middle
    # (CI and here: 3-12 received, 13-14 not, 15 on), which the recorder must count as lost (it cannot tell)
    burst = node.publisher("/lab/burst", "std_msgs/msg/String", keep_all=True)
    burst_pub = node._decl[-1]
    for i in range(N_BURST):
        if i == N_EARLY:
            wait_until(lambda: burst_pub.matching_status.matching, 10)
            time.sleep(1.0)
        burst(ros_msg("std_msgs/msg/String", data=f"burst {i}"))
        time.sleep(0.001)
    ses.put(keys.batch("feedbeef", 99, "physics"), b"HSB\x01 not a batch at all")
    # a well-formed batch on physics' batch key holding two samples of a key the key table does not give physics
    forged = msgs.encode(msgs.Twist())
    ses.put(keys.batch("feedbeef", 98, "physics"),
            batch.encode([(keys.topic("cmd_vel"), b"\x07" * batch.GID_SIZE)], [(0, 1, 0, forged), (0, 2, 0, forged)]))
    assert wait_until(lambda: len(got) > 0, 5)

    return {"tf_first_s": got[0] - t_sub, "tf_got": got}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("batch")
    return {"off": _run(tmp, "off", 0), "on": _run(tmp, "on", 256, _actors),
            # composed apart from the recorder, its services batch for it; composed with it, only the planner
            "composed": _run(tmp, "composed", 256, compose="physics,sensors,controller"),
            "composed_recorder": _run(tmp, "composed_recorder", 256, compose="physics,sensors,controller,logger")}


# keys whose samples depend on wall time (health figures, log lines) or on the test's own writers
def _sim_keys(summary: dict[str, Any]) -> set[str]:
    keys = Keys()
    return {k for k in summary if "/health/" not in k and "/log/" not in k and k != keys.tf
            and not k.startswith("0/lab/") and not k.startswith(keys.prefix) and not summary[k].get("batch_refused")}


@pytest.mark.e2e
def test_batches_record_what_samples_record(runs: dict[str, dict[str, Any]]) -> None:
    """Per key, the batching run records the same samples, bytes and order as the run without:
    every sample of the simulation (lockstep, same seed: the same run), each once, nothing lost."""
    off, on = runs["off"], runs["on"]
    for r in (off, on):
        for k, c in r["summary"].items():
            assert c["received"] == c["recorded"] == c["bagged"], (k, c)
            assert c["lost"] == 0 and c["dropped"] == 0, (k, c)
        assert sum(len(v) for v in r["bag"].values()) == sum(c["bagged"] for c in r["summary"].values())
    sim_off, sim_on = _sim_keys(off["summary"]), _sim_keys(on["summary"])
    # the latched keys (robot_description, tf_static), sent once at start: in the batch too, so the
    # batching recorder has them, once, even when their put went out before a subscription reached them
    assert sim_off <= sim_on and all("robot_description" in k or "tf_static" in k for k in sim_on - sim_off)
    keys = Keys()
    for k in (keys.topic("robot_description"), keys.tf_static):
        assert on["summary"][k]["received"] == len(on["bag"][k]) == 1, (k, on["summary"].get(k))
    assert len(sim_off) >= 12, sim_off
    for k in sim_off:  # every sample; the same bytes where they hold no wall time (a plan's duration)
        assert len(on["bag"][k]) == len(off["bag"][k]) == on["summary"][k]["received"], k
    same = [keys.clock, keys.topic("joint_states"), keys.topic("joint_commands"), keys.topic("imu"),
            keys.truth("joint_states"), keys.truth("imu"), keys.topic("controller/reference"), keys.sync("planner")]
    for k in same:
        assert [d for _, _, d in on["bag"][k]] == [d for _, _, d in off["bag"][k]], k
    clock = Keys().clock
    assert on["summary"][clock]["received"] == 4001, on["summary"][clock]  # steps 0..4000 of a 4 s run
    # the services' health and log keys: every sample they say they sent, once
    for service in ("physics", "sensors", "controller", "planner"):
        finals = _finals(on["bag"], service)
        for k, v in finals.items():
            key = k.removeprefix("published:")
            if k.startswith("published:") and "/health/" not in k and key != keys.tf:  # /tf: the node's too
                assert on["summary"][key]["received"] == int(v), (service, key)


@pytest.mark.e2e
@pytest.mark.parametrize("run", ["composed", "composed_recorder"])
def test_composed_runs_batch_the_same(runs: dict[str, dict[str, Any]], run: str) -> None:
    """Composed apart from the recorder, the process's services send it batches; composed with it,
    they hand it message objects and the planner, apart, sends batches: the same samples either way."""
    off, got = runs["off"], runs[run]
    for k, c in got["summary"].items():
        assert c["received"] == c["recorded"] == c["bagged"] and c["lost"] == 0, (k, c)
    sim_off, sim = _sim_keys(off["summary"]), _sim_keys(got["summary"]) | {Keys().tf}
    assert sim_off <= sim, sim_off - sim
    for k in sim_off:
        assert len(got["bag"][k]) == len(off["bag"][k]), k
    keys = Keys()
    for k in (keys.clock, keys.topic("joint_states"), keys.truth("joint_states"), keys.topic("controller/reference"),
              keys.sync("planner")):
        assert [d for _, _, d in got["bag"][k]] == [d for _, _, d in off["bag"][k]], k
    planner = _finals(got["bag"], "planner")
    assert int(planner["batches"]) >= 1, planner  # the planner, in a process of its own, batches
    controller = _finals(got["bag"], "controller")
    assert ("batches" in controller) == (run == "composed"), controller


@pytest.mark.e2e
def test_a_key_only_the_recorder_reads_is_not_put(runs: dict[str, dict[str, Any]]) -> None:
    """controller/reference: recorded every step, put on its key never (only in batches)."""
    on, off = runs["on"], runs["off"]
    ref = Keys().topic("controller/reference")
    finals = _finals(on["bag"], "controller")
    assert int(finals[f"published:{ref}"]) == on["summary"][ref]["received"] == 4001
    assert finals[f"put:{ref}"] == "0"
    assert int(finals["batches"]) >= 1 and int(finals["batched"]) >= 4001
    # what the controller reads is still put: physics' joint states are its input
    assert int(_finals(on["bag"], "sensors")[f"put:{Keys().topic('joint_states')}"]) == 4001
    # without batches nothing changes: no batch figures, and the key put for the recorder
    assert "put:" + ref not in _finals(off["bag"], "controller", final=False)


@pytest.mark.e2e
def test_a_subscriber_that_appears_gets_samples_at_once_and_nothing_is_recorded_twice(
        runs: dict[str, dict[str, Any]]) -> None:
    on = runs["on"]
    tf = Keys().tf
    assert on["tf_first_s"] < 1.0, on["tf_first_s"]  # /tf comes at 50 Hz sim time: one within a second
    physics = _finals(on["bag"], "physics")
    published, put = int(physics[f"published:{tf}"]), int(physics[f"put:{tf}"])
    # put only once someone subscribed: what the plain subscriber got (besides the node's), all of it
    assert 0 < put < published and put == len(on["tf_got"]) - N_ROS, (put, published, len(on["tf_got"]))
    c = on["summary"][tf]
    # physics' samples came in batches and on the key (the ROS 2 node's writer made the recorder
    # subscribe to it): each recorded once, plus the node's own
    assert c["received"] == published + N_ROS and c["lost"] == 0, c
    assert c["duplicates"] > 0, c
    seqs = [(g, s) for g, s, _ in on["bag"][tf]]
    assert len(seqs) == len(set(seqs)) == published + N_ROS


@pytest.mark.e2e
def test_a_writer_announced_only_by_its_token_is_recorded(runs: dict[str, dict[str, Any]]) -> None:
    on = runs["on"]
    chatter = [k for k in on["summary"] if k.startswith("0/lab/chatter/")]
    assert chatter, sorted(on["summary"])
    c = on["summary"][chatter[0]]
    assert c["received"] == c["recorded"] == N_ROS and c["rejected"] == 0 and c["lost"] == 0, c
    texts = [msgs.decode(msgs.String, d).data for _, _, d in on["bag"][chatter[0]]]
    assert texts == [f"hello {i}" for i in range(N_ROS)]


@pytest.mark.e2e
def test_a_writer_that_sends_at_once_is_recorded_from_the_recorders_subscription_on_and_the_rest_is_said(
        runs: dict[str, dict[str, Any]]) -> None:
    """A ROS 2 node's publisher that sends as soon as it is made: what it sent before the recorder's
    subscription (made when its token is seen) reached it is not recorded, as with ros2 bag record's
    discovery; everything from there is, in order, and the samples before are counted and said."""
    on = runs["on"]
    key = next(k for k in on["summary"] if k.startswith("0/lab/burst/"))
    c = on["summary"][key]
    assert c["key_subscribed"] and c["received"] == c["recorded"] == c["bagged"] and c["lost"] == 0, c
    assert c["received"] + c["before_first"] == N_BURST, c  # every sample: recorded, or said not to be
    texts = [msgs.decode(msgs.String, d).data for _, _, d in on["bag"][key]]
    assert texts == [f"burst {i}" for i in range(c["before_first"], N_BURST)]
    if c["before_first"]:
        assert f"not recorded: {c['before_first']} samples their writers published before the recorder subscribed" \
            in on["text"], on["text"]


@pytest.mark.e2e
def test_a_malformed_batch_is_rejected_and_the_recording_goes_on(runs: dict[str, dict[str, Any]]) -> None:
    on = runs["on"]
    bad = Keys().batch("feedbeef", 99, "physics")
    assert on["summary"][bad]["received"] == on["summary"][bad]["rejected"] == 1, on["summary"][bad]
    assert on["summary"][Keys().clock]["received"] == 4001  # every step after it recorded too
    assert "malformed batch on" in (on["out"] / "logger.log").read_text()
    # a batch holds only what its service may write (the key table): the forged cmd_vel in physics' is not recorded,
    # counted per key in the summary, said once in the recorder's log and in the run's summary
    cmd_vel = Keys().topic("cmd_vel")
    assert on["summary"][cmd_vel]["batch_refused"] == 2, on["summary"][cmd_vel]
    assert on["summary"][cmd_vel]["received"] == on["summary"][cmd_vel]["recorded"] == 0, on["summary"][cmd_vel]
    assert cmd_vel not in on["bag"]
    assert (on["out"] / "logger.log").read_text().count("a batch of physics holds a sample of 0/arm/cmd_vel/") == 1
    assert "not recorded: 2 samples in batches of services the key table does not let write them" in on["text"]
    # and nothing a service may write was refused, in any run (the services' own batches hold only their keys)
    for name, r in runs.items():
        refused = {k: c["batch_refused"] for k, c in r["summary"].items() if c.get("batch_refused")}
        assert refused == ({cmd_vel: 2} if name == "on" else {}), (name, refused)
