"""Table II figures: the metrics against analytic step responses, and ``hilsim report step`` end to end."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hilsim.tools.tuning.metrics import step_figures

REPO = Path(__file__).resolve().parent.parent


def second_order(t: np.ndarray, zeta: float, wn: float) -> np.ndarray:
    """Unit step response of wn² / (s² + 2ζ wn s + wn²), 0 < ζ < 1."""
    wd = wn * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * wn * t) / math.sqrt(1 - zeta**2) * np.sin(wd * t + math.acos(zeta))


@pytest.mark.parametrize("zeta,wn", [(0.2, 8.0), (0.5, 10.0), (0.7, 25.0)])
def test_second_order_overshoot_and_peak_time(zeta: float, wn: float) -> None:
    t = np.arange(0.0, 8.0, 1e-4)
    y0, step = 0.3, -0.5  # any start, either direction
    f = step_figures(t, y0 + step * second_order(t, zeta, wn), y0, y0 + step)
    root = math.sqrt(1 - zeta**2)
    assert f.overshoot_pct == pytest.approx(100 * math.exp(-zeta * math.pi / root), rel=1e-4)
    assert f.peak_time_s == pytest.approx(math.pi / (wn * root), abs=2e-4)
    # the 2 % envelope bound: settled no later than ln(50/√(1-ζ²))/(ζ wn)
    assert f.settling_time_s <= math.log(50 / root) / (zeta * wn) + 1e-3
    assert f.steady_state_error < 1e-5


def test_a_quantised_peak_is_timed_at_the_middle_of_the_count_it_holds() -> None:
    """An encoder of 8192 counts per turn holds the top count of a 0.2 rad step's overshoot for ~30 ms:
    the peak time is the middle of that, within 2 ms of the analytic peak (its first sample is not)."""
    zeta, wn = 0.6, 28.0
    t = np.arange(0.0, 1.0, 2e-3)
    q = 2 * math.pi / 8192
    y = np.round(0.2 * second_order(t, zeta, wn) / q) * q
    f = step_figures(t, y, 0.0, 0.2)
    analytic = math.pi / (wn * math.sqrt(1 - zeta**2))
    first = float(t[np.argmax(y)])
    assert abs(f.peak_time_s - analytic) < 2e-3 < abs(first - analytic)


def test_first_order_rise_and_settling() -> None:
    tau = 0.13
    t = np.arange(0.0, 2.0, 1e-3)  # coarse on purpose: crossings are interpolated
    f = step_figures(t, 1 - np.exp(-t / tau), 0.0, 1.0)
    assert f.rise_time_s == pytest.approx(tau * math.log(9), abs=2e-4)
    assert f.settling_time_s == pytest.approx(tau * math.log(50), abs=2e-4)
    assert f.overshoot_pct == 0.0
    # no overshoot: the peak is where it first comes within 1e-3 of the target
    assert f.peak_time_s == pytest.approx(tau * math.log(1e3), abs=2e-3)


def test_steady_state_error_and_never_settling() -> None:
    t = np.arange(0.0, 1.0, 1e-3)
    f = step_figures(t, 0.9 * (1 - np.exp(-t / 0.05)), 0.0, 1.0)
    assert f.steady_state_error == pytest.approx(0.1, abs=1e-6)
    assert math.isinf(f.settling_time_s) and math.isinf(f.peak_time_s) and math.isinf(f.rise_time_s)
    # a response that never even reaches 10 % has never risen either (inf, not nan)
    assert math.isinf(step_figures(t, 0.05 * (1 - np.exp(-t / 0.05)), 0.0, 1.0).rise_time_s)


def test_report_step_end_to_end(tmp_path: Path) -> None:
    """One joint of the arm, a short window: the real services in lockstep, measured on the truth.
    The arm's gains give a fast response (well inside the paper's joint_4 row for rise time), and the
    run is reproducible: a second run gives the same figures to the last digit."""
    cmd = [sys.executable, "-m", "hilsim.cli", "report", "step", "arm", "--joints", "joint_4", "--step", "0.2",
           "--measure", "0.6", "--settle", "0.1", "--json"]
    outs = []
    for i in range(2):
        p = subprocess.run([*cmd, "--out", str(tmp_path / f"r{i}")], capture_output=True, text=True, cwd=REPO,
                           timeout=180)
        assert p.returncode == 0, p.stdout + p.stderr
        outs.append(json.loads(p.stdout))
    rep = outs[0]
    assert rep["robot"] == "arm" and [j["joint"] for j in rep["joints"]] == ["joint_4"]
    j = rep["joints"][0]
    assert set(j) == {"joint", "step_rad", "rise_time_s", "settling_time_s", "peak_time_s", "overshoot_pct",
                      "steady_state_error_rad"}
    assert j["step_rad"] == pytest.approx(0.2, abs=2e-4)  # from where the truth was: encoder-held home
    assert 0.02 < j["rise_time_s"] < 0.18
    assert j["settling_time_s"] is not None and j["rise_time_s"] < j["settling_time_s"] < 0.6
    assert j["steady_state_error_rad"] < 5e-3
    assert outs[1] == rep  # lockstep: same seed, same figures
    out = tmp_path / "r0"
    rows = list(csv.DictReader(open(out / "step_report.csv")))
    assert rows[0]["joint"] == "joint_4" and float(rows[0]["rise_time_s"]) == pytest.approx(j["rise_time_s"], abs=1e-6)
    assert (out / "step_report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "step_report.rrd").stat().st_size > 1000


def test_report_step_rover_end_to_end(tmp_path: Path) -> None:
    """The rover's eight loops by the real services in lockstep (physics, sensors, rover controller),
    measured on the truth: steering angles and traction speeds. Stated target, with the scenario's gains:
    traction rises within 0.15 s, settles (2 %) within 1.0 s, overshoots at most 10 %, ends inside the band;
    steering does not overshoot and has covered more than half of its step at the end of the 1 s window
    (at standstill the tyres' scrub holds it back: docs/seed-tables.md). The four wheels of a kind
    measure alike."""
    p = subprocess.run([sys.executable, "-m", "hilsim.cli", "report", "step", "rover", "--step", "0.2", "--speed",
                        "2.0", "--measure", "1.0", "--settle", "0.3", "--json", "--out", str(tmp_path)],
                       capture_output=True, text=True, cwd=REPO, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    rep = json.loads(p.stdout)
    wheels = ["fl", "fr", "rl", "rr"]
    assert rep["robot"] == "rover"
    assert [j["joint"] for j in rep["joints"]] == [f"{w}_steering" for w in wheels] + [f"{w}_traction" for w in wheels]
    steer, drive = rep["joints"][:4], rep["joints"][4:]
    for j in steer:
        assert set(j) == {"joint", "step_rad", "rise_time_s", "settling_time_s", "peak_time_s", "overshoot_pct",
                          "steady_state_error_rad"}
        assert j["step_rad"] == pytest.approx(0.2, abs=2e-3)  # from where the truth stood: angle ~0
        assert j["overshoot_pct"] <= 0.5
        assert 0.0 < j["steady_state_error_rad"] < 0.5 * 0.2
    for j in drive:
        assert set(j) == {"joint", "step_rad_s", "rise_time_s", "settling_time_s", "peak_time_s", "overshoot_pct",
                          "steady_state_error_rad_s"}
        assert j["step_rad_s"] == pytest.approx(2.0, abs=0.02)  # from the crawl (0.0067 rad/s)
        assert 0.01 < j["rise_time_s"] <= 0.15
        assert j["settling_time_s"] is not None and j["rise_time_s"] < j["settling_time_s"] <= 1.0
        assert 0.0 <= j["overshoot_pct"] <= 10.0 and j["peak_time_s"] < j["settling_time_s"]
        assert j["steady_state_error_rad_s"] < 0.02 * 2.0  # inside the 2 % band at the end
    for group, key in ((steer, "steady_state_error_rad"), (drive, "rise_time_s")):
        vals = [j[key] for j in group]
        assert max(vals) - min(vals) <= 0.05 * max(vals), vals
    rows = list(csv.DictReader(open(tmp_path / "step_report.csv")))
    assert [r["quantity"] for r in rows] == ["position"] * 4 + ["velocity"] * 4
    assert float(rows[4]["rise_time_s"]) == pytest.approx(drive[0]["rise_time_s"], abs=1e-6)
    assert (tmp_path / "step_report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "step_report.rrd").stat().st_size > 1000


def test_report_step_rover_bad_steps_say_why() -> None:
    """A step the rover cannot take is one line and exit 2, before any service starts."""
    for args, why in ((["--step", "2.0"], "steering step +2 rad: expected a non-zero angle strictly inside"),
                      (["--speed", "50"], "traction step +50 rad/s: expected a non-zero wheel speed"),
                      (["--joints", "joint_1"], "joint_1: not a loop of the rover")):
        p = subprocess.run([sys.executable, "-m", "hilsim.cli", "report", "step", "rover", *args],
                           capture_output=True, text=True, cwd=REPO, timeout=60)
        assert p.returncode == 2 and p.stderr.count("\n") == 1 and why in p.stderr, p.stderr


def test_the_verdict_against_the_paper_states_its_tolerance() -> None:
    """The paper's overshoot and steady-state error are 0: ours above 0 is never a plain "yes" (as
    0.020 % and 3.6e-05 rad once were), but "within tolerance", with the tolerance said; beyond it, "no"."""
    from hilsim.tools.tuning.metrics import Figures
    from hilsim.tools.tuning.rig import Experiment, Response
    from hilsim.tools.tuning.step_report import Row, format_table, summary_line, verdict

    def row(joint: str, overshoot_pct: float, error: float) -> Row:
        f = Figures(0.2, 0.204, 0.347, 0.434, overshoot_pct, error)
        resp = Response(Experiment(joint, 0.2), np.zeros(1), np.zeros(1), 0.0, 0.2)
        return Row(joint, f, resp)

    close = row("joint_1", 0.020, 3.6e-05)  # joint_1 as docs/seed-tables.md measured it
    exact, over = row("joint_2", 0.0, 0.0), row("joint_3", 1.0, 3.6e-05)  # 1 % of 0.2 rad: 2 mrad past
    assert verdict("joint_1", close.figures) == "within tolerance"
    assert verdict("joint_2", exact.figures) == "yes"
    assert verdict("joint_3", over.figures).startswith("no: overshoot 1.000 % (2.00 mrad) > 0.25 mrad")
    table = format_table([close, exact])
    assert "at or better (tolerance: overshoot <= 0.25 mrad past the target, steady-state error < 0.001 rad)" \
        in table.splitlines()[0], table
    assert table.splitlines()[2].endswith("| within tolerance |") and table.splitlines()[3].endswith("| yes |")
    line = summary_line([close, exact])
    assert line.startswith("at or better than the paper on every joint: yes within tolerance (") and \
        "overshoot <= 0.25 mrad past the target, steady-state error < 0.001 rad" in line, line
    assert summary_line([exact]) == "at or better than the paper on every joint: yes"
    assert summary_line([close, over]) == "at or better than the paper on every joint: no"
