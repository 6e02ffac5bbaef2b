"""ROS 2 on DDS: a robot's topics for labs whose ROS 2 runs on the default RMW (Fast DDS, Cyclone DDS)
(``hilsim up rover --hil config/ros2/dds.yaml``; docs/ros2.md, "Labs on the default RMW (DDS)").

hilsim's keys are rmw_zenoh's, so a ROS 2 node on ``rmw_zenoh_cpp`` reads them directly. A node on a
DDS RMW does not speak Zenoh: this bridge is a DDS participant (Cyclone DDS, the ``cyclonedds``
binding) that republishes the topics of ``to_dds`` as ROS 2 does on DDS and takes those of
``from_dds`` back onto their Zenoh keys:

- topic ``rt/<ROS 2 topic name>`` (``rt/rover/odom``, ``rt/clock``), type ``<pkg>::msg::dds_::<Type>_``,
  XCDR1 little endian (data representation XCDR1 only, as the RMWs write). The type is a cyclonedds
  ``IdlStruct`` generated from the ROS 2 definition in :mod:`hilsim.core.ros2.types` (its name and,
  for peers that compare them, its XTypes layout); the samples themselves are hilsim's CDR bytes,
  sent as they are (the binding's raw write and take), so nothing is decoded and encoded again on
  the way out. A payload the type does not fit is refused by Cyclone's own check (counted,
  ``dds_write_failed``);
- QoS as ROS 2 publishes: ``rmw_qos_profile_default`` (reliable, volatile, keep-last 10) for most,
  ``sensor_data`` (best effort, keep-last 5) for ``scan``, ``imu``, ``gps/fix`` as sensor drivers
  publish them, rclcpp's ``ClockQoS`` (best effort, keep-last 1) for ``/clock``, tf2's (reliable,
  keep-last 100) for ``tf``, transient local keep-last 1 for ``/tf_static`` and ``robot_description``
  (taken from Zenoh as rmw_zenoh subscribes to them: from the publishers' caches too, so a late
  bridge still has them); ``qos`` overrides per topic. Readers of ``from_dds`` are reliable,
  keep-last 10 (what ``ros2 topic pub``, teleop and Nav2 write);
- DDS domain = ``ros2.domain_id`` of the scenario (ROS_DOMAIN_ID);
- what comes from DDS is decoded and validated like any input (:func:`hilsim.core.msgs.decode`): a
  payload that is not a valid message (garbage, NaN, arrays that disagree) is a counted rejection
  (``rejected:rt/<topic>``), logged, and the bridge goes on. A valid one is published on the
  Zenoh key with this bridge's publisher (graph token, rmw_zenoh attachment, as every service's).

Where DDS goes: ``CYCLONEDDS_URI`` when it is set (the lab's own Cyclone configuration), else
:data:`LOOPBACK_CONFIG`: interface ``lo`` only, multicast off, unicast discovery to 127.0.0.1 with
``ParticipantIndex`` auto, so nothing leaves the machine unless asked to.

Loop prevention: DDS readers ignore this participant's own writers (``IgnoreLocal``), and a Zenoh
sample written by this bridge's own publishers (its gid, in the attachment) is not sent to DDS
again; both counted (``loop_dropped``). So a topic may be in both lists.

Only topics: the goals (``planner/goal``, ``navigator/goal``) and ROS 2 actions are not bridged.

Reads: the keys of ``to_dds`` (raw, only from announced writers: :mod:`hilsim.core.provenance`).
Writes: the keys of ``from_dds``; ``health/bridge-ros2-dds`` (per DDS topic ``dds_out:``/``dds_in:``
counts and ``matched:`` peers, ``loop_dropped``, ``dds_write_failed``), ``log/bridge-ros2-dds``.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import zenoh
import zenoh.ext as zenoh_ext

# the binding's raw sample calls: bytes in, bytes out (DataWriter.write and DataReader.take would
# go through Python objects); Cyclone still checks every sample against the topic's type
from cyclonedds._clayer import ddspy_take, ddspy_write
from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from pydantic import BaseModel, ConfigDict, Field

from hilsim.bridges import dds_discovery
from hilsim.bridges.dds_graph import GraphAnnouncer, participant_user_data
from hilsim.bridges.dds_types import dds_struct, user_data
from hilsim.bridges.link import OncePer
from hilsim.core import keys as keyscheme
from hilsim.core import msgs, registry, transport
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire
from hilsim.core.service import Publisher, Service

QosName = Literal["default", "sensor_data", "clock", "tf", "latched"]
PROFILES: dict[str, wire.Qos] = {
    "default": wire.QOS_DEFAULT,  # rmw_qos_profile_default: reliable, volatile, keep-last 10
    "sensor_data": wire.QOS_SENSOR_DATA,  # best effort, volatile, keep-last 5
    "clock": wire.QOS_CLOCK,  # rclcpp ClockQoS: best effort, keep-last 1
    "tf": wire.Qos(depth=100),  # tf2_ros DynamicBroadcasterQoS: reliable, volatile, keep-last 100
    "latched": wire.QOS_LATCHED,  # tf2_ros StaticBroadcasterQoS, robot_description: transient local, keep-last 1
}
#: how ROS 2 publishes these (a driver's SensorDataQoS, the clock's, tf2's), by configured or full
#: topic name; every other topic: default
TOPIC_QOS: dict[str, QosName] = {"scan": "sensor_data", "imu": "sensor_data", "gps/fix": "sensor_data",
                                 "/clock": "clock", "tf": "tf", "/tf": "tf", "/tf_static": "latched",
                                 "robot_description": "latched"}
CLOCK = "/clock"
TAKE_AT_ONCE = 64  # samples taken from one reader per wake-up
DDS_RETCODE_TIMEOUT = -10  # dds_write's answer when a reliable reader is too far behind


class Ros2DdsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    to_dds: list[str] | None = Field(
        None, description="topics republished on DDS: the robot's (relative to its namespace, as in docs/keys.md) "
                          "or the simulation's (/clock; tf is the robot's or /tf, wherever docs/keys.md puts it); "
                          "default: what the scenario's robot publishes (default_to_dds)")
    from_dds: list[str] = Field(default_factory=lambda: ["cmd_vel", "joint_trajectory"],
                                description="the robot's topics taken from DDS onto their Zenoh keys")
    qos: dict[str, QosName] = Field(default_factory=dict, description="per topic, over the defaults (sensor_data "
                                    "for scan, imu, gps/fix; clock for /clock; tf for tf; latched for /tf_static and "
                                    "robot_description; else default)")


def default_to_dds(sc: Scenario) -> list[str]:
    """What a ROS 2 user of this scenario's robot reads: its encoders and frames, the clock, its
    description, its enabled sensors' outputs (imu, scan, gps/fix), and the wheel odometry of a
    mobile base's controller."""
    out = ["joint_states", "tf", "/tf_static", CLOCK, "robot_description"]
    for s in sc.sensors.values():
        if s.enabled:
            topic = registry.load("sensors", s.type).output_topic
            if topic not in out:
                out.append(topic)
    if "odom" in getattr(registry.service_class("controller", sc), "writes_topics", ()):
        out.append("odom")
    return out


_DOMAINS: dict[int, Any] = {}  # one Cyclone domain per id in a process (a fleet's bridges, composed)
_DOMAINS_LOCK = threading.Lock()


def _shared_domain(domain_id: int, xml: str) -> Any:
    """The process's Cyclone domain ``domain_id``, made with ``xml`` by the first bridge that asks (Cyclone
    refuses a second one of the same id); kept while a participant lives in it."""
    with _DOMAINS_LOCK:
        d = _DOMAINS.get(domain_id)
        if d is None:
            d = _DOMAINS[domain_id] = Domain(domain_id, xml)
        return d


# ------------------------------------------------------------------------------ QoS on DDS
def dds_qos(q: wire.Qos, *, reader: bool = False, ros_type: str | None = None) -> Qos:
    # a writer never waits for a slow DDS reader (max_blocking_time 0): the simulation does not run at the
    # pace of a lab's node; what such a reader could not take in time is dropped for it, and counted
    reliability = (Policy.Reliability.Reliable(duration(seconds=0)) if q.reliability == wire.Reliability.RELIABLE
                   else Policy.Reliability.BestEffort)
    durability = (Policy.Durability.TransientLocal if q.durability == wire.Durability.TRANSIENT_LOCAL
                  else Policy.Durability.Volatile)
    history = Policy.History.KeepAll if q.history == wire.History.KEEP_ALL else Policy.History.KeepLast(q.depth)
    policies = [reliability, durability, history, Policy.DataRepresentation(use_cdrv0_representation=True)]
    if ros_type is not None:  # the ROS 2 type hash, where rclpy's graph reads it
        policies.append(Policy.Userdata(user_data(ros_type)))
    if reader:
        policies.append(Policy.IgnoreLocal.Participant)  # never what this bridge wrote itself
    return Qos(*policies)


@dataclass
class Route:
    """One topic between its Zenoh key and its DDS topic."""

    name: str  # as configured: "odom", "/clock"
    key: str
    cls: type
    dds_topic: str  # rt/rover/odom
    qos: QosName
    writer: Any = None  # DataWriter (to_dds)
    reader: Any = None  # DataReader (from_dds)
    pub: Publisher | None = None  # its Zenoh publisher (from_dds)
    decls: list[Any] = field(default_factory=list)


class Ros2DdsBridgeService(Service):
    name = "bridge-ros2-dds"
    stop_rank = 40  # after the loop's services, like the other bridges
    Config = Ros2DdsConfig
    cfg: Ros2DdsConfig
    WARN_EVERY = 5.0

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = f"{scenario.source or 'scenario'}: {self.name}"
        self.domain_id = self.keys.domain
        to_dds = default_to_dds(scenario) if self.cfg.to_dds is None else self.cfg.to_dds
        self.out = [self._route(n, f"{where}.to_dds") for n in to_dds]
        self.inn = [self._route(n, f"{where}.from_dds") for n in self.cfg.from_dds]
        for r in self.inn:
            if r.key == self.keys.clock or r.name.startswith("truth/"):
                raise ConfigError(f"{where}.from_dds: {r.name} is written by physics; a second writer from DDS "
                                  f"would fight it")
        for names, what in ((to_dds, "to_dds"), (self.cfg.from_dds, "from_dds")):
            if len(set(names)) != len(names):
                raise ConfigError(f"{where}.{what}: a topic is listed twice")
        unknown = sorted(set(self.cfg.qos) - {r.name for r in [*self.out, *self.inn]})
        if unknown:
            raise ConfigError(f"{where}.qos: {', '.join(unknown)} not in to_dds or from_dds")
        try:
            self.discovery = dds_discovery.discovery()
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None
        self._said = OncePer(self.WARN_EVERY)
        self._dds_lock = threading.Lock()  # DDS entities exist while held and _dds_open
        self._dds_open = False
        self._domain: Any = None
        self._graph: GraphAnnouncer | None = None
        self.dp: Any = None
        self._topics: dict[str, Any] = {}
        self._own_gids: set[bytes] = set()  # this bridge's Zenoh publishers: never back to DDS
        self._own_writers: set[int] = set()  # this bridge's DDS writers: never back to Zenoh
        self.dds_out: Counter[str] = Counter()
        self.dds_in: Counter[str] = Counter()
        self.loop_dropped = 0
        self.write_failed = 0
        self.slow_dropped: Counter[str] = Counter()

    def _route(self, name: str, where: str) -> Route:
        bare = name.lstrip("/")
        if not name.startswith("/") and (bare in keyscheme.TOPICS or bare in keyscheme.plugin_topics()):
            key = self.keys.topic(name)  # the robot's: odom -> /rover/odom
        elif bare in keyscheme.GLOBAL_TOPICS and isinstance(getattr(self.keys, bare, None), str):
            key = getattr(self.keys, bare)  # the simulation's: /clock (and tf, where it is global)
        else:
            known = sorted([*keyscheme.TOPICS, *keyscheme.plugin_topics(), *(f"/{g}" for g in keyscheme.GLOBAL_TOPICS)])
            raise ConfigError(f"{where}: unknown topic {name!r}; known: {', '.join(known)}")
        cls = keyscheme.message_type(key)
        ros_type = msgs.type_name(cls)
        try:
            dds_struct(ros_type)
        except (KeyError, ValueError) as e:
            raise ConfigError(f"{where}: {name}: {ros_type} cannot be put on DDS: {e}") from None
        qos = self.cfg.qos.get(name) or TOPIC_QOS.get(name) or TOPIC_QOS.get(keyscheme.topic_name(key), "default")
        return Route(name, key, cls, "rt" + keyscheme.topic_name(key), qos)

    # ---------------------------------------------------------------- wiring
    def setup(self) -> None:
        assert self.session is not None
        self._domain = _shared_domain(self.domain_id, self.discovery.xml)
        # a ROS 2 participant says its enclave in USER_DATA (rmw_dds_common): how the RMWs tell one from a bare DDS app
        pq = Qos(Policy.Userdata(participant_user_data(self.sc.ros2.enclave)))
        self.dp = DomainParticipant(self.domain_id, qos=pq)
        for r in self.out:
            r.writer = DataWriter(self.dp, self._topic(r), qos=dds_qos(PROFILES[r.qos], ros_type=self._ros_type(r)))
            self._own_writers.add(r.writer.get_instance_handle())
        for r in self.inn:
            r.pub = self.publisher(r.key)
            self._own_gids.add(r.pub.gid)
            r.reader = DataReader(self.dp, self._topic(r),
                                  qos=dds_qos(PROFILES[r.qos], reader=True, ros_type=self._ros_type(r)))
        # the ROS 2 graph: one node, /<robot>/bridge_ros2_dds, holding every reader and writer
        self._graph = GraphAnnouncer(self.dp)
        self._graph.announce([(self.keys.namespace, self.node_name, [r.reader for r in self.inn],
                               [r.writer for r in self.out])])
        self._dds_open = True
        # Zenoh -> DDS: the payloads as they are (no decode), from announced writers only
        local = getattr(self.session, "local_subscriber", None)
        for r in self.out:
            latched = r.qos == "latched"
            if latched and isinstance(self.session, zenoh.Session):
                # transient-local, as rmw_zenoh subscribes: the publishers' caches give what came before
                history = zenoh_ext.HistoryConfig(detect_late_publishers=True)
                r.decls.append(zenoh_ext.declare_advanced_subscriber(self.session, r.key, self._on_zenoh(r),
                                                                     history=history))
            else:
                r.decls.append(self.session.declare_subscriber(r.key, self._on_zenoh(r)))
            qos = wire.QOS_LATCHED if latched else None
            r.decls.append(self.session.liveliness().declare_token(self.graph_token("MS", r.key, qos)))
            if local is not None:  # composed (hilsim.launch.compose): the process's own services' messages
                r.decls.append(local(r.key, lambda k, m, att, r=r: self._to_dds(r, k, msgs.encode(m), att)))
        self.log.info("DDS domain %d (%s) as node %s/%s: to DDS %s; from DDS %s", self.domain_id,
                      self.discovery.said, self.keys.namespace.rstrip("/"), self.node_name,
                      ", ".join(r.dds_topic for r in self.out),
                      ", ".join(r.dds_topic for r in self.inn) or "nothing")

    @staticmethod
    def _ros_type(r: Route) -> str:
        return msgs.type_name(r.cls)

    def _topic(self, r: Route) -> Any:
        t = self._topics.get(r.dds_topic)
        if t is None:
            t = self._topics[r.dds_topic] = Topic(self.dp, r.dds_topic, dds_struct(msgs.type_name(r.cls)),
                                                  qos=dds_qos(PROFILES[r.qos]))
        return t

    # ---------------------------------------------------------------- Zenoh -> DDS
    def _on_zenoh(self, r: Route) -> Callable[[Any], None]:
        def on_sample(sample: Any) -> None:
            self._to_dds(r, str(sample.key_expr), sample.payload.to_bytes(), transport.read_attachment(sample))
        return on_sample

    def _to_dds(self, r: Route, k: str, data: bytes, att: transport.Attachment | None) -> None:
        self.counts_in[k] += 1
        if att is not None and att.gid in self._own_gids:
            with self.lock:
                self.loop_dropped += 1  # what this bridge took from DDS itself
            return
        why, gap = self.provenance.check(k, att, data)  # the payload: a duplicate is the same sample
        if why is not None:
            with self.lock:
                self.reject(k, why)
            return
        if gap:
            self.seq_gaps[k] += gap
        if len(data) < 4 or data[:2] != b"\x00\x01":
            with self.lock:
                self.reject(k, f"not little-endian plain CDR (header {data[:4].hex()})")
            return
        data = data.ljust((len(data) + 3) & ~3, b"\0")
        with self._dds_lock:
            if not self._dds_open:
                return
            rc = ddspy_write(r.writer._ref, data)
        with self.lock:
            if rc == DDS_RETCODE_TIMEOUT:  # a reliable reader that has not acknowledged enough yet
                self.slow_dropped[r.dds_topic] += 1
                if self._said.due(f"slow:{r.dds_topic}"):
                    self.warn(f"a DDS reader of {r.dds_topic} is too slow: {self.slow_dropped[r.dds_topic]} samples "
                              "dropped for it so far (the simulation does not wait for DDS)")
            elif rc < 0:
                self.write_failed += 1
                if self._said.due(f"write:{r.dds_topic}"):
                    self.warn(f"DDS write on {r.dds_topic} failed (return code {rc}, {self.write_failed} so far): "
                              f"the payload does not fit {ros2types.dds_type_name(msgs.type_name(r.cls))}")
            else:
                self.dds_out[r.dds_topic] += 1

    # ---------------------------------------------------------------- DDS -> Zenoh
    def loop(self) -> None:
        if not self.inn:
            super().loop()
            return
        ws = WaitSet(self.dp)
        conds = [ReadCondition(r.reader, SampleState.Any | ViewState.Any | InstanceState.Any) for r in self.inn]
        for c in conds:
            ws.attach(c)
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        while not self.stop_event.is_set():
            ws.wait(duration(milliseconds=200))
            for r in self.inn:
                got = ddspy_take(r.reader._ref, mask, TAKE_AT_ONCE)
                if isinstance(got, int):  # a DDS error code
                    with self.lock:
                        self.fault(f"taking from {r.dds_topic} failed (return code {got})")
                    continue
                for data, info in got:
                    if info.valid_data:
                        self.from_dds(r, bytes(data), info.publication_handle)
        for c in conds:
            ws.detach(c)

    def from_dds(self, r: Route, data: bytes, writer: int = 0) -> bool:
        """One sample taken from DDS: validated and put on its Zenoh key (True), or counted and dropped."""
        with self.lock:
            if self.stop_event.is_set():
                return False
            self.counts_in[r.dds_topic] += 1
            if writer in self._own_writers:
                self.loop_dropped += 1
                return False
            try:
                m = msgs.decode(r.cls, data)
            except msgs.BadMessage as e:
                return self.reject(r.dds_topic, str(e))
            assert r.pub is not None
            r.pub.put(m)
            self.dds_in[r.dds_topic] += 1
            return True

    # ---------------------------------------------------------------- reporting, end
    def health_values(self) -> dict[str, Any]:
        v: dict[str, Any] = {"dds_domain": self.domain_id,
                             "dds_config": self.discovery.said,
                             "loop_dropped": self.loop_dropped, "dds_write_failed": self.write_failed}
        for r in self.out:
            v[f"dds_out:{r.dds_topic}"] = self.dds_out[r.dds_topic]
            v[f"matched:{r.dds_topic}"] = self._matched(r.writer)
            if self.slow_dropped[r.dds_topic]:
                v[f"slow_reader_dropped:{r.dds_topic}"] = self.slow_dropped[r.dds_topic]
        for r in self.inn:
            v[f"dds_in:{r.dds_topic}"] = self.dds_in[r.dds_topic]
            v[f"matched_writers:{r.dds_topic}"] = self._matched(r.reader)
        return v

    def _matched(self, entity: Any) -> int | str:
        """Peers matched (instance handles only: the builtin topics' data is never read here)."""
        if entity is None or not self._dds_open:
            return 0
        try:
            if isinstance(entity, DataWriter):
                return len(entity.get_matched_subscriptions())
            return len(entity.get_matched_publications())
        except Exception:
            return "?"

    def teardown(self) -> None:
        for r in [*self.out, *self.inn]:
            for d in r.decls:
                try:
                    d.undeclare()
                except Exception:
                    pass
        with self._dds_lock:  # no Zenoh callback is writing now, and none will
            self._dds_open = False
            for r in [*self.out, *self.inn]:
                r.writer = r.reader = None
            self._topics.clear()
            self._graph = None
            self.dp = None  # deleting the participant deletes what is left of it
            self._domain = None
