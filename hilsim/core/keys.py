"""The key scheme: the one place that spells Zenoh keys and says which message type each carries.

Every key is ``<prefix>/<robot>/<topic>`` (prefix ``hilsim`` by default, so several
simulations can share a network by choosing different prefixes), except sim time, which
is ``<prefix>/clock``. Ground truth lives under ``<prefix>/<robot>/truth/…``.
``docs/keys.md`` documents the same table for people; ``TOPICS`` below is the table for code,
extended by other packages through the ``hilsim.topics`` entry-point group (:func:`plugin_topics`).

No other module builds a key string by hand: services ask a :class:`Keys` instance.
"""

from __future__ import annotations

from dataclasses import dataclass

from hilsim.core import msgs

DEFAULT_PREFIX = "hilsim"

# topic -> message type. Topics are relative to <prefix>/<robot>/ unless listed in GLOBAL_TOPICS.
TOPICS: dict[str, type] = {
    "joint_states": msgs.JointState,
    "joint_commands": msgs.JointState,
    "joint_trajectory": msgs.JointTrajectory,
    "controller/reference": msgs.JointState,
    "imu": msgs.Imu,
    "gps/fix": msgs.NavSatFix,
    "scan": msgs.LaserScan,
    "cmd_vel": msgs.Twist,
    "odom": msgs.Odometry,
    "tf": msgs.TFMessage,
    "truth/joint_states": msgs.JointState,
    "truth/imu": msgs.Imu,
    "truth/odom": msgs.Odometry,
    "truth/contacts": msgs.Contacts,
    "planner/path": msgs.JointTrajectory,
    "planner/feedback": msgs.MoveFeedback,
    "planner/result": msgs.MoveResult,
    "task/result": msgs.MoveResult,
    "map": msgs.OccupancyGrid,
    "plan": msgs.Path,
    "navigator/feedback": msgs.MoveFeedback,
    "navigator/result": msgs.MoveResult,
}
# Keys whose last segment is a service name.
PER_SERVICE_TOPICS: dict[str, type] = {
    "health": msgs.DiagnosticArray,
    "sync": msgs.Clock,
    "log": msgs.Log,
}
# Keys <prefix>/<robot>/hw/<server>/<topic>: what an external joint server (a bridge, the motor
# model) publishes. One key per server, so each has exactly one writer.
SERVER_TOPICS: dict[str, type] = {"joint_states": msgs.JointState}
GLOBAL_TOPICS: dict[str, type] = {"clock": msgs.Clock}

# Queryables (request/reply): topic -> (request type, reply type).
SERVICES: dict[str, tuple[type, type]] = {
    "planner/goal": (msgs.MoveGoal, msgs.GoalResponse),
    "planner/cancel": (msgs.CancelRequest, msgs.GoalResponse),
    "navigator/goal": (msgs.MoveGoal, msgs.GoalResponse),
    "navigator/cancel": (msgs.CancelRequest, msgs.GoalResponse),
    "controller/set_parameters": (msgs.SetParameters, msgs.SetParametersResult),
}


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


@dataclass(frozen=True)
class Keys:
    """Builds the keys of one robot in one simulation."""

    prefix: str = DEFAULT_PREFIX
    robot: str = "arm"

    def topic(self, name: str) -> str:
        if name not in TOPICS and name not in SERVICES and name not in plugin_topics():
            known = sorted([*TOPICS, *plugin_topics()])
            raise UnknownKey(f"unknown topic {name!r}; known: {', '.join(known)}")
        return f"{self.prefix}/{self.robot}/{name}"

    @property
    def clock(self) -> str:
        return f"{self.prefix}/clock"

    def truth(self, name: str) -> str:
        return self.topic(f"truth/{name}")

    def health(self, service: str) -> str:
        return f"{self.prefix}/{self.robot}/health/{service}"

    def sync(self, service: str) -> str:
        """Lockstep acknowledgement of a participant: a Clock stamped with the step it finished."""
        return f"{self.prefix}/{self.robot}/sync/{service}"

    def log(self, service: str) -> str:
        return f"{self.prefix}/{self.robot}/log/{service}"

    def alive(self, service: str) -> str:
        """Liveliness token of a running service (no payload)."""
        return f"{self.prefix}/{self.robot}/alive/{service}"

    def server_state(self, server: str) -> str:
        """Measured state of the joints an external server serves (sensor_msgs/JointState)."""
        return f"{self.prefix}/{self.robot}/hw/{server}/joint_states"

    @property
    def all_server_states(self) -> str:
        return f"{self.prefix}/{self.robot}/hw/*/joint_states"

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

    def writer(self, gid: bytes, key: str) -> str:
        """Liveliness token of a publisher: writer ``gid`` writes ``key`` (a key under this prefix)."""
        rest = key[len(self.prefix) + 1:] if key.startswith(f"{self.prefix}/") else key
        return f"{self.prefix}/writers/{gid.hex()}/{rest}"

    @property
    def all_writers(self) -> str:
        return f"{self.prefix}/writers/**"

    def scoped(self, expr: str) -> str:
        """A key expression under this simulation's prefix, e.g. ``scoped("**")``."""
        return f"{self.prefix}/{expr}"

    @property
    def everything(self) -> str:
        """Wildcard matching every key of the simulation (all robots, the clock, liveliness)."""
        return self.scoped("**")


def message_type(key: str) -> type:
    """Message type carried by a concrete key of the scheme (any prefix and robot)."""
    parts = key.split("/")
    if len(parts) == 2 and parts[1] in GLOBAL_TOPICS:
        return GLOBAL_TOPICS[parts[1]]
    if len(parts) >= 3:
        rest = "/".join(parts[2:])
        if rest in TOPICS:
            return TOPICS[rest]
        if rest in plugin_topics():
            return plugin_topics()[rest]
        if len(parts) == 4 and parts[2] in PER_SERVICE_TOPICS:
            return PER_SERVICE_TOPICS[parts[2]]
        if len(parts) == 5 and parts[2] == "hw" and parts[4] in SERVER_TOPICS:
            return SERVER_TOPICS[parts[4]]
    raise UnknownKey(f"{key!r} is not a hilsim data key")
