"""``hilsim bench loss`` reads a run's loss as its summary judges it (issue 42 item 3)."""

from __future__ import annotations

import json
from pathlib import Path

from hilsim.cli import build_parser
from hilsim.tools.bench.loss import _figures


def test_a_runs_missed_share_is_its_summarys(tmp_path: Path) -> None:
    (tmp_path / "record_summary.json").write_text(json.dumps({
        "0/clock": {"received": 900, "recorded": 900, "lost": 100, "dropped": 60},
        "0/arm/joint_states": {"received": 1000, "recorded": 1000, "lost": 0, "dropped": 0},
        "_recording_stopped": None}))
    out = ("summary:\n  sim time 3.000 s, real-time factor 0.987, clock realtime, seed 0\n"
           "  100 published samples never reached the recorder: clock 100\nresult: STOPPED (duration) 0/3 targets\n")
    f = _figures(tmp_path, out, 3)
    assert (f["received"], f["lost"], f["dropped_by_recorder"], f["lost_in_transport"], f["never_reached"]) == (
        1900, 100, 60, 40, 100)
    assert f["missed_share"] == 200 / 2100 and f["real_time_factor"] == 0.987
    assert f["result"] == "STOPPED (duration) 0/3 targets"
    assert "error" in _figures(tmp_path / "none", out, 1)
    args = build_parser().parse_args(["bench", "loss"])
    assert (args.runs, args.repeat, args.seconds) == (2, 3, 20.0)
