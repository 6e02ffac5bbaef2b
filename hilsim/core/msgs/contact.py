"""Contacts in the physics truth (``hilsim_msgs/msg/Contacts``), like gazebo_msgs/ContactsState:
which geoms of which bodies touch, where, and how deep."""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import float64, sequence

from hilsim.core.msgs.builtin import Header
from hilsim.core.msgs.geometry import Point


@dataclass
class Contact(IdlStruct, typename="hilsim_msgs/msg/Contact"):
    body1: str = ""
    body2: str = ""
    geom1: str = ""
    geom2: str = ""
    position: Point = field(default_factory=Point)  # world frame [m]
    depth: float64 = 0.0  # penetration [m]; negative: within the contact margin, not touching


@dataclass
class Contacts(IdlStruct, typename="hilsim_msgs/msg/Contacts"):
    """Every contact at ``header.stamp`` (an empty list: nothing touches)."""

    header: Header = field(default_factory=Header)
    contacts: sequence[Contact] = field(default_factory=list)
