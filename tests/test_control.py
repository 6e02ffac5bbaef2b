"""PID, trajectory sampling and a closed-loop step on the MuJoCo arm (no network)."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from hilsim.core import msgs
from hilsim.core.config import ConfigError, PidGains
from hilsim.core.scenario import load_scenario
from hilsim.sim import control

JOINTS = ["joint_1", "joint_2", "joint_3"]
DT = 0.001


def pid(**kw: float) -> control.Pid:
    lo = kw.pop("lo", -math.inf)
    hi = kw.pop("hi", math.inf)
    return control.Pid(PidGains(**kw), lo, hi)


# ---------------------------------------------------------------- PID
def test_p_only_is_proportional() -> None:
    c = pid(kp=10.0)
    assert c.update(1.0, 0.0, 0.75, 0.0, DT) == pytest.approx(2.5)
    assert c.update(0.0, 0.0, 0.1, 0.0, DT) == pytest.approx(-1.0)
    assert c.integral == 0.0


def test_integral_accumulates_and_anti_windup_clamps_it() -> None:
    c = pid(kp=0.0, ki=10.0, i_limit=0.5)
    assert c.update(1.0, 0.0, 0.0, 0.0, DT) == pytest.approx(10.0 * 1.0 * DT)
    for _ in range(1000):
        u = c.update(1.0, 0.0, 0.0, 0.0, DT)
    assert u == pytest.approx(0.5)  # |ki * integral| <= i_limit
    assert c.ki * c.integral == pytest.approx(0.5)
    # Error reverses: recovery starts at once instead of unwinding a huge integral.
    u = c.update(0.0, 0.0, 1.0, 0.0, DT)
    assert u < 0.5


def test_no_integration_while_saturated_in_the_same_direction() -> None:
    c = pid(kp=100.0, ki=10.0, lo=-5.0, hi=5.0)
    for _ in range(100):
        assert c.update(1.0, 0.0, 0.0, 0.0, DT) == 5.0
    assert c.integral == 0.0  # saturated upward with a positive error: frozen
    # Saturated upward but the error is now negative: integration resumes.
    c.update(0.0, 0.0, 0.01, 0.0, DT)
    assert c.integral < 0.0


def test_output_limit_clamps_to_the_tighter_of_config_and_actuator() -> None:
    c = pid(kp=100.0, output_limit=3.0, lo=-12.0, hi=12.0)
    assert c.update(1.0, 0.0, 0.0, 0.0, DT) == 3.0
    assert c.update(-1.0, 0.0, 0.0, 0.0, DT) == -3.0
    c.set("output_limit", 50.0)  # the actuator range still applies
    assert c.update(1.0, 0.0, 0.0, 0.0, DT) == 12.0
    asym = pid(kp=100.0, lo=-2.0, hi=7.0)
    assert asym.update(1.0, 0.0, 0.0, 0.0, DT) == 7.0
    assert asym.update(-1.0, 0.0, 0.0, 0.0, DT) == -2.0


def test_derivative_on_measurement_gives_no_kick_on_setpoint_step() -> None:
    c = pid(kp=10.0, kd=5.0)
    assert c.update(0.0, 0.0, 0.0, 0.0, DT) == 0.0
    # The setpoint jumps by 1: only the P term responds, no (1/dt)-sized derivative spike.
    assert c.update(1.0, 0.0, 0.0, 0.0, DT) == pytest.approx(10.0)
    # Measured motion is damped.
    assert c.update(1.0, 0.0, 0.0, 2.0, DT) == pytest.approx(10.0 - 5.0 * 2.0)


def test_velocity_feedforward_and_reference_damping() -> None:
    c = pid(kp=0.0, kd=1.0, feedforward=0.5)
    # On target and moving with the reference: kd term is zero, feed-forward remains.
    assert c.update(0.0, 2.0, 0.0, 2.0, DT) == pytest.approx(0.5 * 2.0)
    c.set("feedforward", 0.0)
    assert c.update(0.0, 2.0, 0.0, 2.0, DT) == pytest.approx(0.0)


def test_set_ki_zero_drops_the_integral() -> None:
    c = pid(kp=0.0, ki=10.0, i_limit=1.0)
    for _ in range(50):
        c.update(1.0, 0.0, 0.0, 0.0, DT)
    assert c.integral > 0
    c.set("i_limit", 0.1)
    assert c.ki * c.integral == pytest.approx(0.1)
    c.set("ki", 0.0)
    assert c.integral == 0.0


def test_check_parameter() -> None:
    assert control.check_parameter("joint_2.kp", 80.0, JOINTS) == (1, "kp")
    assert "unknown joint" in control.check_parameter("joint_9.kp", 1.0, JOINTS)
    assert "unknown gain" in control.check_parameter("joint_2.kx", 1.0, JOINTS)
    assert "not finite" in control.check_parameter("joint_2.kp", math.nan, JOINTS)
    assert ">= 0" in control.check_parameter("joint_2.kd", -1.0, JOINTS)
    assert "> 0" in control.check_parameter("joint_2.i_limit", 0.0, JOINTS)


def test_a_gain_is_checked_by_the_schemas_rule_for_every_caller() -> None:
    # the live rule is the scenario's (PidGains): what one refuses the other refuses, field by field
    for f in control.GAIN_FIELDS:
        for v in (-1.0, 0.0, 2.5, math.inf):
            why = control.check_gain(f"joint_2.{f}", f, v)
            try:
                PidGains(**{"kp": 1.0, f: v})
                schema_ok = math.isfinite(v)  # the schema allows i_limit inf (its default); a live value is finite
            except ValueError:
                schema_ok = False
            assert (why is None) == schema_ok, (f, v, why)
    # the panel's case of issue 45: a negative feedforward, refused in one line naming the field
    assert control.check_gain("joint_2.feedforward", "feedforward", -0.5) == \
        "joint_2.feedforward: value -0.5 must be >= 0"
    assert control.check_gain("joint_2.output_limit", "output_limit", 0.0) == \
        "joint_2.output_limit: value 0.0 must be > 0"


def test_gains_fall_back_to_default_and_bad_names_fail() -> None:
    g = {"default": PidGains(kp=1.0), "joint_2": PidGains(kp=2.0)}
    assert [x.kp for x in control.gains_for(g, JOINTS)] == [1.0, 2.0, 1.0]
    with pytest.raises(ConfigError, match=r"controller.gains: no gains for joint_1"):
        control.gains_for({"joint_2": PidGains(kp=2.0)}, JOINTS)
    with pytest.raises(ConfigError, match=r"controller.gains.joint_7: not a joint"):
        control.gains_for({"default": PidGains(kp=1.0), "joint_7": PidGains(kp=2.0)}, JOINTS)


# ---------------------------------------------------------------- trajectories
def point(pos: list[float], t: float, vel: list[float] | None = None) -> msgs.JointTrajectoryPoint:
    return msgs.JointTrajectoryPoint(positions=pos, velocities=vel or [], time_from_start=msgs.duration(t))


def traj(names: list[str], *points: msgs.JointTrajectoryPoint, start_ns: int = 0) -> msgs.JointTrajectory:
    return msgs.JointTrajectory(header=msgs.header(start_ns), joint_names=names, points=list(points))


S = 1_000_000_000


def test_hermite_hits_points_and_velocities() -> None:
    tr = traj(JOINTS, point([0, 0, 0], 0, [0, 0, 0]), point([1, 2, -1], 1, [0.5, 0, 0]), point([2, 2, 0], 2, [0, 0, 0]))
    s = control.TrajectorySampler(tr, JOINTS, 10 * S, np.zeros(3))
    p, v = s.sample(10 * S)
    assert np.allclose(p, 0) and np.allclose(v, 0)
    p, v = s.sample(11 * S)
    assert np.allclose(p, [1, 2, -1]) and np.allclose(v, [0.5, 0, 0])
    # Midpoint of a Hermite segment with zero end velocities: halfway, speed 1.5 * dp/dt.
    p, v = s.sample(int(10.5 * S))
    assert np.allclose(p, [0.5 - 0.125 * 0.5, 1.0, -0.5])
    assert np.allclose(v, [1.5 - 0.25 * 0.5, 3.0, -1.5])
    assert s.progress(11 * S) == pytest.approx(0.5)
    assert not s.done(11 * S) and s.done(12 * S)


def test_hermite_is_the_textbook_formula_bit_for_bit() -> None:
    """sample() works joint by joint on floats (it runs every control step): its values are the
    cubic Hermite basis evaluated on whole arrays, bit for bit, at knots, between them and past the
    ends, so a run is the same whichever way the arithmetic is written."""
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.01, 0.2, 30))
    tr = traj(JOINTS, *(point(rng.uniform(-1, 1, 3).tolist(), float(x),
                              rng.uniform(-1, 1, 3).tolist() if k % 3 else None) for k, x in enumerate(t)))
    s = control.TrajectorySampler(tr, JOINTS, S, np.zeros(3))
    times = [S + round(x * 1e9) for x in t] + [int(v) for v in rng.integers(0, 8 * S, 3000)]
    for now in times:
        x = (now - s.start_ns) * 1e-9
        p, v = s.sample(now)
        if x < s.t[0] or x >= s.t[-1]:
            assert not v.any()
            continue
        i = int(np.searchsorted(s.t, x, side="right")) - 1
        h = s.t[i + 1] - s.t[i]
        u = (x - s.t[i]) / h
        u2, u3 = u * u, u * u * u
        p0, p1, v0, v1 = s.pos[i], s.pos[i + 1], s.vel[i], s.vel[i + 1]
        want_p = (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * h * v0 + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * h * v1
        want_v = (((6 * u2 - 6 * u) * p0 + (-6 * u2 + 6 * u) * p1) / h
                  + (3 * u2 - 4 * u + 1) * v0 + (3 * u2 - 2 * u) * v1)
        assert p.tobytes() == want_p.tobytes() and v.tobytes() == want_v.tobytes(), now


def test_hold_first_point_before_start_and_last_after_end() -> None:
    tr = traj(JOINTS, point([0.1, 0.2, 0.3], 0), point([1, 1, 1], 0.5))
    s = control.TrajectorySampler(tr, JOINTS, 2 * S, np.zeros(3))
    p, v = s.sample(1 * S)
    assert np.allclose(p, [0.1, 0.2, 0.3]) and np.allclose(v, 0)
    p, v = s.sample(9 * S)
    assert np.allclose(p, [1, 1, 1]) and np.allclose(v, 0)
    assert s.progress(1 * S) == 0.0 and s.progress(9 * S) == 1.0


def test_missing_velocities_use_finite_differences() -> None:
    tr = traj(["joint_1"], point([0.0], 0), point([1.0], 1), point([3.0], 2))
    s = control.TrajectorySampler(tr, ["joint_1"], 0, np.zeros(1))
    assert s.vel[:, 0] == pytest.approx([0.0, 1.5, 0.0])  # central difference inside, rest at the ends
    _, v = s.sample(S)
    assert v[0] == pytest.approx(1.5)


def test_joint_reordering_and_subset_keep_the_others() -> None:
    base = np.array([0.5, -0.5, 0.25])
    tr = traj(["joint_3", "joint_1"], point([1.0, 2.0], 0), point([3.0, 4.0], 1))
    s = control.TrajectorySampler(tr, JOINTS, 0, base)
    p, _ = s.sample(5 * S)
    assert np.allclose(p, [4.0, -0.5, 3.0])
    p, _ = s.sample(0)
    assert np.allclose(p, [2.0, -0.5, 1.0])


def test_late_first_point_starts_from_the_base() -> None:
    tr = traj(["joint_1"], point([1.0], 1.0))
    s = control.TrajectorySampler(tr, ["joint_1"], 0, np.array([0.0]))
    assert s.sample(0)[0][0] == 0.0
    assert 0.0 < s.sample(S // 2)[0][0] < 1.0
    assert s.sample(S)[0][0] == 1.0


@pytest.mark.parametrize(
    ("tr", "reason"),
    [
        (traj(["joint_1", "wrist"], point([0, 0], 0)), "unknown joint"),
        (traj(["joint_1", "joint_1"], point([0, 0], 0)), "twice"),
        (traj(["joint_1"], point([0], 1), point([1], 1)), "increasing"),
        (traj(["joint_1"], point([0, 1], 0)), "positions"),
        (traj(["joint_1"], point([0], 0, [1, 2])), "velocities"),
        (traj(["joint_1"], point([math.nan], 0)), "non-finite"),
        (traj(["joint_1"], point([5.0], 0)), "outside its limits"),
        (traj(["joint_1"]), "no points"),
    ],
)
def test_bad_trajectories_are_rejected(tr: msgs.JointTrajectory, reason: str) -> None:
    lower, upper = np.full(3, -3.0), np.full(3, 3.0)
    with pytest.raises(control.TrajectoryError, match=reason):
        control.TrajectorySampler(tr, JOINTS, 0, np.zeros(3), lower, upper)


def test_joint_table_reads_names_and_limits() -> None:
    sc = load_scenario("arm")
    tab = control.joint_table(sc.world.model)
    assert tab.names == tuple(f"joint_{i}" for i in range(1, 7))
    assert tab.effort_upper[1] == pytest.approx(15.0) and tab.effort_lower[1] == pytest.approx(-15.0)
    assert tab.lower[1] < 0 < tab.upper[1]


def test_step_figures() -> None:
    t = np.arange(1, 1001) * DT
    y = 1 - np.exp(-t / 0.1)
    f = control.step_figures(t, y, 0.0, 1.0, 0.02)
    assert f.rise_time == pytest.approx(0.1 * math.log(9), abs=2e-3)
    assert f.overshoot == 0.0
    assert f.settling_time == pytest.approx(0.1 * math.log(50), abs=2e-3)


# ---------------------------------------------------------------- closed loop on the arm
def gravity_compensated_arm(path: str) -> mujoco.MjModel:
    # body_gravcomp must be set before compiling: MuJoCo decides at compile time whether to
    # compute gravity compensation at all (setting model.body_gravcomp afterwards is ignored).
    spec = mujoco.MjSpec.from_file(path)
    for b in spec.bodies:
        b.gravcomp = 1.0
    m = spec.compile()
    m.opt.timestep = DT
    return m


def test_closed_loop_step_on_joint_2_settles() -> None:
    sc = load_scenario("arm")
    tab = control.joint_table(sc.world.model)
    m = gravity_compensated_arm(str(sc.world.model))
    assert m.ngravcomp > 0
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    gains = control.gains_for(sc.controller.gains, tab.names)
    pids = [control.Pid(g, tab.effort_lower[i], tab.effort_upper[i]) for i, g in enumerate(gains)]
    ref = d.qpos[: tab.n].copy()
    ref[1] += 0.3
    t, y = [], []
    for k in range(2000):
        q, v = d.qpos[: tab.n].tolist(), d.qvel[: tab.n].tolist()
        d.ctrl[:] = [p.update(ref[i], 0.0, q[i], v[i], DT) for i, p in enumerate(pids)]
        mujoco.mj_step(m, d)
        t.append((k + 1) * DT)
        y.append(d.qpos[1])
    f = control.step_figures(np.array(t), np.array(y), 0.0, ref[1], 0.01)
    assert f.settling_time < 2.0, f
    assert abs(y[-1] - ref[1]) < 0.01
    assert f.overshoot < 0.1, f
