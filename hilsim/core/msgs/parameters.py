"""Parameters (live controller gains): a SetParameters request and its result."""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import float64, sequence


@dataclass
class Parameter(IdlStruct, typename="hilsim_msgs/msg/Parameter"):
    """A named float parameter, e.g. ``joint_2.kp``."""

    name: str = ""
    value: float64 = 0.0


@dataclass
class SetParameters(IdlStruct, typename="hilsim_msgs/srv/SetParameters_Request"):
    parameters: sequence[Parameter] = field(default_factory=list)


@dataclass
class SetParametersResult(IdlStruct, typename="rcl_interfaces/msg/SetParametersResult"):
    successful: bool = False
    reason: str = ""
