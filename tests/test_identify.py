"""``hilsim identify``'s parts without processes: the drive model a twin's joint is simulated with (and
the world stepping it in lockstep), the fit against data from the project's drive emulator's own model
(parameters the fit does not know), the encoder's quantum, and the twin file."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from hilsim.bridges.drive_emulator import DriveEmulatorConfig
from hilsim.bridges.drive_emulator import DriveModel as EmulatedMotor
from hilsim.core import msgs
from hilsim.core.config import ConfigError, DriveConfig
from hilsim.core.scenario import load_scenario
from hilsim.core.simclock import SimClock
from hilsim.sim.drive import DriveModel, simulate
from hilsim.sim.world import World
from hilsim.tools.tuning.identify.data import JointRecord
from hilsim.tools.tuning.identify.fit import LIMITS, Fit, encoder_quantum, fit_record
from hilsim.tools.tuning.identify.twin import twin_data, write_twin
from hilsim.tools.tuning.metrics import step_figures

REPO = Path(__file__).resolve().parent.parent
EMULATED = REPO / "config" / "hil" / "arm-can-emulated.yaml"


TIMES = np.arange(1, 1001) * 1e-3  # 1 ms steps to 1 s


def response(cfg: DriveConfig, step: float, t_step: float = 0.05) -> np.ndarray:
    m = DriveModel(cfg, 0.0)
    m.command(t_step, step, 0.0)
    out = []
    for t in TIMES:
        m.advance(float(t))
        out.append(m.out_p)
    return np.array(out)


def test_the_drive_model_has_its_dead_time_limits_quantum_and_period() -> None:
    """A step acts exactly a dead time after its stamp; the velocity and acceleration never pass their
    limits; the report is a multiple of the quantum, new only every period; the fit's simulate gives the
    same motion, bit for bit."""
    base = DriveConfig(dead_time=0.02, natural_frequency=30.0, damping_ratio=0.6)
    y = response(base, 0.2)
    assert np.all(y[:69] == 0.0) and y[70] > 0.0  # stamped 0.05 s, acts at 0.07 s: moving at the step after
    f = step_figures(np.arange(y.size - 70) * 1e-3, y[70:], 0.0, 0.2)
    # the textbook's second order (integrated at 1 ms, semi-implicitly: a little more damped)
    assert f.overshoot_pct == pytest.approx(100 * math.exp(-0.6 * math.pi / math.sqrt(1 - 0.36)), abs=0.5)
    lim = base.model_copy(update={"max_velocity": 1.5, "max_acceleration": 20.0})
    y = response(lim, 1.0)
    v, a = np.diff(y) / 1e-3, np.diff(y, 2) / 1e-6
    assert 1.49 < v.max() <= 1.5 + 1e-9 and a.max() <= 20.0 + 1e-6
    enc = lim.model_copy(update={"resolution": 0.001, "period": 0.004})
    y = response(enc, 1.0)
    assert np.allclose(y / 0.001, np.round(y / 0.001), atol=1e-9)
    changes = np.nonzero(np.diff(y))[0] + 2  # step index (1 ms) at which a new report shows
    assert np.all(changes % 4 == 0)
    assert np.array_equal(simulate(lim, [0.05], [1.0], [0.0], np.concatenate([[0.0], TIMES]), 0.0)[1:],
                          response(lim, 1.0))


def test_the_world_steps_a_simulated_drive_in_lockstep(scenario: Any) -> None:
    """joints.joint_1.drive: physics moves joint_1 as the model does from the commands' stamps (MuJoCo's
    motor applies nothing to it), the other joints as ever; a drive on a joint served by hardware, or
    on an effort joint, is refused in one line."""
    drive = {"dead_time": 0.01, "natural_frequency": 25.0, "damping_ratio": 0.7, "max_velocity": 2.0,
             "max_acceleration": 30.0, "resolution": 0.0005, "period": 0.002}
    sc = scenario("arm", {"joints.joint_1": {"interface": "position", "drive": drive}})
    w = World(sc)
    ref = DriveModel(DriveConfig(**drive), 0.0)
    seen, want = [], []
    for k in range(600):
        if k == 100:  # the controller's step at t = 0.1 s: 0.5 rad, stamped with that step
            cmd = msgs.JointState(header=msgs.header(100_000_000), name=["joint_1"], position=[0.5], velocity=[0.0])
            w.command(cmd)
            ref.command(100_000_000 * 1e-9, 0.5, 0.0)
        w.step()
        ref.advance(w.time_ns * 1e-9)
        seen.append(w.positions()[0])
        want.append(ref.out_p)
    assert seen == want and 0.49 < seen[-1] < 0.51 and w.data.actuator_force[0] == 0.0
    for bad, why in (({"interface": "position", "server": "motor-model", "drive": drive}, "server is 'motor-model'"),
                     ({"interface": "effort", "drive": drive}, "not effort")):
        with pytest.raises(ConfigError, match=f"joints.joint_1.drive: .*{why}"):
            scenario("arm", {"joints.joint_1": bad})


def emulated_record(params: dict[str, float], dead_time: float, cpr: int, span: float = 5.0,
                    setpoints: bool = False) -> JointRecord:
    """What the project's drive emulator's own motor model (bridges/drive_emulator.py) does with steps and a
    chirp, reported every 2 ms with its encoder's counts and a little jitter of the reports' times. With
    ``setpoints``, each command reaches the bus 1 to 4 ms after its stamp, and one at the large step is held
    up 40 ms (a busy machine), as the bridge says in hw/<server>/setpoints; without, the commands reach it
    at their stamps."""
    cfg = DriveEmulatorConfig(dead_time=dead_time, encoder_cpr=cpr, **params)
    motor = EmulatedMotor(cfg, 0.0)
    motor.t = 0.0
    rng = np.random.default_rng(1)
    levels = [(0.3, 0.05), (0.65, -0.05), (1.0, 0.3), (1.5, -0.3), (2.1, 1.4), (3.1, 0.0)]
    cmd_t = np.arange(0.0, span, 0.004)
    cmd_p, cmd_v = np.zeros_like(cmd_t), np.zeros_like(cmd_t)
    for t0, lv in levels:
        cmd_p[cmd_t >= t0] = lv
    ch = cmd_t >= 3.8  # a chirp with its velocity as feed-forward
    s = cmd_t[ch] - 3.8
    ph = 2 * math.pi * (0.5 * s + 1.5 * s * s / 1.2)
    cmd_p[ch] = 0.05 * np.sin(ph)
    cmd_v[ch] = 0.05 * np.cos(ph) * 2 * math.pi * (0.5 + 3.0 * s / 1.2)
    way = rng.uniform(0.001, 0.004, cmd_t.size) if setpoints else np.zeros(cmd_t.size)
    if setpoints:
        way[np.searchsorted(cmd_t, 2.1)] = 0.040
    sent = np.maximum.accumulate(cmd_t + way)  # the bus passes them on in order
    inp = (0.0, 0.0, 0.0)
    k, hw = 0, []
    for te in np.arange(0.002, span, 0.002):
        while k < cmd_t.size and sent[k] <= te:
            inp = motor.advance(float(sent[k]), True, "position", inp)
            motor.take((float(cmd_p[k]), float(cmd_v[k]), 0.0), float(sent[k]))
            k += 1
        inp = motor.advance(float(te), True, "position", inp)
        hw.append((te + rng.uniform(0.0, 3e-4), motor.encoder(), motor.v))
    h = np.array(hw)
    sp = (sent, cmd_p, cmd_v) if setpoints else (np.zeros(0),) * 3
    return JointRecord("joint_1", "position", "bridge-can", cmd_t, cmd_p, cmd_v, h[:, 0], h[:, 1], h[:, 2],
                       h[:, 0], h[:, 1], h[:, 2], *sp)


def test_the_fit_finds_what_the_emulator_was_given() -> None:
    """Dead time, ω_n, ζ, both limits and the encoder's quantum of the emulator's own motor model (which
    integrates on its own, at 0.5 ms), from steps and a chirp: each within a few % (the dead time within
    1 ms), with uncertainties and residuals said, though the commands reached the drive late by 1 to 4 ms
    and once by 40 ms: the drive's own dead time is told from the way to it (its median is the twin's);
    fitted again without the acceleration limit it is clearly worse. A record that never reaches a
    limit does not fit it."""
    given = {"natural_frequency": 30.0, "damping_ratio": 0.6, "max_velocity": 2.5, "max_acceleration": 25.0}
    rec = emulated_record(given, dead_time=0.008, cpr=8192, setpoints=True)
    t0 = time.monotonic()
    f = fit_record(rec)
    took = time.monotonic() - t0
    d = f.drive
    assert d.order == 2 and all(f.reached.values()), f.as_json()
    assert f.own_dead_time == pytest.approx(0.008, abs=1e-3) and f.way is not None
    assert f.way[0] == pytest.approx(0.0025, abs=3e-4) and 0.0035 < f.way[1] < 0.0045
    assert d.dead_time == pytest.approx(f.own_dead_time + f.way[0], abs=1e-12)
    for k, v in given.items():
        assert getattr(d, k) == pytest.approx(v, rel=0.05), (k, f.as_json())
    assert d.resolution == pytest.approx(2 * math.pi / 8192, rel=1e-6) and d.period == pytest.approx(0.002, rel=0.01)
    assert all(0 < f.sigma[k] < 0.05 * getattr(d, k) for k in f.fitted_names() if k != "dead_time"), f.sigma
    assert f.rms < 2e-3 and f.n > 1000 and took < 30.0
    worse = fit_record(rec, limits=("max_velocity",))
    assert not worse.reached["max_acceleration"] and worse.rms > 3 * f.rms
    slow = emulated_record({**given, "max_velocity": 50.0, "max_acceleration": 5e3}, dead_time=0.004, cpr=0, span=2.5)
    g = fit_record(slow)
    assert not any(g.reached[k] for k in LIMITS) and g.drive.resolution == 0.0
    assert math.isinf(g.drive.max_velocity) and g.seen["velocity"] < 50.0


def test_a_velocity_drive_is_fitted_on_its_speed() -> None:
    """A wheel's traction drive (velocity control: the emulator's first-order loop of bandwidth 2ζω_n, an
    acceleration limit) stepped in speed both ways: order 1, its time constant and limit found."""
    cfg = DriveEmulatorConfig(natural_frequency=25.0, damping_ratio=0.8, max_acceleration=40.0, dead_time=0.005)
    motor = EmulatedMotor(cfg, 0.0)
    motor.t = 0.0
    cmd_t = np.arange(0.0, 3.0, 0.01)
    cmd_v = np.select([cmd_t < 0.2, cmd_t < 0.8, cmd_t < 1.4, cmd_t < 2.2], [0.0, 0.5, -2.5, 5.0], 0.0)
    inp, k, hw = (0.0, 0.0, 0.0), 0, []
    for te in np.arange(0.002, 3.0, 0.002):
        while k < cmd_t.size and cmd_t[k] <= te:
            inp = motor.advance(float(cmd_t[k]), True, "velocity", inp)
            motor.take((0.0, float(cmd_v[k]), 0.0), float(cmd_t[k]))
            k += 1
        inp = motor.advance(float(te), True, "velocity", inp)
        hw.append((te, motor.encoder(), motor.v))
    h, z = np.array(hw), np.zeros(0)
    rec = JointRecord("fl_traction", "velocity", "bridge-can", cmd_t, np.full(cmd_t.size, np.nan), cmd_v,
                      h[:, 0], h[:, 1], h[:, 2], h[:, 0], h[:, 1], h[:, 2], z, z, z)
    f = fit_record(rec)
    assert f.drive.order == 1 and f.reached == {"max_velocity": False, "max_acceleration": True}, f.as_json()
    assert f.drive.time_constant == pytest.approx(1 / (2 * 0.8 * 25.0), rel=0.05)
    assert f.drive.max_acceleration == pytest.approx(40.0, rel=0.05)
    assert f.drive.dead_time == pytest.approx(0.005, abs=2e-3) and f.rms < 0.05


def test_the_encoder_quantum_is_read_from_the_reports() -> None:
    q = 2 * math.pi / 4096
    counts = np.random.default_rng(0).integers(-3000, 3000, 500)
    # float32 turns on the wire: each count comes back a few 1e-8 rad off
    values = (counts * q / (2 * math.pi)).astype(np.float32).astype(float) * 2 * math.pi
    assert encoder_quantum(values) == pytest.approx(q, rel=1e-5)
    assert encoder_quantum(np.random.default_rng(1).uniform(-1, 1, 500)) == 0.0


def test_the_sim_clock_follows_the_promptest_command() -> None:
    """Sim time on the wall clock: the offset of the least delayed stamped sample of the last second."""
    c = SimClock(window=1.0)
    assert c.sim_ns(5.0) == 0
    for w, delay in ((10.0, 0.003), (10.1, 0.0005), (10.2, 0.01)):
        c.saw(round((w - 10.0 - delay) * 1e9), w)  # sim = wall − 10 s, each sample late by `delay`
    assert c.sim_ns(10.3) == pytest.approx(0.2995e9, abs=1e3)
    c.saw(round((11.5 - 10.002 - 0.001) * 1e9), 11.5)  # physics 2 ms behind now: the old maximum has aged out
    assert c.sim_ns(11.5) == pytest.approx(1.497e9, abs=1e3)


def test_the_twin_file_extends_the_scenario_without_hardware(tmp_path: Path) -> None:
    """The twin extends the scenario (path relative to the file), runs in lockstep without the drive
    emulator or any external server, and its joint is physics' with the fitted drive."""
    full = load_scenario(EMULATED, {"bridge-can.bus.port": 40000, "controller.rate_hz": 500})
    drive = DriveConfig(dead_time=0.012, natural_frequency=31.0, damping_ratio=0.62, max_velocity=2.49,
                        max_acceleration=float("inf"), resolution=7.67e-4, period=0.002)
    names = ["dead_time", "natural_frequency", "damping_ratio", "max_velocity"]
    f = Fit("joint_1", "position", drive, dict.fromkeys(names, 0.01), 1e-3, 5e-3, 0.4, 1000,
            {"velocity": 2.5, "acceleration": 20.0}, {"max_velocity": True, "max_acceleration": False})
    path = tmp_path / "twins" / "twin.yaml"
    data = twin_data(full, [f], [EMULATED], path, {"bridge-can.bus.port": 40000, "controller.rate_hz": 500})
    write_twin(path, data, [f], str(EMULATED))
    raw = yaml.safe_load(path.read_text())
    assert (path.parent / raw["extends"]).resolve() == EMULATED.resolve()
    assert "bridge-can" not in raw and "drive-emulator" not in raw and raw["controller"]["rate_hz"] == 500
    twin = load_scenario(path)
    assert not twin.external_servers() and twin.clock.mode == "lockstep" and "drive-emulator" not in twin.services
    j = twin.joint("joint_1")
    assert j.server == "sim" and j.interface == "position" and j.drive is not None
    assert j.drive.max_velocity == 2.49 and math.isinf(j.drive.max_acceleration) and j.drive.period == 0.002
    assert "# The twin of" in path.read_text() and "dead_time" in path.read_text().splitlines()[3]


def test_a_fit_from_a_starved_run_says_so() -> None:
    """The way from the controller's step to the drive varied (a busy machine): the fit's summary and its
    JSON say so in a warning; a steady way says nothing."""
    from hilsim.tools.tuning.identify import fit_summary

    drive = DriveConfig(dead_time=0.012, natural_frequency=31.0, damping_ratio=0.62, max_velocity=2.49,
                        max_acceleration=float("inf"), resolution=7.67e-4, period=0.002)
    names = ["dead_time", "natural_frequency", "damping_ratio", "max_velocity"]

    def fit(way: tuple[float, float]) -> Fit:
        return Fit("joint_1", "position", drive, dict.fromkeys(names, 0.01), 1e-3, 5e-3, 0.4, 1000,
                   {"velocity": 2.5, "acceleration": 20.0}, {"max_velocity": True, "max_acceleration": False},
                   own_dead_time=0.010, way=way)

    steady, starved = fit((0.0008, 0.0021)), fit((0.0009, 0.0310))
    assert steady.starved() is None and "warning" not in fit_summary(steady)
    assert steady.as_json()["warning"] is None
    said = fit_summary(starved).splitlines()[-1]
    assert said == ("  warning: the way to the drive varied: median 0.9 ms, 95 % within 31 ms (a busy machine?); "
                    "the twin's dead time takes the median: identified on a quiet machine, it fits closer"), said
    assert starved.as_json()["warning"] == said.removeprefix("  warning: ")
