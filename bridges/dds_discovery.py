"""Where the ROS 2 DDS bridge looks for peers: as a ROS 2 node of the same machine would.

ROS 2 (Iron and later) says how far a node's discovery reaches with two environment variables that every
RMW honours, and the bridge honours them the same way (with Cyclone DDS, as rmw_cyclonedds does):

- ``ROS_AUTOMATIC_DISCOVERY_RANGE``: ``SUBNET`` (the default, also when unset or ``SYSTEM_DEFAULT``) —
  Cyclone's own defaults: its preferred interface and multicast discovery on 239.255.0.1, which is what a
  node on Fast DDS or Cyclone DDS with default settings does, so the bridge and the lab's nodes find each
  other; ``LOCALHOST`` — this machine only: interface ``lo``, no multicast, discovery by unicast to the
  participant ports on 127.0.0.1 (what nodes started with the same setting find); ``OFF`` — no
  automatic discovery, only the static peers.
- ``ROS_STATIC_PEERS``: semicolon-separated addresses always asked, whatever the range.

``CYCLONEDDS_URI``, when set, is the lab's own Cyclone configuration and wins over both.

Whatever the discovery, the domain is made with :data:`TYPE_MATCHING` too: Cyclone's permission for the
XTypes type objects Fast DDS writes (collection elements without a try-construct flag,
:mod:`hilsim.bridges.dds_types`), which the bridge announces so that Fast DDS 3 matches it; and, towards
other Cyclone DDS participants (vendor 1.16), matching by type name, as rmw_cyclonedds does (it gives
Cyclone no type information): Cyclone's own assignability check does not take Fast DDS's type objects.

A note for this project's own machine: DDS with default settings multicasts on the machine's LAN
interface, so every test that runs the bridge runs it inside a network namespace of its own.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from hilsim.core.config import ConfigError

RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
#: merged over every configuration (Cyclone takes a comma-separated list of configurations)
TYPE_MATCHING = ('<CycloneDDS><Domain Id="any"><Compatibility><AllowInvalidTryConstruct>true'
                 "</AllowInvalidTryConstruct><IgnoreTypeInformation>1.16</IgnoreTypeInformation></Compatibility>"
                 "</Domain></CycloneDDS>")


@dataclass(frozen=True)
class Discovery:
    """The Cyclone configuration the bridge's domain is made with (``xml``: Cyclone's list of configurations,
    the last one winning), and what to say about it in the log and health."""

    xml: str
    said: str


def discovery(env: Mapping[str, str] | None = None) -> Discovery:
    """The bridge's discovery from the environment (``os.environ`` by default), or a one-line ConfigError."""
    env = os.environ if env is None else env
    uri = env.get("CYCLONEDDS_URI", "").strip()
    if uri:
        return Discovery(f"{uri},{TYPE_MATCHING}", "CYCLONEDDS_URI")
    rng = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper() or "SUBNET"
    if rng not in RANGES:
        raise ConfigError(f"ROS_AUTOMATIC_DISCOVERY_RANGE={env['ROS_AUTOMATIC_DISCOVERY_RANGE']!r}: expected one of "
                          f"{', '.join(RANGES)} (as for every ROS 2 node)")
    peers = [p.strip() for p in env.get("ROS_STATIC_PEERS", "").split(";") if p.strip()]
    peer_xml = "".join(f"<Peer address={quoteattr(p)}/>" for p in peers)
    said = f"ROS_AUTOMATIC_DISCOVERY_RANGE={rng}" + (f", ROS_STATIC_PEERS={';'.join(peers)}" if peers else "")
    if rng in ("SUBNET", "SYSTEM_DEFAULT"):
        if not peers:
            return Discovery(TYPE_MATCHING, said + " (Cyclone's defaults: multicast discovery on its interface)")
        general, disc = "", f"<Peers>{peer_xml}</Peers>"
    elif rng == "LOCALHOST":
        general = ('<Interfaces><NetworkInterface name="lo"/></Interfaces>'
                   "<AllowMulticast>false</AllowMulticast>")
        disc = ("<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>"
                f'<Peers><Peer address="127.0.0.1"/>{peer_xml}</Peers>')
    else:  # OFF
        general = "<AllowMulticast>false</AllowMulticast>"
        disc = f"<ParticipantIndex>auto</ParticipantIndex><Peers>{peer_xml}</Peers>" if peers else \
            "<ParticipantIndex>none</ParticipantIndex>"
    xml = (f'<CycloneDDS><Domain Id="any"><General>{general}</General><Discovery>{disc}</Discovery>'
           "</Domain></CycloneDDS>")
    return Discovery(f"{xml},{TYPE_MATCHING}", said)
