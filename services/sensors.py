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

With ``fleet.arrays`` (robots > 1, :class:`FleetSensorService`) the encoders of every robot are stepped
by the fleet driver from ``fleet/truth/joint_states`` instead; the other sensors stay here.

Noise comes from generators seeded by ``seed`` and the sensor name: the same scenario and the
same truth give the same outputs, bit for bit.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.keys import topic_name
from hilsim.core.service import Publisher, Service
from hilsim.sim.sensing import Encoder, Sensor, make_sensor

# Physics publishes this truth last before the clock: handling it completes the step.
ACK_TRUTH = "joint_states"


class SensorService(Service):
    name = "sensors"
    stop_rank = 30

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        # with a controller, its command for step k proves the sensors handled step k
        return None if "controller" in sc.services else 1

    @classmethod
    def array_driver(cls, sc: Scenario) -> type[Service] | None:
        """The fleet driver stepping every robot's encoders as arrays (fleet.arrays)."""
        return FleetSensorService

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
            if self.fleet_driven and topic == ACK_TRUTH:
                continue  # robots as arrays: the fleet driver reads fleet/truth/joint_states for every robot
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
        throttle, tick = self._throttle, self.sc.planner_tick

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
                    if throttle is not None and s.output_topic == "joint_states" and tick(stamp):
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


class FleetSensorService(Service):
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): every robot's encoders in one step.

    Reads ``<prefix>/<robot>/fleet/truth/joint_states`` (every robot's truth, joints ``arm<k>/<joint>``).
    Writes ``<prefix>/<robot>/fleet/joint_states`` (every robot's encoders, same layout, same stamp),
    ``fleet/joint_states_throttle`` (the same, of the planners' decision steps only; with a planner) and,
    from the same values, each robot's ``<prefix>/arm<k>/joint_states`` (and ``joint_states_throttle``)
    through that robot's own publisher, when anyone subscribes it; ``sync/sensors`` in the scenario's namespace when the
    sensors are a lockstep participant (no controller). The robots' other sensors (the IMU) stay
    with their :class:`SensorService`. Each robot's noise comes from its own encoder's generator
    (seed ``seed + k``), drawn robot by robot, so it is what the per-robot path draws, bit for bit.
    """

    name = "sensors"
    stop_rank = 31  # started before the robots' services it drives, stopped after them
    acks_for_robots = True  # in lockstep its fleet sample is every robot's acknowledgement
    lockstep_period = SensorService.lockstep_period

    def __init__(self, scenario: Scenario, members: list[SensorService]) -> None:
        super().__init__(scenario)
        self.members = members
        self.encoders: list[Encoder] = []
        self.pubs: list[Publisher] = []  # each robot's joint_states, once its own setup declared it
        for m in members:
            enc = [s for s in m.sensors if isinstance(s, Encoder) and s.enabled and s.output_topic == ACK_TRUTH]
            if len(enc) != 1:
                raise ConfigError(f"{scenario.source}: fleet.arrays: {m.sc.robot} needs exactly one enabled encoder "
                                  f"sensor (has {len(enc)})")
            self.encoders.append(enc[0])
        first = self.encoders[0]
        if any(e.decimation != first.decimation for e in self.encoders):
            raise ConfigError(f"{scenario.source}: fleet.arrays: every robot's encoders need the same rate_hz")
        self.n_robots = len(members)
        ps = [e.p for e in self.encoders]
        # per robot (a column): robot_overrides may give each its own encoder parameters
        self.noise = [p.noise_std for p in ps]
        self.vel_noise = [p.velocity_noise_std for p in ps]
        self.res = np.array([[p.resolution] for p in ps])
        self.vel_res = np.array([[p.velocity_resolution] for p in ps])
        self.names: list[str] | None = None
        self.robot_joints: list[list[str]] = []

    def setup(self) -> None:
        self.pub = self.publisher(self.keys.fleet("joint_states"))
        # the planners' ticks (as SensorService's joint_states_throttle): the fleet sample of those steps
        self.throttle = (self.publisher(self.keys.fleet("joint_states_throttle"))
                         if "planner" in self.sc.services else None)
        self.subscribe(self.keys.fleet("truth/joint_states"), msgs.JointState, self.on_truth)

    @staticmethod
    def _quantise(x: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Encoder._quantise row by row: ``round(x / q) * q`` where q > 0, else x, elementwise the same."""
        if not (q > 0.0).any():
            return x
        safe = np.where(q > 0.0, q, 1.0)
        return np.where(q > 0.0, np.round(x / safe) * safe, x)

    def on_truth(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        self.sim_ns = max(self.sim_ns, stamp)
        if self.names is None:
            self.names = list(msg.name)
            n = len(self.names) // self.n_robots
            # each robot's slice by the single robot's joint names, as its own truth names them
            self.robot_joints = [[j.split("/", 1)[-1] for j in self.names[k * n:(k + 1) * n]]
                                 for k in range(self.n_robots)]
        if list(msg.name) != self.names or len(msg.position) != len(msg.name) or len(msg.name) % self.n_robots:
            self.reject(key, f"fleet JointState of {len(msg.name)} joints differs from the first ({len(self.names)})")
            return
        if self.encoders[0].due(stamp):
            self._measure(msg, stamp)
        if self.lockstep:
            self.ack(stamp)

    def _measure(self, msg: msgs.JointState, stamp: int) -> None:
        k_n = self.n_robots
        pos = np.asarray(msg.position, float).reshape(k_n, -1)
        vel = np.asarray(msg.velocity, float).reshape(k_n, -1) if msg.velocity else np.zeros((k_n, 0))
        # noise as Encoder.measure draws it: each robot from its own generator, position then velocity
        if any(self.noise) or any(self.vel_noise):
            pos, vel = pos.copy(), vel.copy()
            for k, e in enumerate(self.encoders):
                if self.noise[k] > 0.0:
                    pos[k] = pos[k] + e.rng.normal(0.0, self.noise[k], pos.shape[1])
                if self.vel_noise[k] > 0.0 and vel.shape[1]:
                    vel[k] = vel[k] + e.rng.normal(0.0, self.vel_noise[k], vel.shape[1])
        pos = self._quantise(pos, self.res)
        vel = self._quantise(vel, self.vel_res)
        header = msgs.header(stamp, msg.header.frame_id)
        effort = list(msg.effort)
        out = msgs.JointState(header=header, name=self.names, position=pos.ravel().tolist(),
                              velocity=vel.ravel().tolist(), effort=effort)
        self.pub.put(out)
        tick = self.throttle is not None and self.sc.planner_tick(stamp)
        if tick:
            self.throttle.put(out)  # type: ignore[union-attr]
        n = pos.shape[1]
        if not self.pubs:  # the robots' services started after this one; by step 0 all are set up
            self.pubs = [next(p for s, p in m._by_truth[ACK_TRUTH] if s is e)  # type: ignore[misc]
                         for e, m in zip(self.encoders, self.members, strict=True)]
        for k, (e, pub, m) in enumerate(zip(self.encoders, self.pubs, self.members, strict=True)):
            e.published += 1
            m.sim_ns = max(m.sim_ns, stamp)
            # lever 1: a robot's own keys cost nothing while nobody reads them (the fleet sample has
            # the same values, and the recorder takes those)
            want = pub.wanted(covered=True)
            throttle = m._throttle if tick else None
            want_tick = throttle is not None and throttle.wanted(covered=True)
            js = msgs.JointState(header=msgs.header(stamp, msg.header.frame_id), name=self.robot_joints[k],
                                 position=pos[k].tolist(), velocity=vel[k].tolist(),
                                 effort=effort[k * n:(k + 1) * n]) if want or want_tick else None
            if js is not None and want:
                pub.put(js)
            else:
                pub.skip()
            if throttle is not None:
                if js is not None and want_tick:
                    throttle.put(js)
                else:
                    throttle.skip()

    def health_values(self) -> dict[str, Any]:
        return {"robots": self.n_robots, "arrays": "yes"}
