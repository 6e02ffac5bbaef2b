"""Runs that can stay up (issue 36): ``--interactive`` at wall-clock pace, the bag split by size and
duration into files that read as one bag, and a recording that stops cleanly at its cap or before
the disk is full while the run goes on."""

from __future__ import annotations

import json
import os
import random
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from rosbags.rosbag2 import Reader
from util import finish, up

from hilsim.cli import build_parser
from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.recording import read_counts
from hilsim.launch.up import up_overrides
from hilsim.record.bag_read import info, open_bag
from hilsim.record.limits import BagSeries, stop_reason
from hilsim.tools.recording.play import Selector, schedule


def _overrides(*argv: str) -> dict[str, Any]:
    return up_overrides(build_parser().parse_args(["up", "arm", *argv]))[0]


def test_an_interactive_run_keeps_wall_clock_pace_unless_lockstep_is_asked_for() -> None:
    assert _overrides("--interactive")["clock.mode"] == "realtime"
    assert _overrides("--interactive", "--clock", "lockstep")["clock.mode"] == "lockstep"
    assert _overrides("--interactive", "--set", "clock.mode=lockstep")["clock.mode"] == "lockstep"
    assert "clock.mode" not in _overrides("--duration", "1")  # a task run: the scenario's clock (lockstep)


def _feed(series: BagSeries, n: int, per_flush: int, pause: float = 0.0, start: int = 0) -> None:
    """``n`` steps of /clock and joint states into a bag, flushed every ``per_flush`` steps, as the recorder does."""
    keys, gid = Keys(), transport.new_gid()
    js = msgs.JointState(name=[f"joint_{i}" for i in range(6)], position=[0.1] * 6, velocity=[0.0] * 6,
                         effort=[0.0] * 6)
    rng = random.Random(n)
    for i in range(start, start + n):
        stamp = msgs.stamp(i * 1_000_000)
        js.header.stamp = stamp
        js.position = [rng.random() for _ in range(6)]  # what zstd cannot squeeze to nothing
        now = time.time_ns()
        series.writer.add(keys.clock, msgs.encode(msgs.Clock(clock=stamp)), now, i + 1, gid)
        series.writer.add(keys.topic("joint_states"), msgs.encode(js), now, i + 1, gid)
        if (i + 1) % per_flush == 0:
            series.flush()
            time.sleep(pause)


def test_a_split_bag_is_one_bag_for_every_reader(tmp_path: Path, capsys: Any) -> None:
    """``logger.max_bag_size``: a new file once the current one is as large; each file complete, every
    split listed in ``metadata.yaml`` as it happens, and the files read as one bag by rosbags' Reader,
    ``hilsim bag info`` and ``hilsim play``'s schedule, every message once, in order."""
    d = tmp_path / "bag"
    series = BagSeries(d, max_size=40_000, metadata={"scenario": "arm"})
    _feed(series, 400, 100)  # the first split comes with the first flush past 40 kB
    assert series.splits >= 1
    listed = yaml.safe_load((d / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert listed["relative_file_paths"] == [p.name for p in series.files[:-1]]  # the closed ones, mid-run
    with Reader(d) as r:  # a valid bag while the run goes on
        assert r.message_count == listed["message_count"] > 0
    _feed(series, 1600, 100, start=400)
    series.close()
    files = sorted(d.glob("*.mcap"))
    assert len(files) >= 4 and all(f.stat().st_size < 40_000 + 80_000 for f in files), files
    meta = yaml.safe_load((d / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [f"bag_{i}.mcap" for i in range(len(files))]
    assert meta["message_count"] == 4000 and sum(f["message_count"] for f in meta["files"]) == 4000
    with Reader(d) as r:
        got = [(c.topic, t) for c, t, _ in r.messages()]
    assert len(got) == 4000 and [t for _, t in got] == sorted(t for _, t in got)
    bag = open_bag(d)
    assert bag.complete and bag.message_count == 4000
    clock = [m.pub_ns for m in bag.messages() if m.topic == "/clock"]
    assert clock == [i * 1_000_000 for i in range(2000)]  # every step once, across the files
    items = schedule(bag, Selector("/clock"), None, False)
    assert [it.sim_ns for it in items] == clock
    text = info(d)
    assert f"Files:             {', '.join(f'bag_{i}.mcap' for i in range(len(files)))}" in text
    assert "Messages:          4000" in text and "Sim time:          0.000000 s to 1.999000 s" in text


@pytest.mark.serial  # wall-clock timing: failed two tests at a time
def test_a_bag_splits_by_duration(tmp_path: Path) -> None:
    series = BagSeries(tmp_path, max_duration=0.1)
    _feed(series, 150, 10, pause=0.04)  # a flush every 40 ms, 15 of them: a new file about every fourth
    series.close()
    meta = yaml.safe_load((tmp_path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert len(meta["relative_file_paths"]) >= 3 and meta["message_count"] == 300, meta["relative_file_paths"]
    assert all(f["duration"]["nanoseconds"] < 0.1e9 + 0.05e9 for f in meta["files"])


def test_the_recording_stops_at_its_cap_or_the_disks_floor(tmp_path: Path) -> None:
    assert stop_reason(tmp_path, 10, 0, 0) is None
    assert "logger.max_size" in (stop_reason(tmp_path, 2_000_000, 2_000_000, 0) or "")
    assert stop_reason(tmp_path, 1_999_999, 2_000_000, 1) is None
    free = os.statvfs(tmp_path).f_bavail * os.statvfs(tmp_path).f_frsize
    assert "logger.min_free" in (stop_reason(tmp_path, 0, 0, free + 10**12) or "")


@pytest.fixture
def small_disk(tmp_path: Path) -> Any:
    """A 24 MB file system of its own (tmpfs, mounted as root), so the disk-full path is taken without
    filling the machine's disk; skipped where nothing can be mounted."""
    d = tmp_path / "disk"
    d.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(d)],
                                           capture_output=True).returncode != 0:
        pytest.skip("a tmpfs cannot be mounted here (root needed)")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


@pytest.mark.e2e
def test_the_recorder_stops_before_the_disk_is_full_and_the_run_goes_on(small_disk: Path) -> None:
    """On a 24 MB disk with ``logger.min_free`` 18 MB and the bag split every 400 kB: the recorder stops
    after about 6 MB, says so in one line, in the summary and in ``record_summary.json``, with both
    files closed whole (the split bag one bag, every message it took in recorded); physics runs the
    whole duration and the run ends as any other (STOPPED by its duration, not FAILED)."""
    run = small_disk / "run"
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    try:
        out = finish(up("arm", "--duration", "4", "--router", ep, "--out", str(run),
                        "--set", "logger.max_bag_size=400kB", "--set", "logger.min_free=18MB"), 300)
    finally:
        router.close()
    assert "result: STOPPED (duration)" in out, out
    assert "  logger: recording stopped at sim time " in out and "logger.min_free (18.0 MB)" in out, out
    assert "sim time 4.0" in out, out  # physics went on to the end
    counts, stopped = read_counts(run)
    assert stopped is not None and "logger.min_free" in stopped["reason"] and stopped["after_stop"] > 0, stopped
    assert 0 < stopped["sim_time"] < 3.5, stopped
    for k, c in counts.items():
        assert c["received"] == c["recorded"] == c["bagged"] and c["lost"] == 0, (k, c)
    bag = open_bag(run)
    files = sorted((run / "bag").glob("*.mcap"))
    assert bag.complete and len(files) >= 3, (files, out)
    assert bag.message_count == sum(c["bagged"] for c in counts.values())
    meta = yaml.safe_load((run / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [f.name for f in files]
    clock = [m.pub_ns for m in bag.messages() if m.topic == "/clock"]
    assert clock == [i * 1_000_000 for i in range(len(clock))] and len(clock) == counts[Keys().clock]["received"]
    summary_line = [ln for ln in out.splitlines() if ln.startswith("  recording stopped at sim time")]
    assert len(summary_line) == 1, out
    assert json.loads((run / "record_summary.json").read_text())["_recording_stopped"]["bytes"] > 4_000_000
    from hilsim.core.recording import contents

    assert contents(run / "recording.rrd").last_sim_ns is not None  # the .rrd closed whole, readable
