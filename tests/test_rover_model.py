"""The rover model: the committed files are what generate.py derives; the worlds load with the rover
in them; and on the ground it drives straight, turns in place and climbs the outdoor slope
(MuJoCo alone, a plain per-wheel PID, the four-wheel-steer kinematics of hilsim.sim.steering)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from hilsim.sim import steering

MODELS = Path(__file__).resolve().parent.parent / "models"
ROVER = MODELS / "rover"


def _generator():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("rover_generate", ROVER / "generate.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = gen  # its dataclasses look their module up
    try:
        spec.loader.exec_module(gen)
    finally:
        del sys.modules[spec.name]
    return gen


def test_committed_model_matches_its_generator(tmp_path: Path) -> None:
    gen = _generator()
    gen.write_urdf(str(tmp_path / "rover.urdf"))
    gen.write_mjcf(str(tmp_path / "rover.xml"))
    for name in ("rover.urdf", "rover.xml"):
        assert (tmp_path / name).read_text() == (ROVER / name).read_text(), f"{name} was edited by hand"


def test_model_structure() -> None:
    m = mujoco.MjModel.from_xml_path(str(ROVER / "rover.xml"))
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE and m.body(m.jnt_bodyid[0]).name == "base_link"
    acts = [m.actuator(i).name for i in range(m.nu)]
    assert acts == [f"{w}_{k}" for w in ("fl", "fr", "rl", "rr") for k in ("steering", "traction")]
    for a in range(m.nu):  # actuators named like their joints
        assert m.joint(m.actuator_trnid[a, 0]).name == acts[a]
    for w in ("fl", "fr", "rl", "rr"):
        s, t = m.joint(f"{w}_steering"), m.joint(f"{w}_traction")
        assert s.limited[0] and np.allclose(s.range, [-math.pi / 2, math.pi / 2]) and not t.limited[0]
    for site in ("laser", "imu", "gps"):
        assert m.site(site).bodyid[0] == m.body("base_link").id
    assert 50 < sum(m.body_mass) < 60  # 54.8 kg, models/rover/README.md


def _drive(world: str, start: tuple[float, float, float], plan: list[tuple[tuple[float, float, float], float]]):
    m = mujoco.MjModel.from_xml_path(str(MODELS / "worlds" / world))
    d = mujoco.MjData(m)
    d.qpos[0:3] = start
    mujoco.mj_forward(m, d)
    j = [m.actuator_trnid[i, 0] for i in range(m.nu)]
    qa, da = [m.jnt_qposadr[k] for k in j], [m.jnt_dofadr[k] for k in j]
    g = steering.Geometry(((0.35, 0.4), (0.35, -0.4), (-0.35, 0.4), (-0.35, -0.4)), 0.15)
    integ = np.zeros(4)
    for twist, secs in plan:
        for k in range(round(secs / m.opt.timestep)):
            if k % 5 == 0:
                ang, spd = steering.inverse(*twist, g, [d.qpos[qa[2 * w]] for w in range(4)], 10.0)
                for w in range(4):
                    e = ang[w] - d.qpos[qa[2 * w]]
                    d.ctrl[2 * w] = 40 * e - 2 * d.qvel[da[2 * w]]
                    ev = spd[w] * steering.traction_scale(e) - d.qvel[da[2 * w + 1]]
                    integ[w] = np.clip(integ[w] + ev * 0.01, -2, 2)
                    d.ctrl[2 * w + 1] = 8 * ev + 10 * integ[w]
            mujoco.mj_step(m, d)
    q = d.qpos[3:7]
    yaw = math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
    return d.qpos[0:3].copy(), yaw


def test_drives_straight_and_turns_in_place_indoors() -> None:
    pos, yaw = _drive("indoor.xml", (0, 0, 0.255), [((0, 0, 0), 0.3), ((0.5, 0, 0), 2.0), ((0, 0, 0), 0.5)])
    assert pos[0] == pytest.approx(1.0, abs=0.05) and abs(pos[1]) < 0.01 and abs(yaw) < 0.01
    pos2, yaw2 = _drive("indoor.xml", (0, 0, 0.255), [((0, 0, 0.5), 3.5), ((0, 0, 0), 0.5)])
    assert np.hypot(*pos2[:2]) < 0.03, pos2  # in place: no sliding away
    assert yaw2 == pytest.approx(1.6, abs=0.2)


def test_climbs_the_outdoor_slope() -> None:
    pos, yaw = _drive("outdoor.xml", (6.0, -10.0, 0.26), [((0.5, 0, 0), 14.0)])
    assert pos[0] > 12.0 and pos[2] > 0.9, pos  # up the 10 degree slope, not sliding back
    assert abs(pos[1] + 10.0) < 0.1 and abs(yaw) < 0.05


def test_crabs_sideways_and_turns_ackermann_like() -> None:
    pos, yaw = _drive("indoor.xml", (0, 0, 0.255), [((0, 0.3, 0), 3.0), ((0, 0, 0), 0.5)])
    # 0.9 m less the quarter turn of the wheels at the start (while they turn they roll along x a little)
    assert pos[1] == pytest.approx(0.85, abs=0.06) and abs(pos[0]) < 0.1 and abs(yaw) < 0.03, (pos, yaw)
    # R = vx / wz = 1 m to the left for 2 s: about a quarter circle and a bit
    pos, yaw = _drive("outdoor.xml", (0, 0, 0.255), [((0.5, 0, 0.5), 2.0), ((0, 0, 0), 0.5)])
    assert yaw == pytest.approx(0.9, abs=0.15), yaw
    # on an arc about (0, 1) m; a little wider, as the wheels steer in during the first moments
    assert 0.95 <= math.hypot(pos[0], pos[1] - 1.0) <= 1.15 and pos[1] > 0.25, pos
