"""Sensor emulator service: turns physics ground truth into what real sensors would report.

Reads (``<prefix>/<robot>/…``):
  ``truth/joint_states`` (sensor_msgs/JointState), ``truth/imu`` (sensor_msgs/Imu), ``truth/odom``
  (nav_msgs/Odometry; laser and GPS of a mobile robot) — the truth topics of the configured
  sensors (:mod:`hilsim.sim.sensing`, :mod:`hilsim.sim.sensors_mobile`);
  ``hw/<server>/joint_states`` (sensor_msgs/JointState) — joints served by external servers.
Writes:
  ``joint_states`` (encoders), ``joint_states_throttle`` (the same messages of the planner's
  decision steps only, ``planner.rate_hz``; in scenarios with a planner), ``imu``, ``scan``
  (sensor_msgs/LaserScan), ``gps/fix`` (sensor_msgs/NavSatFix) — each stamped with the truth stamp, at the sensor's rate
  (the physics steps ``k`` with ``k % decimation == 0``). ``joint_states`` is *one* message with
  every joint: the simulated joints from the encoders, the external joints as their server last
  measured them (a real encoder needs no emulated noise), merged at each step;
  ``sync/sensors`` (lockstep, only in scenarios without a controller, whose command would
  otherwise be the proof): the acknowledgement of step ``t_k`` once ``truth/joint_states`` of
  ``t_k`` is handled (physics publishes ``truth/imu`` and ``truth/odom`` before it, so every truth
  of the step has been handled by then).

Noise comes from generators seeded by ``seed`` and the sensor name: the same scenario and the
same truth give the same outputs, bit for bit.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.keys import topic_name
from hilsim.core.service import Publisher, Service
from hilsim.sim.sensing import Sensor, make_sensor

# Physics publishes this truth last before the clock: handling it completes the step.
ACK_TRUTH = "joint_states"


class SensorService(Service):
    name = "sensors"
    stop_rank = 30

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        # with a controller, its command for step k proves the sensors handled step k
        return None if "controller" in sc.services else 1

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = f"{scenario.source}: " if scenario.source else ""
        self.sensors: list[Sensor] = [
            make_sensor(n, cfg, seed=scenario.seed, dt_ns=scenario.dt_ns, where=where, scenario=scenario)
            for n, cfg in scenario.sensors.items()
        ]
        outputs: dict[str, str] = {}
        for s in self.sensors:
            if not s.enabled:
                continue
            if s.output_topic in outputs:
                raise ConfigError(
                    f"{where}sensors.{s.name}: writes {s.output_topic} like sensors.{outputs[s.output_topic]}; "
                    "disable one of them"
                )
            outputs[s.output_topic] = s.name
            # The controller runs once per joint_states message, so the encoders set its rate.
            if s.output_topic == "joint_states" and "controller" in scenario.services:
                if abs(s.rate_hz - scenario.controller.rate_hz) > 1e-9:
                    raise ConfigError(
                        f"{where}sensors.{s.name}.rate_hz: {s.rate_hz:g} Hz must equal controller.rate_hz "
                        f"({scenario.controller.rate_hz:g} Hz): the controller runs on every joint_states message"
                    )
        self._by_truth: dict[str, list[tuple[Sensor, Publisher | None]]] = defaultdict(list)
        self._joint_names: list[str] | None = None
        # external joints: their latest measurement (position, velocity, effort), by name
        self._external = bool(scenario.external_servers())
        self._measured: dict[str, tuple[float, float, float]] = {}
        # the planner's ticks: joint_states of every planner_decimation-th step, on their own key
        self._throttle: Publisher | None = None

    def setup(self) -> None:
        topics = {s.truth_topic: s.truth_type for s in self.sensors}
        topics.setdefault(ACK_TRUTH, msgs.JointState)  # the ack needs it even without encoders
        for s in self.sensors:
            pub = self.publisher(self.keys.topic(s.output_topic)) if s.enabled else None
            self._by_truth[s.truth_topic].append((s, pub))
            if pub is not None and s.output_topic == "joint_states" and "planner" in self.sc.services:
                self._throttle = self.publisher(self.keys.topic("joint_states_throttle"))
        for topic, cls in topics.items():
            self.subscribe(self.keys.truth(topic), cls, self._make_handler(topic))
        if self._external:
            self.subscribe(self.keys.all_server_states, msgs.JointState, self._on_server_state)

    def _on_server_state(self, js: msgs.JointState, key: str) -> None:
        server = topic_name(key).split("/")[-2]  # …/hw/<server>/joint_states
        if any(self.sc.joint(n).server != server for n in js.name) or len(js.position) != len(js.name):
            self.reject(key, f"{server} reports joints it does not serve, or no positions: {list(js.name)}")
            return
        for k, n in enumerate(js.name):
            self._measured[n] = (js.position[k], js.velocity[k] if js.velocity else 0.0,
                                 js.effort[k] if js.effort else 0.0)

    def _merge_external(self, out: msgs.JointState) -> None:
        """Put the servers' measurements in place of the emulated encoders of external joints."""
        for i, n in enumerate(out.name):
            m = self._measured.get(n)
            if m is not None:
                out.position[i] = m[0]
                if out.velocity:
                    out.velocity[i] = m[1]
                if out.effort:
                    out.effort[i] = m[2]

    def _make_handler(self, topic: str) -> Any:
        sensors = self._by_truth.get(topic, [])
        ack = topic == ACK_TRUTH and self.lockstep
        merge = bool(self._external)
        throttle, dt_ns, dec = self._throttle, self.sc.dt_ns, self.sc.planner_decimation

        def handle(msg: Any, key: str) -> None:
            stamp = msgs.ns_of(msg.header.stamp)
            self.sim_ns = max(self.sim_ns, stamp)
            if topic == "joint_states" and not self._check_joints(msg, key):
                return  # rejected: no ack either, physics reports the missing acknowledgement
            for s, pub in sensors:
                out = s.sample(msg, stamp) if pub is not None else None
                if out is not None:
                    if merge and s.output_topic == "joint_states":
                        self._merge_external(out)
                    pub.put(out)
                    if throttle is not None and s.output_topic == "joint_states" and (stamp // dt_ns) % dec == 0:
                        throttle.put(out)
            if ack:
                self.ack(stamp)

        return handle

    def _check_joints(self, msg: msgs.JointState, key: str) -> bool:
        """The joints of the truth must not change during a run (names fixed by the first message)."""
        if not msg.position:
            return self.reject(key, "JointState without positions")
        if self._joint_names is None:
            self._joint_names = list(msg.name)
        elif msg.name != self._joint_names:
            return self.reject(key, f"JointState names {list(msg.name)} differ from {self._joint_names}")
        return True

    def health_values(self) -> dict[str, Any]:
        return {
            f"sensor:{s.name}": (f"{s.type_name} {s.rate_hz:g} Hz, {s.published} out" if s.enabled else "disabled")
            for s in self.sensors
        }
