"""A DDS participant as a ROS 2 graph sees it: where ``ros2 node list`` finds the bridge's node.

A ROS 2 node on DDS is no DDS entity: every RMW on DDS (rmw_fastrtps, rmw_cyclonedds, rmw_connextdds)
publishes, per participant, one ``rmw_dds_common/msg/ParticipantEntitiesInfo`` on the topic
``ros_discovery_info`` (reliable, transient local, keep-last 1): the participant's gid and, per node,
its namespace, name and the gids of its readers and writers. A gid is the entity's DDS GUID (12 bytes
of prefix, 4 of entity id). rclpy's ``get_node_names_and_namespaces()`` lists those nodes, and
``get_publishers_info_by_topic()`` names each endpoint's node from them; an endpoint of a participant
that publishes none is ``_CREATED_BY_BARE_DDS_APP_``.

Writes (DDS): ``ros_discovery_info`` (rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_).
"""

from __future__ import annotations

from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from hilsim.bridges.dds_types import dds_struct, user_data

TOPIC = "ros_discovery_info"
TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"


def participant_user_data(enclave: str) -> bytes:
    """A ROS 2 participant's USER_DATA: ``enclave=<enclave>;`` (the RMWs add a participant to the graph by it)."""
    return f"enclave={enclave or '/'};".encode()


def gid(entity: Any) -> bytes:
    """An entity's ROS 2 gid: its DDS GUID, 16 bytes."""
    return entity.guid.bytes


def entities_info(participant: bytes, nodes: list[tuple[str, str, list[bytes], list[bytes]]]) -> Any:
    """The ParticipantEntitiesInfo of a participant's nodes: (namespace, name, reader gids, writer gids) each."""
    gid_t = dds_struct("rmw_dds_common/msg/Gid")
    node_t = dds_struct("rmw_dds_common/msg/NodeEntitiesInfo")
    return dds_struct(TYPE)(
        gid=gid_t(data=list(participant)),
        node_entities_info_seq=[node_t(node_namespace=ns, node_name=name,
                                       reader_gid_seq=[gid_t(data=list(g)) for g in readers],
                                       writer_gid_seq=[gid_t(data=list(g)) for g in writers])
                                for ns, name, readers, writers in nodes])


class GraphAnnouncer:
    """The participant's ``ros_discovery_info`` writer: :meth:`announce` (again whenever its endpoints change)."""

    def __init__(self, participant: Any) -> None:
        self.participant = participant
        policies = [Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.TransientLocal,
                    Policy.History.KeepLast(1), Policy.DataRepresentation(use_cdrv0_representation=True)]
        self.topic = Topic(participant, TOPIC, dds_struct(TYPE), qos=Qos(*policies))
        # USER_DATA is an endpoint's policy, not a topic's
        self.writer = DataWriter(participant, self.topic, qos=Qos(*policies, Policy.Userdata(user_data(TYPE))))

    def announce(self, nodes: list[tuple[str, str, list[Any], list[Any]]]) -> None:
        """Publish this participant's nodes: (namespace, name, readers, writers) each."""
        self.writer.write(entities_info(gid(self.participant), [
            (ns, name, [gid(r) for r in readers], [gid(w) for w in writers])
            for ns, name, readers, writers in nodes]))
