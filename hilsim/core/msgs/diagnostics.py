"""diagnostic_msgs (service health) and rcl_interfaces/Log (service logs)."""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import sequence, uint8, uint32

from hilsim.core.msgs.builtin import Header, Time


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs/msg/KeyValue"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs/msg/DiagnosticStatus"):
    level: uint8 = 0  # OK=0 WARN=1 ERROR=2 STALE=3
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs/msg/DiagnosticArray"):
    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


@dataclass
class Log(IdlStruct, typename="rcl_interfaces/msg/Log"):
    stamp: Time = field(default_factory=Time)
    level: uint8 = 20  # DEBUG=10 INFO=20 WARN=30 ERROR=40 FATAL=50
    name: str = ""
    msg: str = ""
    file: str = ""
    function: str = ""
    line: uint32 = 0
