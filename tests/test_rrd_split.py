"""The Rerun recording split by size like the bag (issue 42 item 4): ``logger.max_rrd_size`` and
``max_rrd_duration``, each file closed whole and said on the run's screen, nothing recorded lost across
a split, and every reader of a run's recording taking all of its files; ``--interactive`` bounded."""

from __future__ import annotations

import argparse
import os
import subprocess
import warnings
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from util import finish, up

from hilsim.core import transport
from hilsim.core.recording import (
    RecordingError,
    cmd_view,
    disable_analytics,
    read_counts,
    recording_files,
    recording_parts,
    rerun_env,
    rerun_executable,
)
from hilsim.core.scenario import load_scenario
from hilsim.launch.up import INTERACTIVE_FILE_BYTES, bound_interactive
from hilsim.record.bag_read import open_bag

# entities of the .rrd whose rows are one per sample of a bag topic (hilsim.record.rows)
PAIRS = {
    "/clock": "/clock",
    "/joints/joint_1/position/measured": "/arm/joint_states",
    "/joints/joint_1/position/truth": "/arm/truth/joint_states",
    "/joints/joint_1/effort/command": "/arm/joint_commands",
    "/joints/joint_1/position/reference": "/arm/controller/reference",
}


def test_a_runs_recording_files_in_order(tmp_path: Path) -> None:
    names = ["recording.restart-1.part-1.rrd", "recording.part-10.rrd", "recording.rrd", "recording.part-2.rrd",
             "recording.restart-1.rrd", "recording.restart-2.rrd", "recording.rrd.recovering", "step_report.rrd"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    want = ["recording.rrd", "recording.part-2.rrd", "recording.part-10.rrd", "recording.restart-1.rrd",
            "recording.restart-1.part-1.rrd", "recording.restart-2.rrd"]
    assert [p.name for p in recording_parts(tmp_path)] == want
    assert [p.name for p in recording_files(tmp_path / "recording.rrd")] == want  # the run's, all of it
    assert recording_files(tmp_path / "step_report.rrd") == [tmp_path / "step_report.rrd"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no recording"):
        recording_files(tmp_path / "empty")


def test_an_interactive_run_is_bounded_unless_told_otherwise() -> None:
    sc = load_scenario("arm", {})
    bound_interactive(sc)
    assert sc.logger.max_rrd_size == sc.logger.max_bag_size == INTERACTIVE_FILE_BYTES == 500_000_000
    sc = load_scenario("arm", {"logger.max_rrd_size": "2GB", "logger.max_bag_size": 0})
    bound_interactive(sc)
    assert (sc.logger.max_rrd_size, sc.logger.max_bag_size) == (2_000_000_000, 0)
    assert load_scenario("arm", {}).logger.max_rrd_size == 0  # a task run: unsplit, as before


def _sim_times(files: list[Path]) -> dict[str, list[int]]:
    """sim_time of every row of the PAIRS entities, read with Rerun's own reader, file by file."""
    disable_analytics()
    from rerun.chunk import RrdReader

    out: dict[str, list[int]] = defaultdict(list)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a file without its footer would warn: each must be whole
        for f in files:
            for chunk in RrdReader(f).stream().to_chunks():
                if chunk.entity_path in PAIRS:
                    out[chunk.entity_path] += chunk.to_record_batch().column("sim_time").cast("int64").to_pylist()
    return out


@pytest.mark.e2e
def test_a_split_recording_holds_every_sample_once(tmp_path: Path, capsys: Any, monkeypatch: Any) -> None:
    """A lockstep arm run with ``logger.max_rrd_size=1MB`` (and the bag split at 150 kB): two or more
    ``.rrd`` files, each closed whole (``rerun rrd verify``), one recording id and the layout in each,
    a line per closed file on the run's screen; read back with Rerun's reader, the rows of the per-step
    entities across the files are the bag's samples of the same run, sim time for sim time, each once;
    ``hilsim export`` and ``hilsim view`` take every file."""
    run = tmp_path / "run"
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    try:
        out = finish(up("arm", "--duration", "0.5", "--router", ep, "--out", str(run),
                        "--set", "logger.max_rrd_size=1MB", "--set", "logger.max_bag_size=150kB"), 300)
    finally:
        router.close()
    assert "result: STOPPED (duration)" in out, out
    files = recording_parts(run)
    assert len(files) >= 2 and files[0].name == "recording.rrd", (files, out)
    assert [f.name for f in files] == ["recording.rrd"] + [f"recording.part-{i}.rrd" for i in range(1, len(files))]
    closed = [ln for ln in out.splitlines() if ln.startswith("  logger: closed recording")]
    assert [ln.split()[2] for ln in closed] == [f.name for f in files[:-1]], out
    assert f"recording on in {files[1].name}" in closed[0] and "up to sim time" in closed[0], closed
    assert any(ln.startswith("  logger: closed bag/bag_0.mcap") for ln in out.splitlines()), out
    assert f"recording: {run / 'recording.rrd'} and {len(files) - 1} more file" in out, out
    assert "closed recording.rrd" in (run / "logger.log").read_text()

    r = subprocess.run([rerun_executable(), "rrd", "verify", *map(str, files)], capture_output=True, text=True,
                       env={**os.environ, **rerun_env()}, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    from rerun.chunk import RrdReader

    ids = {(s.application_id, s.recording_id) for f in files for s in RrdReader(f).recordings()}
    assert len(ids) == 1, ids  # one recording: Rerun's viewer opens the files as one
    assert all(len(RrdReader(f).blueprints()) == 1 for f in files)  # the layout in each

    got = _sim_times(files)
    bag: dict[str, list[int]] = defaultdict(list)
    for m in open_bag(run).messages():
        bag[m.topic].append(m.pub_ns)
    counts, _ = read_counts(run)
    for entity, topic in PAIRS.items():
        assert len(got[entity]) == len(set(got[entity])) == len(bag[topic]) > 400, (entity, len(got[entity]))
        assert sorted(got[entity]) == sorted(bag[topic]), entity
    assert sum(c["recorded"] for c in counts.values()) == sum(len(v) for v in bag.values())
    assert sum(1 for f in files if _sim_times([f])["/clock"]) >= 2  # the clock's rows spread over the files

    from hilsim.tools.recording.export import cmd_export

    assert cmd_export(argparse.Namespace(run=str(run), out=str(tmp_path / "csv"), to="csv", runs="runs")) == 0
    clock_csv = tmp_path / "csv" / "clock" / "Scalars.scalars.csv"
    assert len(clock_csv.read_text().splitlines()) == 1 + len(bag["/clock"])  # every file's rows

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    capsys.readouterr()
    assert cmd_view(argparse.Namespace(rrd=str(run), runs="runs")) == 1  # no display: the command to run
    assert " ".join(map(str, files)) in capsys.readouterr().err
