"""Same seed, same bag (docs/recording.md): in lockstep a run with a task ends on a step the task sets
(physics stops sim time ``TASK_END_MARGIN_NS`` after the task's result), so two runs with the same seed
record the same messages, message for message; ``hilsim bag diff`` says so, and says where two seeds'
bags first differ. Checked again with the mcap library's own reader, independently of hilsim's."""

from __future__ import annotations

import fnmatch
import os
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

from hilsim.record.bag_diff import WALL_TOPICS

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parent.parent
TARGET = "[[0.5,-0.4,0.2,0.0,-0.5,0.0]]"  # one target, reached at some 2 s of sim time


def _payloads(run: Path) -> dict[str, list[Any]]:
    """Each topic's payloads in order of publish time (the sim stamp), read with mcap's reader; the
    wall-clock topics (health, logs) and the stamp-less ones (their publish time is the receive time) aside;
    a planner's result decoded (mcap_ros2's decoder, from the schema in the bag), its planning time (wall) aside."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    decoders = DecoderFactory()
    out: dict[str, list[tuple[int, int, Any]]] = defaultdict(list)
    for f in sorted((run / "bag").glob("*.mcap")):
        with f.open("rb") as fh:
            for i, (schema, channel, message) in enumerate(make_reader(fh).iter_messages(log_time_order=False)):
                if any(fnmatch.fnmatchcase(channel.topic, p) for p in WALL_TOPICS):
                    continue
                if message.publish_time == message.log_time:
                    continue
                value: Any = bytes(message.data)
                if schema is not None and "planning_time" in schema.data.decode():
                    decode = decoders.decoder_for(channel.message_encoding, schema)
                    assert decode is not None
                    m = decode(message.data)
                    value = repr({k: getattr(m, k) for k in m.__slots__ if k != "planning_time"})
                out[channel.topic].append((message.publish_time, i, value))
    return {t: [d for *_, d in sorted(ms, key=lambda x: x[:2])] for t, ms in out.items()}


def test_two_runs_with_the_same_seed_record_the_same_bag(tmp_path: Path) -> None:
    runs = {name: tmp_path / name for name in ("a", "b", "other")}
    seeds = {"a": "3", "b": "3", "other": "4"}
    procs = {name: subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--seed", seeds[name], "--out",
                                     str(d), "--set", f"task.targets={TARGET}"],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                                    start_new_session=True)
             for name, d in runs.items()}  # side by side: how fast each goes changes nothing
    outs = {}
    try:
        for name, p in procs.items():
            outs[name] = p.communicate(timeout=400)[0]
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    for name, p in procs.items():
        assert p.returncode == 0, outs[name]
    end = {name: next(ln for ln in out.splitlines() if ln.startswith("  sim time ")).split(",")[0] for name, out in
           outs.items()}
    assert end["a"] == end["b"], end  # the same last step
    same = subprocess.run([sys.executable, "-m", "hilsim.cli", "bag", "diff", str(runs["a"]), str(runs["b"])],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert same.returncode == 0 and "the bags hold the same messages" in same.stdout, same
    differ = subprocess.run([sys.executable, "-m", "hilsim.cli", "bag", "diff", str(runs["a"]), str(runs["other"])],
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    assert differ.returncode == 1 and "the bags differ on" in differ.stdout, differ
    # where: a topic, a message, a sim time and a field, e.g. "/arm/imu message 1 at t=0.000 s: linear_acceleration.x"
    first = differ.stdout.splitlines()[1].strip()
    topic, rest = first.split(" message ", 1)
    index = int(rest.split()[0]) - 1
    assert " at t=" in rest and ": " in rest, first
    # checked with mcap's reader: the same seed, the same payloads on every topic; the other seed's differ there
    pa, pb, po = _payloads(runs["a"]), _payloads(runs["b"]), _payloads(runs["other"])
    assert pa.keys() == pb.keys() and all(pa[t] == pb[t] for t in pa), [t for t in pa if pa[t] != pb.get(t)]
    assert len(pa["/clock"]) > 1000, len(pa["/clock"])
    if topic in pa and index < min(len(pa[topic]), len(po.get(topic, []))):
        assert pa[topic][index] != po[topic][index], first
        assert pa[topic][:index] == po[topic][:index], first  # and not before
