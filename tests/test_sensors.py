"""Emulated sensors (hilsim.sim.sensing) and the sensor service against a test router."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from util import wait_until

from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError, SensorConfig
from hilsim.core.keys import Keys
from hilsim.services.sensors import SensorService
from hilsim.sim import sensing

DT_NS = 1_000_000
NAMES = [f"joint_{i}" for i in range(1, 7)]


def make(name: str = "enc", seed: int = 0, **fields: Any) -> sensing.Sensor:
    return sensing.make_sensor(name, SensorConfig(**fields), seed=seed, dt_ns=DT_NS)


def truth_js(k: int, pos: list[float] | None = None) -> msgs.JointState:
    p = pos if pos is not None else [0.1 * i + 0.0001234 * k for i in range(6)]
    return msgs.JointState(
        header=msgs.header(k * DT_NS), name=NAMES, position=p, velocity=[0.5] * 6, effort=[1.0, 2, 3, 4, 5, 6]
    )


def truth_imu(k: int) -> msgs.Imu:
    return msgs.Imu(
        header=msgs.header(k * DT_NS, "tool"),
        orientation=msgs.Quaternion(x=0.0, y=0.0, z=0.6, w=0.8),
        angular_velocity=msgs.Vector3(x=0.1, y=0.2, z=0.3),
        linear_acceleration=msgs.Vector3(x=0.0, y=0.0, z=9.81),
    )


# ---------------------------------------------------------------- sensor classes
def test_encoder_quantises_positions_and_passes_names_and_effort() -> None:
    enc = make(type="encoder", rate_hz=1000, resolution=0.001)
    out = enc.sample(truth_js(3, [0.0, 0.0104, -0.0106, 1.23456, 0.0, 0.0]), 3 * DT_NS)
    assert out.name == NAMES and out.effort == [1.0, 2, 3, 4, 5, 6]
    assert out.position == pytest.approx([0.0, 0.010, -0.011, 1.235, 0.0, 0.0])
    assert msgs.ns_of(out.header.stamp) == 3 * DT_NS
    assert out.velocity == [0.5] * 6  # no velocity noise configured: truth velocity


def test_encoder_noise_statistics() -> None:
    enc = make(type="encoder", rate_hz=1000, noise_std=0.01, velocity_noise_std=0.1)
    pos = np.array([enc.sample(truth_js(k, [1.0] * 6), k * DT_NS).position for k in range(2000)])
    vel = np.array([enc.sample(truth_js(k), k * DT_NS).velocity for k in range(2000)])
    err = pos - 1.0
    assert abs(err.mean()) < 0.001 and err.std() == pytest.approx(0.01, rel=0.05)
    assert (vel - 0.5).std() == pytest.approx(0.1, rel=0.05)
    # Noise is independent across joints.
    assert abs(np.corrcoef(err[:, 0], err[:, 1])[0, 1]) < 0.1


def test_imu_bias_noise_and_covariance() -> None:
    imu = make(
        "imu", type="imu", rate_hz=1000, accel_noise_std=0.05, gyro_noise_std=0.01,
        accel_bias=[0.1, -0.2, 0.3], gyro_bias=[0.01, 0.0, -0.01],
    )  # fmt: skip
    outs = [imu.sample(truth_imu(k), k * DT_NS) for k in range(3000)]
    acc = np.array([[o.linear_acceleration.x, o.linear_acceleration.y, o.linear_acceleration.z] for o in outs])
    gyr = np.array([[o.angular_velocity.x, o.angular_velocity.y, o.angular_velocity.z] for o in outs])
    assert acc.mean(axis=0) == pytest.approx([0.1, -0.2, 9.81 + 0.3], abs=0.005)
    assert gyr.mean(axis=0) == pytest.approx([0.11, 0.2, 0.29], abs=0.001)
    assert acc.std(axis=0) == pytest.approx([0.05] * 3, rel=0.07)
    assert gyr.std(axis=0) == pytest.approx([0.01] * 3, rel=0.07)
    o = outs[0]
    assert (o.orientation.z, o.orientation.w) == (0.6, 0.8) and o.header.frame_id == "tool"
    assert o.linear_acceleration_covariance[0] == pytest.approx(0.05**2)
    assert o.angular_velocity_covariance[8] == pytest.approx(0.01**2)
    assert o.angular_velocity_covariance[1] == 0.0


def test_same_seed_same_outputs_other_seed_or_name_differs() -> None:
    def run(seed: int, name: str = "enc") -> list[list[float]]:
        enc = make(name, seed=seed, type="encoder", rate_hz=1000, noise_std=0.001)
        return [enc.sample(truth_js(k), k * DT_NS).position for k in range(50)]

    assert run(7) == run(7)
    assert run(7) != run(8)
    assert run(7) != run(7, "other")


def test_decimation_by_rate() -> None:
    imu = make("imu", type="imu", rate_hz=200)
    assert imu.decimation == 5
    due = [k for k in range(20) if imu.sample(truth_imu(k), k * DT_NS) is not None]
    assert due == [0, 5, 10, 15]
    off = make("imu", type="imu", rate_hz=200, enabled=False)
    assert off.sample(truth_imu(0), 0) is None


def test_unknown_sensor_type_lists_available() -> None:
    with pytest.raises(
        ConfigError, match=r"sensors.lidar.type: unknown sensor type 'lidar2d'; available: encoder, imu"
    ):
        make("lidar", type="lidar2d")
    with pytest.raises(sensing.UnknownSensorType):
        sensing.sensor_class("nope")


@pytest.mark.parametrize(
    ("fields", "where"),
    [
        ({"type": "encoder", "resolution": -1.0}, "sensors.enc.resolution: Input should be greater than or equal to 0"),
        ({"type": "encoder", "resolutoin": 0.1}, "sensors.enc.resolutoin: Extra inputs are not permitted"),
        ({"type": "encoder", "noise_std": "loud"}, "sensors.enc.noise_std: Input should be a valid number"),
        ({"type": "imu", "accel_bias": [0.1, 0.2]}, "sensors.enc.accel_bias"),
        ({"type": "imu", "gyro_noise_std": float("nan")}, "sensors.enc.gyro_noise_std"),
        ({"type": "imu", "rate_hz": 300}, "sensors.enc.rate_hz: 300 Hz must divide the physics rate"),
    ],
)
def test_bad_parameters_give_one_line_errors(fields: dict[str, Any], where: str) -> None:
    with pytest.raises(ConfigError) as e:
        make(**fields)
    assert where in str(e.value) and "\n" not in str(e.value)


def test_service_config_errors(scenario: Callable[..., Any]) -> None:
    with pytest.raises(ConfigError, match=r"sensors.encoders.rate_hz: 500 Hz must equal controller.rate_hz"):
        SensorService(scenario(overrides={"sensors.encoders.rate_hz": 500}))
    with pytest.raises(ConfigError, match=r"sensors.imu.type: unknown sensor type"):
        SensorService(scenario(overrides={"sensors.imu.type": "imu9"}))
    # Without a controller the encoder rate is free.
    SensorService(scenario(overrides={"sensors.encoders.rate_hz": 500, "services": ["physics", "sensors"]}))


# ---------------------------------------------------------------- the service over Zenoh
class Inbox:
    """Collects decoded messages from keys, by key."""

    def __init__(self, session: Any, keys: dict[str, type]) -> None:
        self.items: dict[str, list[Any]] = {k: [] for k in keys}
        self.cv = threading.Condition()
        self.subs = [session.declare_subscriber(k, self._cb(k, cls)) for k, cls in keys.items()]

    def _cb(self, key: str, cls: type) -> Callable[[Any], None]:
        def cb(sample: Any) -> None:
            with self.cv:
                self.items[key].append(msgs.decode(cls, sample.payload.to_bytes()))
                self.cv.notify_all()

        return cb

    def wait(self, key: str, n: int, timeout: float = 5.0) -> list[Any]:
        with self.cv:
            self.cv.wait_for(lambda: len(self.items[key]) >= n, timeout)
            return list(self.items[key])

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def test_service_publishes_due_outputs_and_acks(
    scenario: Callable[..., Any], session: Any, run_service: Callable[[Any], Any]
) -> None:
    # without a controller in the scenario, the sensors acknowledge every step themselves
    sc = scenario(overrides={"services": ["physics", "sensors", "logger"]})
    keys = Keys.of(sc)
    inbox = Inbox(
        session,
        {keys.topic("joint_states"): msgs.JointState, keys.topic("imu"): msgs.Imu, keys.sync("sensors"): msgs.Clock},
    )
    pub_js = transport.publisher(session, keys.truth("joint_states"))
    pub_imu = transport.publisher(session, keys.truth("imu"))
    try:
        with run_service(SensorService(sc)) as svc:
            assert svc.lockstep
            assert svc.state == "running"
            assert wait_until(lambda: pub_js.matching_status.matching and pub_imu.matching_status.matching)
            for k in range(10):
                pub_imu.put(msgs.encode(truth_imu(k)))
                pub_js.put(msgs.encode(truth_js(k)))
                # lockstep: wait for the ack before the next step, as physics does
                acks = inbox.wait(keys.sync("sensors"), k + 1)
                assert msgs.ns_of(acks[-1].clock) == k * DT_NS
            js = inbox.wait(keys.topic("joint_states"), 10)
            imu = inbox.wait(keys.topic("imu"), 2)
            assert [msgs.ns_of(m.header.stamp) for m in js] == [k * DT_NS for k in range(10)]
            assert [msgs.ns_of(m.header.stamp) for m in imu] == [0, 5 * DT_NS]  # 200 Hz
            assert js[3].position == pytest.approx(truth_js(3).position, abs=2e-4)

            # Malformed truth is rejected and counted; the service keeps working.
            pub_js.put(b"\x00\x01garbage")
            pub_js.put(msgs.encode(truth_js(10))[:-7])
            bad = truth_js(10)
            bad.position[2] = float("nan")
            pub_js.put(msgs.encode(bad))
            short = truth_js(10)
            short.position = short.position[:5]
            pub_js.put(msgs.encode(short))
            renamed = truth_js(10)
            renamed.name = [*NAMES[:5], "extra"]
            pub_js.put(msgs.encode(renamed))
            key = keys.truth("joint_states")
            assert wait_until(lambda: svc.rejected[key] == 5), dict(svc.rejected)
            pub_js.put(msgs.encode(truth_js(11)))
            assert msgs.ns_of(inbox.wait(keys.topic("joint_states"), 11)[-1].header.stamp) == 11 * DT_NS
            health = {kv.key: kv.value for kv in svc.health().status[0].values}
            assert health["rejected"] == "5" and health["state"] == "running"
    finally:
        pub_js.undeclare()
        pub_imu.undeclare()
        inbox.close()


def test_service_is_deterministic(scenario: Callable[..., Any]) -> None:
    # Two service instances, same scenario, same truth: identical outputs (noise included).
    def outputs() -> list[Any]:
        svc = SensorService(scenario())
        res = []
        for k in range(20):
            for s in svc.sensors:
                truth = truth_imu(k) if s.truth_topic == "imu" else truth_js(k)
                res.append(s.sample(truth, k * DT_NS))
        return [msgs.encode(m) for m in res if m is not None]

    a, b = outputs(), outputs()
    assert a == b and len(a) == 20 + 4
