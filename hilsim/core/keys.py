"""The key scheme: the one place that spells Zenoh keys and says which message type each carries.

Every data key is the key a ROS 2 node on ``rmw_zenoh_cpp`` uses for the same topic
(:mod:`hilsim.core.ros2.wire`): ``<domain id>/<namespace>/<topic>/<DDS type>/<RIHS01 type hash>``,
e.g. ``0/arm/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e…``. A robot's namespace
is ``/<robot>`` by default (``ros2.namespace``); sim time is the global ``/clock``; ground truth
lives under ``<namespace>/truth/…``. So ``ros2 topic echo /arm/joint_states`` on rmw_zenoh connected
to the same router reads what the controller reads, and two simulations share a router by using
different ``ros2.domain_id`` values, as ROS 2 systems do.

hilsim's own liveliness (a service is alive, a lockstep participant's role) stays under
``<prefix>/<robot>/…``: it is not data, and ROS 2 tools do not look there; the ROS 2 graph
(nodes, publishers, subscriptions) is announced as rmw_zenoh does, under ``@ros2_lv/<domain>/…``.

``docs/keys.md`` documents the same table for people; ``TOPIC_TABLE`` below is the table for code (each
topic's message type and writers: :mod:`hilsim.core.rights` turns the writers into the router's access
control, so the table decides who may write what), ``TOPICS`` its types,
extended by other packages through the ``hilsim.topics`` entry-point group (:func:`plugin_topics`).
No other module builds a key string by hand: services ask a :class:`Keys` instance, and
:func:`message_type` / :func:`topic_name` read a key back.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any, NamedTuple

from hilsim.core import msgs
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire as ros2wire

DEFAULT_PREFIX = "hilsim"

# Who writes a key (docs/keys.md's "written by"): a service of the scenario by name (every robot's,
# for a per-robot service), USER (the run's tools and the ROS 2 nodes given their credentials:
# what a person is meant to command), or OWN (each service its own key: ``health/<service>``). This
# table, not a second list, decides who may write what: hilsim.core.rights turns it into the router's
# access control (docs/security.md); a key no service of a run writes is the user's in that run.
USER = "user"
OWN = "own"


class Topic(NamedTuple):
    """A row of the key table: the message type a topic carries, who writes it, and whether each sample
    is given once (``once``: an order or a result that no later sample replaces, as a trajectory, unlike
    a stream of states at a rate). In realtime a stream's sample may be dropped on a congested link
    (the next one replaces it); a sample given once never is (hilsim.core.publisher)."""

    cls: type
    writers: tuple[str, ...]
    once: bool = False


def _row(cls: type, *writers: str, once: bool = False) -> Topic:
    return Topic(cls, writers, once)


# topic -> (message type, writers). Topics are relative to <prefix>/<robot>/ unless listed in GLOBAL_TOPICS.
TOPIC_TABLE: dict[str, Topic] = {
    "joint_states": _row(msgs.JointState, "sensors"),
    # joint_states of the planner's decision steps only (planner.rate_hz), named as topic_tools'
    # throttle names its output: the planner decides at 100 Hz and need not take 1 kHz
    "joint_states_throttle": _row(msgs.JointState, "sensors"),
    # the drive emulator in simulation mode commands its joints in the controller's place
    "joint_commands": _row(msgs.JointState, "controller", "drive-emulator"),
    # given once: dropped on a congested link (a loaded machine), the arm would never move to its target
    # a person's, a tool's, a ROS 2 node's command (the planner hands its own on planner/joint_trajectory)
    "joint_trajectory": _row(msgs.JointTrajectory, "bridge-ros2-dds", USER, once=True),
    # the planner's trajectory, on a key only its identity may write: a replay of it by anyone else can
    # come only on joint_trajectory, where it is a person's command like any other (docs/security.md)
    "planner/joint_trajectory": _row(msgs.JointTrajectory, "planner", once=True),
    "controller/reference": _row(msgs.JointState, "controller"),
    "imu": _row(msgs.Imu, "sensors"),
    "gps/fix": _row(msgs.NavSatFix, "sensors", "bridge-mavlink"),  # a real GPS in the loop, in its place
    "scan": _row(msgs.LaserScan, "sensors"),
    "cmd_vel": _row(msgs.Twist, "navigator", "bridge-ros2-dds", USER),
    "odom": _row(msgs.Odometry, "controller"),
    "robot_description": _row(msgs.String, "physics"),  # the URDF, transient-local (a late joiner gets it)
    "truth/joint_states": _row(msgs.JointState, "physics"),
    "truth/imu": _row(msgs.Imu, "physics"),
    "truth/odom": _row(msgs.Odometry, "physics"),
    "truth/contacts": _row(msgs.Contacts, "physics"),
    "planner/path": _row(msgs.JointTrajectory, "planner", once=True),
    "planner/feedback": _row(msgs.MoveFeedback, "planner"),
    "planner/result": _row(msgs.MoveResult, "planner", once=True),
    "task/result": _row(msgs.MoveResult, "planner", "navigator", once=True),
    "map": _row(msgs.OccupancyGrid, "navigator"),
    "plan": _row(msgs.Path, "navigator", once=True),
    "navigator/feedback": _row(msgs.MoveFeedback, "navigator"),
    "navigator/result": _row(msgs.MoveResult, "navigator", once=True),
    # robots > 1 with fleet.arrays (hilsim.core.fleet): one sample per step for every robot, under the
    # scenario's own namespace (/arm/fleet/…), its joints named <robot>/<joint> (arm0/joint_1, …)
    "fleet/truth/joint_states": _row(msgs.JointState, "physics"),
    "fleet/joint_states": _row(msgs.JointState, "sensors"),
    "fleet/joint_states_throttle": _row(msgs.JointState, "sensors"),
    "fleet/joint_commands": _row(msgs.JointState, "controller"),
    "fleet/controller/reference": _row(msgs.JointState, "controller"),
}
TOPICS: dict[str, type] = {t: row.cls for t, row in TOPIC_TABLE.items()}
# Keys whose last segment is a service name: each written by that service only.
PER_SERVICE_TOPICS: dict[str, type] = {
    "health": msgs.DiagnosticArray,
    "sync": msgs.Clock,
    "log": msgs.Log,
}
# Keys <prefix>/<robot>/hw/<server>/<topic>: what an external joint server (a bridge, the motor
# model) publishes. One key per server, so each has exactly one writer: the server itself (setpoints:
# a bridge's setpoints as they went on the bus, for hilsim identify)
SERVER_TOPICS: dict[str, type] = {"joint_states": msgs.JointState, "setpoints": msgs.JointState}
# /tf and /tf_static are global, as tf2 and rviz2 expect (a fleet prefixes its frames with the robot name)
GLOBAL_TABLE: dict[str, Topic] = {"clock": _row(msgs.Clock, "physics"), "tf": _row(msgs.TFMessage, "physics"),
                                  "tf_static": _row(msgs.TFMessage, "physics")}
GLOBAL_TOPICS: dict[str, type] = {t: row.cls for t, row in GLOBAL_TABLE.items()}


class Served(NamedTuple):
    """A row of the queryables' table: request and reply types, who serves it, who may ask."""

    request: type
    reply: type
    server: str
    askers: tuple[str, ...]


# Queryables (request/reply): topic -> (request type, reply type, server, who may ask).
SERVED_TABLE: dict[str, Served] = {
    "planner/goal": Served(msgs.MoveGoal, msgs.GoalResponse, "planner", (USER,)),
    "planner/cancel": Served(msgs.CancelRequest, msgs.GoalResponse, "planner", (USER,)),
    "navigator/goal": Served(msgs.MoveGoal, msgs.GoalResponse, "navigator", (USER,)),
    "navigator/cancel": Served(msgs.CancelRequest, msgs.GoalResponse, "navigator", (USER,)),
    "controller/set_parameters": Served(msgs.SetParameters, msgs.SetParametersResult, "controller", (USER,)),
    # lockstep: the planner asks whether the controller holds the trajectory that starts at a stamp
    "controller/has_trajectory": Served(msgs.Time, msgs.GoalResponse, "controller", ("planner",)),
}
SERVICES: dict[str, tuple[type, type]] = {n: (row.request, row.reply) for n, row in SERVED_TABLE.items()}
# controller/has_trajectory's answer when no trajectory of that start stamp reached the controller (its
# reason begins so): a realtime planner then sends it again; any other refusal is the trajectory's own
NOT_REACHED = "no joint_trajectory"


def plugin_topics() -> dict[str, type]:
    """Topics other packages add through the ``hilsim.topics`` entry-point group
    (``"my_service/status" = "my_pkg.msgs:Status"``, a message class); a built-in name wins."""
    global _PLUGIN_TOPICS
    if _PLUGIN_TOPICS is None:
        from importlib.metadata import entry_points

        found: dict[str, type] = {}
        for ep in entry_points(group="hilsim.topics"):
            if ep.name in TOPICS or ep.name in SERVICES:
                continue
            try:
                found[ep.name] = ep.load()
            except Exception:  # a broken plug-in must not break the key scheme of everyone else
                continue
        _PLUGIN_TOPICS = found
    return _PLUGIN_TOPICS


_PLUGIN_TOPICS: dict[str, type] | None = None


class UnknownKey(KeyError):
    """A key outside the scheme: no message type is known for it."""


DEFAULT_DOMAIN = 0
DEFAULT_NAMESPACE = "/{robot}"


@cache
def _type_segments(cls: type) -> str:
    """``<DDS type>/<type hash>`` of a message class: the last two chunks of its keys."""
    name = msgs.type_name(cls)
    return f"{ros2types.dds_type_name(name)}/{ros2types.type_hash(name)}"


def classes_by_type() -> dict[str, type]:
    """ROS 2 type name (``sensor_msgs/msg/JointState``) -> message class, for every type a key may carry."""
    global _BY_TYPE
    if _BY_TYPE is None:
        found: dict[str, type] = {}
        tables = [TOPICS, PER_SERVICE_TOPICS, SERVER_TOPICS, GLOBAL_TOPICS, plugin_topics()]
        for table in tables:
            for cls in table.values():
                found.setdefault(msgs.type_name(cls), cls)
        for req, rep in SERVICES.values():
            found.setdefault(msgs.type_name(req), req)
            found.setdefault(msgs.type_name(rep), rep)
        _BY_TYPE = found
    return _BY_TYPE


_BY_TYPE: dict[str, type] | None = None


@dataclass(frozen=True)
class Keys:
    """Builds the keys of one robot in one simulation."""

    prefix: str = DEFAULT_PREFIX
    robot: str = "arm"
    domain: int = DEFAULT_DOMAIN
    namespace_template: str = DEFAULT_NAMESPACE

    @classmethod
    def of(cls, sc: Any, robot: str | None = None) -> Keys:
        """The keys of scenario ``sc`` (its ``prefix``, ``ros2`` section) for ``robot`` (default its own)."""
        ros2 = getattr(sc, "ros2", None)
        return cls(sc.prefix, sc.robot if robot is None else robot,
                   ros2.domain_id if ros2 is not None else DEFAULT_DOMAIN,
                   ros2.namespace if ros2 is not None else DEFAULT_NAMESPACE)

    @property
    def namespace(self) -> str:
        """The robot's ROS 2 namespace, e.g. ``/arm`` (``*`` for every robot in a wildcard)."""
        ns = "/" + self.namespace_template.format(robot=self.robot).strip("/")
        return ns.rstrip("/") or "/"

    def for_robot(self, robot: str) -> Keys:
        return Keys(self.prefix, robot, self.domain, self.namespace_template)

    def _data(self, topic: str, cls: type) -> str:
        return f"{self.domain}/{topic.strip('/')}/{_type_segments(cls)}"

    def topic_name(self, name: str) -> str:
        """The ROS 2 topic name of a topic of this robot, e.g. ``/arm/joint_states``."""
        return f"{self.namespace.rstrip('/')}/{name}"

    def topic(self, name: str) -> str:
        cls = TOPICS.get(name) or plugin_topics().get(name)
        if cls is None and name in SERVICES:
            cls = SERVICES[name][0]
        if cls is None:
            known = sorted([*TOPICS, *plugin_topics()])
            raise UnknownKey(f"unknown topic {name!r}; known: {', '.join(known)}")
        return self._data(self.topic_name(name), cls)

    def service(self, name: str) -> str:
        """The queryable key of a request/reply service of this robot (``planner/goal``)."""
        if name not in SERVICES:
            raise UnknownKey(f"unknown service {name!r}; known: {', '.join(sorted(SERVICES))}")
        return self._data(self.topic_name(name), SERVICES[name][0])

    @property
    def clock(self) -> str:
        return self._data("/clock", GLOBAL_TOPICS["clock"])

    @property
    def tf(self) -> str:
        return self._data("/tf", GLOBAL_TOPICS["tf"])

    @property
    def tf_static(self) -> str:
        return self._data("/tf_static", GLOBAL_TOPICS["tf_static"])

    def truth(self, name: str) -> str:
        return self.topic(f"truth/{name}")

    def fleet(self, name: str) -> str:
        """A fleet-wide topic (``truth/joint_states``, ``joint_states``, ``joint_commands``): with the
        scenario's own keys, ``/<robot>/fleet/<name>`` (hilsim.core.fleet)."""
        return self.topic(f"fleet/{name}")

    def health(self, service: str) -> str:
        return self._data(self.topic_name(f"health/{service}"), PER_SERVICE_TOPICS["health"])

    def sync(self, service: str) -> str:
        """Lockstep acknowledgement of a participant: a Clock stamped with the step it finished."""
        return self._data(self.topic_name(f"sync/{service}"), PER_SERVICE_TOPICS["sync"])

    def log(self, service: str) -> str:
        return self._data(self.topic_name(f"log/{service}"), PER_SERVICE_TOPICS["log"])

    def server_state(self, server: str) -> str:
        """Measured state of the joints an external server serves (sensor_msgs/JointState)."""
        return self._data(self.topic_name(f"hw/{server}/joint_states"), SERVER_TOPICS["joint_states"])

    def server_setpoints(self, server: str) -> str:
        """The setpoints an external server passed on to its device, stamped with the sim time it did (opt-in)."""
        return self._data(self.topic_name(f"hw/{server}/setpoints"), SERVER_TOPICS["setpoints"])

    @property
    def all_server_states(self) -> str:
        return self._data(self.topic_name("hw/*/joint_states"), SERVER_TOPICS["joint_states"])

    # ---------------------------------------------------------- hilsim's own liveliness (not data)
    def alive(self, service: str) -> str:
        """Liveliness token of a running service (no payload)."""
        return f"{self.prefix}/{self.robot}/alive/{service}"

    def lockstep(self, service: str, period: int, lag: int, via: str, gid: str) -> str:
        """Liveliness token of a lockstep participant: ``service`` acknowledges every ``period``-th
        step, and physics waits for the acknowledgement of step k before stepping past k + ``lag``;
        it is ``sync/<service>`` (``via`` = ``sync``) or its ``joint_commands`` (``via`` =
        ``joint_commands``), written by the publisher ``gid`` (hex)."""
        return f"{self.prefix}/{self.robot}/lockstep/{service}/{period}/{lag}/{via}/{gid}"

    @property
    def all_lockstep(self) -> str:
        return f"{self.prefix}/{self.robot}/lockstep/**"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/{self.robot}/alive/*"

    def batch(self, zid: str, node_id: int | str, service: str) -> str:
        """The key on which the ROS 2 node ``node_id`` of Zenoh session ``zid`` (the hilsim service
        ``service``) sends the recorder its samples in batches (``logger.batch``, :mod:`hilsim.core.batch`);
        the same key is its liveliness token, which tells the recorder that this node's publishers need no
        subscription of their own. Under the prefix, not the domain: no ROS 2 tool takes it for a topic.
        The service's name is a chunk of it, so the router lets each service put only its own batches
        (hilsim.core.rights), and the recorder takes from them only the keys the table lets it write."""
        return f"{self.prefix}/batch/{self.domain}/{service}/{zid}/{node_id}"

    @property
    def all_batches(self) -> str:
        """Every batch key (and batching node's token) of the domain, all robots."""
        return f"{self.prefix}/batch/{self.domain}/*/*/*"

    def service_batches(self, service: str) -> str:
        """Every batch key (and token) of ``service``: what the router lets it put."""
        return f"{self.prefix}/batch/{self.domain}/{service}/**"

    @staticmethod
    def batch_service(key: str) -> str | None:
        """The service whose batch key (or token) ``key`` is (:meth:`batch`); None for any other key."""
        parts = key.split("/")
        return parts[-3] if len(parts) >= 6 and parts[-5] == "batch" else None

    @staticmethod
    def batch_node(key: str) -> tuple[str, str] | None:
        """(zid, node id) of a batch key or token (:meth:`batch`); None for any other key."""
        parts = key.split("/")
        if len(parts) < 6 or parts[-5] != "batch":
            return None
        return parts[-2], parts[-1]

    # ---------------------------------------------------------- the ROS 2 graph
    @property
    def all_writers(self) -> str:
        """Every ROS 2 graph token of the domain (publishers among them: :mod:`hilsim.core.provenance`)."""
        return ros2wire.graph_key(self.domain)

    def entity_token(self, kind: str, key: str, *, zid: str, node_id: int, entity_id: int, node: str,
                     enclave: str = "/", qos: ros2wire.Qos = ros2wire.QOS_DEFAULT) -> str:
        """The graph token (``MP``, ``MS``) of node ``node`` in this robot's namespace on the data key ``key``."""
        parts = key.split("/")
        return ros2wire.entity_token(kind, self.domain, zid, node_id, entity_id, enclave, self.namespace, node,
                                     "/" + "/".join(parts[1:-2]), parts[-2], parts[-1], qos)

    def writer_token(self, key: str, node: str = "tool", zid: str = "1", entity_id: int = 1) -> tuple[str, bytes]:
        """The graph token (``MP``) a tool or test declares before writing ``key`` as node ``node`` of
        this robot's namespace, and the gid its samples then carry (the token's hash, as rmw_zenoh's)."""
        token = self.entity_token("MP", key, zid=zid, node_id=0, entity_id=entity_id, node=node)
        return token, ros2wire.entity_gid(token)

    @property
    def everything(self) -> str:
        """Every data key of the domain (all robots, the clock, and any ROS 2 node's topics)."""
        return ros2wire.domain_key(self.domain)

    def scoped(self, expr: str) -> str:
        """A key expression under this simulation's domain, e.g. ``scoped("**")``, ``scoped("arm/**")``."""
        return f"{self.domain}/{expr}"

    # ================================================================ ROS 2 services and actions (rmw_zenoh)
    # (the block below is about ROS 2 request/reply services and actions only; ACTION_TOPICS below the class)
    def ros2_name(self, name: str) -> str:
        """A ROS 2 name of this robot: ``follow_joint_trajectory`` -> ``/arm/follow_joint_trajectory``;
        an absolute name (``/move_group``) stays as it is."""
        return "/" + name.strip("/") if name.startswith("/") else self.topic_name(name.strip("/"))

    def ros2_service(self, name: str, srv_type: str) -> str:
        """The key of ROS 2 service ``name`` (relative to the namespace, or absolute) of type ``srv_type``,
        as rmw_zenoh's server declares its queryable and its client queries it:
        ``<domain>/<service name>/<pkg>::srv::dds_::<Srv>_/<RIHS01 hash of the service type>``. The type is
        the service's (``action_msgs/srv/CancelGoal``; an action's ``…/action/<A>_SendGoal``): rmw_zenoh
        cuts ``Request_``/``Response_`` off its request's or response's type name, and the hash is the
        service type support's (request, response and event), not the request's."""
        return ros2wire.service_key(self.domain, self.ros2_name(name), ros2types.dds_type_name(srv_type),
                                    ros2types.type_hash(srv_type))

    def action(self, name: str, action_type: str) -> ActionKeys:
        """The keys of ROS 2 action ``name`` (relative or absolute) of type ``action_type``
        (``control_msgs/action/FollowJointTrajectory``): three services and two topics under
        ``<name>/_action/`` (rcl_action's names)."""
        full = self.ros2_name(name)
        return ActionKeys(
            name=full,
            action_type=action_type,
            send_goal=self.ros2_service(f"{full}/_action/send_goal", f"{action_type}_SendGoal"),
            cancel_goal=self.ros2_service(f"{full}/_action/cancel_goal", CANCEL_GOAL_SERVICE),
            get_result=self.ros2_service(f"{full}/_action/get_result", f"{action_type}_GetResult"),
            feedback=self._ros2_topic(f"{full}/_action/feedback", f"{action_type}_FeedbackMessage"),
            status=self._ros2_topic(f"{full}/_action/status", GOAL_STATUS_ARRAY),
        )

    def _ros2_topic(self, full_name: str, msg_type: str) -> str:
        return ros2wire.topic_key(self.domain, full_name, ros2types.dds_type_name(msg_type),
                                  ros2types.type_hash(msg_type))


# ==================================================================== ROS 2 services and actions (rmw_zenoh)
# An action <name> of type <pkg>/action/<A> is, as rcl_action names its parts and rmw_zenoh keys them:
#   services <name>/_action/send_goal (<A>_SendGoal), <name>/_action/cancel_goal (action_msgs/srv/CancelGoal),
#            <name>/_action/get_result (<A>_GetResult): queryables, Keys.ros2_service;
#   topics   <name>/_action/feedback (<A>_FeedbackMessage), <name>/_action/status (action_msgs/msg/GoalStatusArray).
CANCEL_GOAL_SERVICE = "action_msgs/srv/CancelGoal"
GOAL_STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"


@dataclass(frozen=True)
class ActionKeys:
    """The keys of one ROS 2 action (:meth:`Keys.action`); ``name`` is its full ROS 2 name."""

    name: str
    action_type: str
    send_goal: str
    cancel_goal: str
    get_result: str
    feedback: str
    status: str


# The topics of the robot's own actions under their default names, so that keys.topic() builds them and
# message_type() (the recorder, `hilsim topic echo`) reads them: the controller's FollowJointTrajectory
# (controller.params.action_ns) and the planner's move action. A key is read by its type chunk, so
# renamed actions are read all the same.
ACTION_TABLE: dict[str, Topic] = {
    "follow_joint_trajectory/_action/feedback": _row(msgs.FollowJointTrajectoryFeedbackMessage, "controller"),
    "follow_joint_trajectory/_action/status": _row(msgs.GoalStatusArray, "controller"),
    "move/_action/feedback": _row(msgs.MoveFeedbackMessage, "planner"),
    "move/_action/status": _row(msgs.GoalStatusArray, "planner"),
}
ACTION_TOPICS: dict[str, type] = {t: row.cls for t, row in ACTION_TABLE.items()}
TOPIC_TABLE.update(ACTION_TABLE)
TOPICS.update(ACTION_TOPICS)
# The ROS 2 actions hilsim's services serve (hilsim.services.ros2_action): action type -> server. Its
# three services are asked by USER; its feedback and status written by the server. Keyed by type, not
# name: a renamed action (controller.params.action_ns) is the same server's.
ACTION_SERVERS: dict[str, str] = {
    "control_msgs/action/FollowJointTrajectory": "controller",
    "hilsim_msgs/action/Move": "planner",
}


def topic_name(key: str) -> str:
    """The ROS 2 topic name of a data key: ``0/arm/joint_states/<type>/<hash>`` -> ``/arm/joint_states``."""
    parts = key.split("/")
    if len(parts) < 4 or not parts[-1].startswith("RIHS"):
        raise UnknownKey(f"{key!r} is not a ROS 2 data key (<domain>/<topic>/<type>/<hash>)")
    return "/" + "/".join(parts[1:-2])


def robot_of(key: str, namespace_template: str = DEFAULT_NAMESPACE) -> str | None:
    """The robot whose namespace a key is in (default namespaces ``/<robot>``); None for ``/clock``."""
    name = topic_name(key).strip("/").split("/")
    fixed = [p for p in namespace_template.strip("/").split("/") if p]
    i = fixed.index("{robot}") if "{robot}" in fixed else 0
    return name[i] if len(name) > i + 1 else None


def relative_topic(key: str, namespace_template: str = DEFAULT_NAMESPACE) -> str:
    """A key's topic below its robot's namespace (``truth/joint_states``); ``clock`` for ``/clock``."""
    name = topic_name(key).strip("/").split("/")
    depth = len([p for p in namespace_template.strip("/").split("/") if p])
    return "/".join(name[depth:]) if len(name) > depth else "/".join(name)


def given_once(key: str, namespace_template: str = DEFAULT_NAMESPACE) -> bool:
    """Whether a data key's samples are each given once: its key table row's ``once``; outside the table
    (a plug-in's topic) a ``…/result`` (a goal's result: its waiters, launchers on every host and clients,
    cannot do without it; seen lost on a congested link to another host when dropped); False for any
    other key (streams, per-service keys, keys outside the scheme)."""
    try:
        topic = relative_topic(key, namespace_template)
    except UnknownKey:
        return False
    row = TOPIC_TABLE.get(topic)
    return row.once if row is not None else topic.endswith("/result")


def message_type(key: str) -> type:
    """Message type carried by a concrete data key (any domain and robot), read from its type chunk."""
    parts = key.split("/")
    if len(parts) >= 4:
        try:
            name = ros2wire.ros_type_name(parts[-2])
        except ValueError:
            name = ""
        cls = classes_by_type().get(name)
        if cls is not None:
            return cls
    raise UnknownKey(f"{key!r} is not a hilsim data key")
