"""``hilsim tune``: the oscillation analysis, the rule, writing the scenario, and the tuner end to end."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario
from hilsim.tools.tuning import autotune as tuning
from hilsim.tools.tuning.rig import Experiment, Response
from hilsim.tools.tuning.rig_run import loop_scenario
from hilsim.tools.tuning.step_report import measure

REPO = Path(__file__).resolve().parent.parent


def test_decay_ratio_and_period() -> None:
    """A decaying oscillation around the target: the ratio per period and the period are exact."""
    sigma, w = 1.5, 2 * math.pi * 12.0
    t = np.arange(0.0, 1.0, 1e-4)
    y = 0.3 - 0.01 * np.exp(-sigma * t) * np.cos(w * t)  # from 0.29 to 0.3: a 0.01 step
    r = Response(Experiment("j", 0.01), t, y, float(y[0]), 0.3)
    ratio, period, _ = tuning.decay_and_period(r)
    assert period == pytest.approx(1 / 12.0, rel=1e-3)
    assert ratio == pytest.approx(math.exp(-sigma / 12.0), rel=1e-3)
    # a response that does not oscillate has no ratio
    mono = 0.3 - 0.01 * np.exp(-20 * t)
    assert tuning.decay_and_period(Response(Experiment("j", 0.01), t, mono, 0.29, 0.3))[0] == 0.0


def test_ziegler_nichols_rule() -> None:
    g = tuning.ziegler_nichols_pid(tuning.Ultimate(ku=100.0, tu=0.2, how=""))
    assert g == pytest.approx({"kp": 60.0, "ki": 600.0, "kd": 1.5})


def test_write_gains_keeps_the_file(tmp_path: Path) -> None:
    sc = tmp_path / "arm.yaml"
    sc.write_text(f"extends: {REPO / 'config/arm.yaml'}\n# mine\ncontroller:\n  rate_hz: 1000\n  gains:\n"
                  "    default: {kp: 100.0, ki: 5.0, kd: 5.0}   # kept\n    joint_2: {kp: 1}\n\nplanner:\n"
                  "  planning_time: 1.0\n")
    tuning.write_gains(sc, "joint_2", {"kp": 12.5, "ki": 0.5, "kd": 0.75, "i_limit": 1.2})
    tuning.write_gains(sc, "joint_6", {"kp": 3.0, "ki": 0.0, "kd": 0.1, "i_limit": 0.3})
    text = sc.read_text()
    assert "# mine" in text and "# kept" in text and "planning_time" in text
    loaded = load_scenario(sc).controller.gains
    assert loaded["joint_2"].kp == 12.5 and loaded["joint_2"].i_limit == 1.2
    assert loaded["joint_6"].kd == 0.1 and loaded["default"].kp == 100.0
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"extends: {REPO / 'config/arm.yaml'}\n")
    with pytest.raises(ConfigError, match=r"no controller\.gains block"):
        tuning.write_gains(bad, "joint_2", {"kp": 1.0})


def test_tune_one_joint_end_to_end() -> None:
    """The relay tuner on joint_5, real services in lockstep: it finds gains that meet a stated target
    (rise <= 0.25 s, settling <= 0.35 s, no overshoot, error < 1e-3 rad on a 0.2 rad step), and the
    same gains, put into the scenario instead of set live, measure the same figures."""
    target = tuning.Target(rise_s=0.25, settling_s=0.35)
    lines: list[str] = []
    r = tuning.tune("arm", "joint_5", "relay", 0.2, target, lines.append, measure=0.5)
    assert r.ultimate.ku > 0 and 0 < r.ultimate.tu < 1
    assert not r.misses, (r.misses, "\n".join(lines))
    assert r.gains["kp"] < r.rule["kp"]  # the refinement moved off the rule
    assert any("trial" in ln for ln in lines)  # progress was shown
    g = dict(r.gains)
    (row,) = measure("arm", ["joint_5"], 0.2, measure_s=0.5, settle_s=0.1,
                     overrides={"controller.gains.joint_5": g})
    f = row.figures
    assert not target.misses(f), target.misses(f)
    assert f.settling_time_s == pytest.approx(r.figures.settling_time_s, abs=0.01)


def test_ziegler_nichols_one_joint_end_to_end() -> None:
    """The Ziegler–Nichols tuner (proportional only, kp doubled to the sustained oscillation) on joint_5,
    real services in lockstep: the ultimate point is found and the gains meet a stated target (rise <=
    0.25 s, settling <= 0.35 s, no overshoot, error < 1e-3 rad on a 0.2 rad step)."""
    target = tuning.Target(rise_s=0.25, settling_s=0.35)
    lines: list[str] = []
    r = tuning.tune("arm", "joint_5", "ziegler-nichols", 0.2, target, lines.append, measure=0.5)
    assert r.method == "ziegler-nichols" and "proportional only" in r.ultimate.how
    # the loop oscillated at the ultimate gain: decaying below it, sustained at or above it
    ratios = [float(ln.split("decay ratio ")[1].split()[0]) for ln in lines if "decay ratio" in ln]
    assert len(ratios) == 10 and min(ratios) < tuning.SUSTAINED <= max(ratios), "\n".join(lines)
    assert r.ultimate.ku > 0 and 0 < r.ultimate.tu < 1
    assert r.rule == pytest.approx(tuning.ziegler_nichols_pid(r.ultimate))
    assert not r.misses, (r.misses, "\n".join(lines))
    f = r.figures
    assert f.step == pytest.approx(0.2, abs=1e-3)
    assert 0 < f.rise_time_s <= 0.25 and f.rise_time_s < f.settling_time_s <= 0.35
    assert f.overshoot_pct <= tuning.MARGIN * tuning.ZERO_OVERSHOOT_PCT and f.steady_state_error < 1e-3
    assert all(math.isfinite(v) and v >= 0 for v in r.gains.values()) and r.gains["kp"] < r.rule["kp"]


def test_rover_loops_are_tuned_by_kind_and_judged_by_the_worst_wheel() -> None:
    """`hilsim tune rover steering|traction`: a kind is its four wheels' loops, traction a speed loop;
    a trial's figures are the worst wheel's; the steps alternate (the rover shuttles); the target is
    relative to the step. (The tuner itself runs on the rover as on the arm: docs/seed-tables.md has
    the gains it wrote; test_step_report.py::test_report_step_rover_end_to_end holds them to this target.)"""
    sc = loop_scenario("rover")
    steer, drive = tuning.loop_of(sc, "steering"), tuning.loop_of(sc, "traction")
    assert steer.joints == ("fl_steering", "fr_steering", "rl_steering", "rr_steering") and not steer.velocity
    assert drive.joints == ("fl_traction", "fr_traction", "rl_traction", "rr_traction") and drive.velocity
    assert tuning.loop_of(sc, "rr_traction").velocity and tuning.loop_of(sc, "rr_traction").joints == ("rr_traction",)
    assert [drive.sign(i) for i in range(4)] == [1.0, -1.0, 1.0, -1.0] and drive.kick == tuning.VELOCITY_KICK
    with pytest.raises(ConfigError, match="wheel_9: not a joint"):
        tuning.loop_of(sc, "wheel_9")
    arm = tuning.loop_of(loop_scenario("arm"), "joint_2")
    assert arm.sign(1) == 1.0 and arm.zeros(0.2) == (tuning.ZERO_OVERSHOOT_PCT, tuning.ZERO_TOL)
    assert drive.zeros(2.0) == pytest.approx((0.5, 0.02))
    target = tuning.rover_target(2.0)
    assert (target.rise_s, target.settling_s, target.overshoot_pct, target.steady_state_error) == \
        pytest.approx((0.25, 0.5, 0.5, 0.02))
    # four wheels: a fast one and a slow, overshooting one; the trial is as good as the worst
    t = np.arange(0.0, 1.0, 1e-3)
    fast = 1 - np.exp(-t / 0.02)
    slow = 1 - np.exp(-t / 0.1) * np.cos(20 * t)
    rs = [Response(Experiment("traction", 1.0), t, y, 0.0, 1.0, n, "velocity")
          for n, y in zip(drive.joints, [fast, fast, slow, fast], strict=True)]
    f = drive.figures(rs)
    fs = [drive.figures([r]) for r in rs]
    assert f.rise_time_s == max(x.rise_time_s for x in fs) and f.settling_time_s == fs[2].settling_time_s
    assert f.overshoot_pct == fs[2].overshoot_pct > 0 and fs[0].overshoot_pct == 0
