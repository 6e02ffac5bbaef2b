"""Emulated sensors: one base class, one small subclass per sensor kind, picked by name.

A scenario's ``sensors:`` section maps a sensor *name* to its ``type`` (a key of
:mod:`hilsim.core.registry`, kind ``sensors``), ``rate_hz``, ``enabled`` and the parameters of that type::

    encoders: {type: encoder, rate_hz: 1000, resolution: 0.0001, noise_std: 0.00002}

The base :class:`Sensor` does what every sensor shares: parameter validation (one-line
errors naming ``sensors.<name>.<field>``), the rate as a decimation of the physics step,
and a noise generator seeded from the scenario seed and the sensor name (stable across runs
and independent of the other sensors). A subclass declares which truth topic it reads, which
topic it writes, its parameters (a pydantic model) and :meth:`Sensor.measure`. A new kind is
a subclass listed in the registry's built-in table, or offered by another package through the
``hilsim.sensors`` entry-point group; nothing else changes.
"""

from __future__ import annotations

import zlib
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilsim.core import msgs
from hilsim.core.config import ConfigError, SensorConfig


class UnknownSensorType(ConfigError):
    """A sensor ``type`` that is not registered."""


class SensorParams(BaseModel):
    """Parameters of a sensor kind; subclasses add fields. NaN/inf and unknown fields are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def sensor_class(type_name: str) -> type[Sensor]:
    from hilsim.core import registry

    try:
        cls = registry.load("sensors", type_name)
    except registry.UnknownName as e:
        raise UnknownSensorType(str(e).replace("unknown sensor", "unknown sensor type")) from None
    if not (isinstance(cls, type) and issubclass(cls, Sensor)):
        raise UnknownSensorType(f"sensor type {type_name!r} is {cls!r}, not a hilsim.sim.sensing.Sensor subclass")
    if not cls.type_name:
        cls.type_name = type_name
    return cls


def make_sensor(name: str, cfg: SensorConfig, *, seed: int, dt_ns: int, where: str = "",
                scenario: Any = None) -> Sensor:
    """Build the sensor ``name`` of a scenario; raises :class:`ConfigError` (one line) on bad config.
    With ``scenario``, the sensor is also bound to it (:meth:`Sensor.bind`)."""
    try:
        cls = sensor_class(cfg.type)
    except UnknownSensorType as e:
        raise UnknownSensorType(f"{where}sensors.{name}.type: {e}") from None
    s = cls(name, cfg, seed=seed, dt_ns=dt_ns, where=where)
    if scenario is not None:
        s.bind(scenario, where)
    return s


class Sensor:
    """Base of every emulated sensor."""

    type_name: ClassVar[str] = ""
    truth_topic: ClassVar[str]  # read: <prefix>/<robot>/truth/<truth_topic>
    output_topic: ClassVar[str]  # written: <prefix>/<robot>/<output_topic>
    truth_type: ClassVar[type]
    Params: ClassVar[type[SensorParams]] = SensorParams

    def __init__(self, name: str, cfg: SensorConfig, *, seed: int, dt_ns: int, where: str = "") -> None:
        self.name = name
        self.enabled = cfg.enabled
        self.rate_hz = cfg.rate_hz
        self.dt_ns = dt_ns
        # The sensor samples every `decimation`-th physics step; anything else would need
        # interpolation of truth that nobody asked for.
        steps = 1e9 / (cfg.rate_hz * dt_ns)
        if round(steps) < 1 or abs(steps - round(steps)) > 1e-6:
            raise ConfigError(
                f"{where}sensors.{name}.rate_hz: {cfg.rate_hz:g} Hz must divide the physics rate ({1e9 / dt_ns:g} Hz)"
            )
        self.decimation = round(steps)
        try:
            self.p = self.Params.model_validate(cfg.model_extra or {})
        except ValidationError as e:
            err = e.errors()[0]
            field = ".".join(str(x) for x in err["loc"]) or "(parameters)"
            got = err.get("input")
            shown = f" (got {got!r})" if err["type"] != "missing" and not isinstance(got, dict) else ""
            raise ConfigError(f"{where}sensors.{name}.{field}: {err['msg']}{shown}") from None
        # Seeded per sensor: adding or removing one sensor leaves the noise of the others unchanged.
        self.rng = np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(name.encode())])
        self.published = 0

    def bind(self, scenario: Any, where: str = "") -> None:
        """Take what the sensor needs from the scenario beyond its own parameters (e.g. the world
        model a laser casts its rays in, the frame a GPS antenna sits at); called once by the
        sensor service after construction. Raise :class:`ConfigError` (one line) if it is unusable."""

    def due(self, stamp_ns: int) -> bool:
        """Whether the sensor samples the truth of the physics step stamped ``stamp_ns``."""
        k = (stamp_ns + self.dt_ns // 2) // self.dt_ns
        return k % self.decimation == 0

    def sample(self, truth: Any, stamp_ns: int) -> Any | None:
        """The output message for this truth, or None if disabled or not due."""
        if not self.enabled or not self.due(stamp_ns):
            return None
        out = self.measure(truth, stamp_ns)
        self.published += 1
        return out

    def measure(self, truth: Any, stamp_ns: int) -> Any:
        """The measurement of ``truth`` (called only when due); stamp the output ``stamp_ns``."""
        raise NotImplementedError


# ---------------------------------------------------------------- joint encoders
class EncoderParams(SensorParams):
    resolution: float = Field(0.0, ge=0, description="quantum of the position [rad per count]; 0 = exact")
    noise_std: float = Field(0.0, ge=0, description="Gaussian position noise before quantisation [rad]")
    velocity_noise_std: float = Field(0.0, ge=0, description="Gaussian velocity noise [rad/s]")
    velocity_resolution: float = Field(0.0, ge=0, description="quantum of the velocity [rad/s]; 0 = exact")


class Encoder(Sensor):
    """Joint encoders: ``joint_states`` from ``truth/joint_states``.

    Position: truth + Gaussian noise (``noise_std``), then rounded to a multiple of ``resolution``
    (the noise stands for jitter at the code edges, so it goes in before quantisation).
    Velocity: the truth velocity with its own optional noise and quantum, as a drive that
    estimates velocity internally reports it (a plain finite difference of 1e-4 rad counts at
    1 kHz would be quantised to 0.1 rad/s, useless for damping). Effort is passed through.
    Names and order are those of the truth message.
    """

    type_name = "encoder"
    truth_topic = "joint_states"
    output_topic = "joint_states"
    truth_type = msgs.JointState
    Params = EncoderParams
    p: EncoderParams

    @staticmethod
    def _quantise(x: list[float], noise: np.ndarray | None, q: float) -> list[float]:
        """``x`` plus ``noise``, rounded to a multiple of ``q`` (0: not rounded). np.rint is what np.round
        does at 0 decimals (half to even), without its Python wrapper: this runs every step."""
        if noise is None and q <= 0.0:
            return list(x)
        a = np.asarray(x, float)
        if noise is not None:
            a = a + noise
        if q > 0.0:
            a = np.rint(a / q) * q
        return a.tolist()

    def measure(self, truth: msgs.JointState, stamp_ns: int) -> msgs.JointState:
        p = self.p
        pos, vel = truth.position, truth.velocity
        n_pos = self.rng.normal(0.0, p.noise_std, len(pos)) if p.noise_std > 0.0 else None
        n_vel = self.rng.normal(0.0, p.velocity_noise_std, len(vel)) if p.velocity_noise_std > 0.0 and vel else None
        return msgs.JointState(
            header=msgs.header(stamp_ns, truth.header.frame_id),
            name=list(truth.name),
            position=self._quantise(pos, n_pos, p.resolution),
            velocity=self._quantise(vel, n_vel, p.velocity_resolution),
            effort=list(truth.effort),
        )


# ---------------------------------------------------------------- IMU
Vec3 = tuple[float, float, float]


class ImuParams(SensorParams):
    accel_noise_std: float = Field(0.0, ge=0, description="[m/s^2]")
    gyro_noise_std: float = Field(0.0, ge=0, description="[rad/s]")
    accel_bias: Vec3 = (0.0, 0.0, 0.0)
    gyro_bias: Vec3 = (0.0, 0.0, 0.0)


class ImuSensor(Sensor):
    """IMU: ``imu`` from ``truth/imu``. Accelerometer and gyro get a constant bias and white
    Gaussian noise; orientation (and its covariance) is passed through; the covariances of the
    rates are diagonal with the noise variances."""

    type_name = "imu"
    truth_topic = "imu"
    output_topic = "imu"
    truth_type = msgs.Imu
    Params = ImuParams
    p: ImuParams

    def __init__(self, name: str, cfg: SensorConfig, *, seed: int, dt_ns: int, where: str = "") -> None:
        super().__init__(name, cfg, seed=seed, dt_ns=dt_ns, where=where)
        a, g = self.p.accel_noise_std**2, self.p.gyro_noise_std**2
        self._accel_cov = [a, 0.0, 0.0, 0.0, a, 0.0, 0.0, 0.0, a]
        self._gyro_cov = [g, 0.0, 0.0, 0.0, g, 0.0, 0.0, 0.0, g]

    def _vec(self, v: msgs.Vector3, bias: Vec3, std: float) -> msgs.Vector3:
        n = self.rng.normal(0.0, std, 3) if std > 0.0 else (0.0, 0.0, 0.0)
        return msgs.Vector3(x=v.x + bias[0] + n[0], y=v.y + bias[1] + n[1], z=v.z + bias[2] + n[2])

    def measure(self, truth: msgs.Imu, stamp_ns: int) -> msgs.Imu:
        p = self.p
        # Draw order fixed (accel, then gyro) so the sequence is reproducible.
        acc = self._vec(truth.linear_acceleration, p.accel_bias, p.accel_noise_std)
        gyr = self._vec(truth.angular_velocity, p.gyro_bias, p.gyro_noise_std)
        return msgs.Imu(
            header=msgs.header(stamp_ns, truth.header.frame_id),
            orientation=truth.orientation,
            orientation_covariance=list(truth.orientation_covariance),
            angular_velocity=gyr,
            angular_velocity_covariance=list(self._gyro_cov),
            linear_acceleration=acc,
            linear_acceleration_covariance=list(self._accel_cov),
        )
