"""Four-wheel-steer kinematics against wheel angles and speeds computed by hand, per mode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilsim.sim import steering

# the rover's wheels (models/rover/generate.py): steering axes at x ±0.35, y ±0.40; radius 0.15
G = steering.Geometry(((0.35, 0.4), (0.35, -0.4), (-0.35, 0.4), (-0.35, -0.4)), 0.15)
FL, FR, RL, RR = range(4)


def test_straight_and_backwards() -> None:
    a, w = steering.inverse(0.3, 0.0, 0.0, G)
    assert np.allclose(a, 0.0) and np.allclose(w, 2.0)  # 0.3 m/s / 0.15 m
    a, w = steering.inverse(-0.3, 0.0, 0.0, G)
    assert np.allclose(a, 0.0) and np.allclose(w, -2.0)  # reversed, not turned by pi
    assert steering.mode(0.3, 0.0, 0.0) == "crab"


def test_crab_every_wheel_parallel() -> None:
    a, w = steering.inverse(0.3, 0.3, 0.0, G)
    assert np.allclose(a, math.pi / 4) and np.allclose(w, math.sqrt(0.18) / 0.15)
    a, w = steering.inverse(0.0, 0.3, 0.0, G)  # straight sideways: at the limit
    assert np.allclose(np.abs(a), math.pi / 2) and np.allclose(np.abs(w), 2.0)
    assert steering.mode(0.0, 0.3, 0.0) == "crab"


def test_turn_in_place_wheels_tangent_and_reversed_within_limits() -> None:
    a, w = steering.inverse(0.0, 0.0, 1.0, G)
    d = math.atan2(0.35, 0.4)  # 0.71883: the wheel velocities (-0.4, 0.35), (0.4, 0.35), … turned into ±pi/2
    s = math.hypot(0.4, 0.35) / 0.15  # 3.5434 rad/s
    assert np.allclose(a, [-d, d, d, -d]), a
    assert np.allclose(w, [-s, s, -s, s]), w
    assert steering.mode(0.0, 0.0, 1.0) == "turn_in_place"


def test_ackermann_like_both_axles_opposite_phase() -> None:
    a, w = steering.inverse(0.5, 0.0, 0.5, G)  # R = 1 m to the left
    inner, outer = math.atan(0.35 / (1 - 0.4)), math.atan(0.35 / (1 + 0.4))  # classic Ackermann, 0.52838 / 0.24498
    assert np.allclose(a, [inner, outer, -inner, -outer]), a
    v_in, v_out = math.hypot(0.3, 0.175) / 0.15, math.hypot(0.7, 0.175) / 0.15  # 2.3154, 4.8103 rad/s
    assert np.allclose(w, [v_in, v_out, v_in, v_out]), w
    assert steering.mode(0.5, 0.0, 0.5) == "ackermann"


def test_wheel_reversed_instead_of_past_its_limit() -> None:
    ang, sp = steering.wheel_command(-1.0, 0.1, 0.0, G)
    assert ang == pytest.approx(math.atan2(-0.1, 1.0)) and sp == pytest.approx(-math.hypot(1.0, 0.1))
    assert G.lower <= ang <= G.upper


def test_nearest_equivalent_angle_and_standstill_keeps_angle() -> None:
    a, w = steering.inverse(0.0, 0.0, 0.0, G, current=[0.3, -0.2, 0.1, 1.0])
    assert np.allclose(a, [0.3, -0.2, 0.1, 1.0]) and np.allclose(w, 0.0)
    # sideways: +pi/2 forwards or -pi/2 backwards; a wheel already near -pi/2 stays there
    a, w = steering.inverse(0.0, 0.3, 0.0, G, current=[-1.4, 1.4, -1.4, 1.4])
    assert np.allclose(a, [-math.pi / 2, math.pi / 2] * 2) and np.allclose(w, [-2.0, 2.0] * 2)


def test_speed_limit_scales_every_wheel_alike() -> None:
    a, w = steering.inverse(0.5, 0.0, 0.5, G, max_wheel_speed=2.0)
    a0, w0 = steering.inverse(0.5, 0.0, 0.5, G)
    assert np.allclose(a, a0) and np.max(np.abs(w)) == pytest.approx(2.0) and np.allclose(w / w0, w[0] / w0[0])


@pytest.mark.parametrize("twist", [(0.3, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 0.7), (0.4, 0.0, -0.3),
                                   (-0.2, 0.1, 0.2)])
def test_wheel_odometry_inverts_the_kinematics(twist: tuple[float, float, float]) -> None:
    a, w = steering.inverse(*twist, G)
    assert np.allclose(steering.forward(a, w, G), twist, atol=1e-12)


def test_integrate_exact_on_arcs() -> None:
    assert steering.integrate((0, 0, 0), (1.0, 0.0, 0.0), 2.0) == pytest.approx((2.0, 0.0, 0.0))
    x, y, th = steering.integrate((0, 0, 0), (1.0, 0.0, 1.0), math.pi)  # half circle of radius 1 to the left
    assert (x, y) == pytest.approx((0.0, 2.0), abs=1e-12) and abs(abs(th) - math.pi) < 1e-12
    pose = (0.0, 0.0, 0.0)
    for _ in range(1000):  # many small steps = one big one
        pose = steering.integrate(pose, (0.5, 0.1, 0.3), 0.01)
    assert pose == pytest.approx(steering.integrate((0, 0, 0), (0.5, 0.1, 0.3), 10.0), abs=1e-9)


def test_traction_scale() -> None:
    assert steering.traction_scale(0.0) == 1.0 and steering.traction_scale(2.0) == 0.0
    assert steering.traction_scale(math.pi / 3) == pytest.approx(0.5)


def test_odometry_with_a_measured_yaw_rate() -> None:
    a, w = steering.inverse(0.4, 0.1, 0.5, G)
    assert np.allclose(steering.forward(a, w, G, yaw_rate=0.5), (0.4, 0.1, 0.5), atol=1e-12)
    # a gyro that disagrees with the wheels wins the rotation; the translation is still fitted
    vx, vy, wz = steering.forward(a, w, G, yaw_rate=0.0)
    assert wz == 0.0 and vx == pytest.approx(0.4) and vy == pytest.approx(0.1)
