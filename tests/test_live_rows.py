"""The live viewer's rows (hilsim.record.live_rows): the file gets every row, the live stream each dense
entity's rows thinned to 30 per second of sim time (a plot's to 10), most health values left out, log lines and
strips whole; both read back with Rerun's own reader."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from hilsim.record.live_rows import LIVE_RATE_HZ, PLOT_RATE_HZ, LiveTee
from hilsim.record.rows.common import TIMELINE, rr


def _read(data: bytes, path: Path) -> dict[str, int]:
    """Rows per entity of an RRD stream."""
    from rerun.chunk import RrdReader

    path.write_bytes(data)
    rows: dict[str, int] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = RrdReader(path)
        chunks = list(reader.stream().to_chunks())
    for c in chunks:
        if not c.is_static:
            rows[c.entity_path] = rows.get(c.entity_path, 0) + c.num_rows
    return rows


def test_the_live_stream_gets_every_dense_entity_thinned_and_logs_and_strips_whole(tmp_path: Path) -> None:
    file_rec = rr.RecordingStream("hilsim")
    file_sink = file_rec.binary_stream()
    live_rec = rr.RecordingStream("hilsim", recording_id=file_rec.get_recording_id())
    live_sink = live_rec.binary_stream()
    tee = LiveTee(file_rec, live_rec)
    tee.log("robot", rr.Points3D([[0, 0, 0]]), static=True)
    # 2 s of sim time at 1 kHz, in flushes of 0.2 s as the recorder sends them
    for k in range(10):
        ns = np.arange(k * 200, (k + 1) * 200, dtype=np.int64) * 1_000_000
        idx = [rr.TimeColumn(TIMELINE, duration=ns.astype("timedelta64[ns]"))]
        tee.send_columns("joints/j1/position", idx, rr.Scalars.columns(scalars=np.sin(ns * 1e-9)))
        tee.send_columns("robot/j1", idx, rr.Transform3D.columns(translation=np.zeros((ns.size, 3))))
        tee.send_columns("health/physics/level", idx, rr.Scalars.columns(scalars=np.zeros(ns.size)))
        tee.send_columns("health/physics/steps", idx, rr.Scalars.columns(scalars=np.zeros(ns.size)))
        tee.send_columns("joint_states_throttle/position/0", idx, rr.Scalars.columns(scalars=np.zeros(ns.size)))
        tee.send_columns("log/physics", idx[:1], rr.TextLog.columns(text=[f"line {i}" for i in ns]))
    strips = [rr.TimeColumn(TIMELINE, duration=np.array([0, 1_000_000, 2_000_000], "timedelta64[ns]"))]
    tee.send_columns("planner/path", strips, rr.LineStrips3D.columns(
        strips=[[[0, 0, 0], [1, 1, 1]]] * 3).partition([1, 1, 1]))
    tee.set_time(TIMELINE, duration=np.timedelta64(5, "s"))
    tee.log("planner/joint_space", rr.LineStrips2D([[[0, 0], [1, 1]]]))
    file_rec.flush()
    live_rec.flush()
    full = _read(file_sink.read(), tmp_path / "file.rrd")
    live = _read(live_sink.read(), tmp_path / "live.rrd")
    assert full["/joints/j1/position"] == 2000 and full["/log/physics"] == 2000 and full["/robot/j1"] == 2000, full
    # the file has every entity; the live stream no health value but the level, no joint_states_throttle
    assert full["/health/physics/steps"] == full["/joint_states_throttle/position/0"] == 2000, full
    assert "/health/physics/steps" not in live and "/joint_states_throttle/position/0" not in live, live
    # a transform: one row per 1/30 s of sim time, 2 s -> 60; a plot's one per 1/10 s, 2 s -> 20 (the periods'
    # boundaries fall inside a flush or between two)
    assert abs(live["/robot/j1"] - 2 * LIVE_RATE_HZ) <= 1, live
    assert abs(live["/joints/j1/position"] - 2 * PLOT_RATE_HZ) <= 1, live
    assert live["/health/physics/level"] == live["/joints/j1/position"], live
    assert live["/log/physics"] == 2000 and live["/planner/path"] == full["/planner/path"] == 3, live
    assert live["/planner/joint_space"] == full["/planner/joint_space"] == 1
    thinned = sum(live[e] for e in ("/joints/j1/position", "/robot/j1", "/health/physics/level"))
    assert tee.thinned == 3 * 2000 - thinned and tee.sent == thinned + 2003


def test_a_row_older_than_what_was_sent_is_not_sent_again() -> None:
    """A batch that comes late (a fleet robot's rows after its topic) never repeats a period already sent."""
    file_rec, live_rec = rr.RecordingStream("hilsim"), rr.RecordingStream("hilsim")
    file_rec.binary_stream()
    live_rec.binary_stream()
    tee = LiveTee(file_rec, live_rec)
    ns = np.arange(0, 100_000_000, 1_000_000, dtype=np.int64)
    idx = [rr.TimeColumn(TIMELINE, duration=ns.astype("timedelta64[ns]"))]
    tee.send_columns("a", idx, rr.Scalars.columns(scalars=np.zeros(ns.size)))
    first = tee.sent
    tee.send_columns("a", idx, rr.Scalars.columns(scalars=np.zeros(ns.size)))
    assert first == 1 and tee.sent == first  # period 0 of a plot's 100 ms, then nothing new


def test_until_a_viewer_joins_the_live_stream_gets_the_static_rows_only() -> None:
    """Nobody watching: the file gets every row, the live stream the static ones only; once active, the rows."""
    file_rec, live_rec = rr.RecordingStream("hilsim"), rr.RecordingStream("hilsim")
    file_rec.binary_stream()
    live_rec.binary_stream()
    sent: list[str] = []
    real_send, real_log = live_rec.send_columns, live_rec.log
    live_rec.send_columns = lambda e, **kw: (sent.append(e), real_send(e, **kw))  # type: ignore[method-assign]
    live_rec.log = lambda e, *a, **kw: (sent.append(e), real_log(e, *a, **kw))  # type: ignore[method-assign]
    watched = False
    tee = LiveTee(file_rec, live_rec, active=lambda: watched)
    idx = [rr.TimeColumn(TIMELINE, duration=np.array([0], "timedelta64[ns]"))]
    tee.log("world/table", rr.Points3D([[0, 0, 0]]), static=True)
    tee.log("planner/joint_space", rr.LineStrips2D([[[0, 0], [1, 1]]]))
    tee.send_columns("plot", idx, rr.Scalars.columns(scalars=[1.0]))
    assert sent == ["world/table"] and tee.sent == 0
    watched = True
    tee.log("planner/joint_space", rr.LineStrips2D([[[0, 0], [1, 1]]]))
    tee.send_columns("plot", idx, rr.Scalars.columns(scalars=[1.0]))
    assert sent == ["world/table", "planner/joint_space", "plot"] and tee.sent == 1
