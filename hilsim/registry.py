"""Services and device backends, picked by name and imported only when chosen."""

from __future__ import annotations

import importlib
from typing import Any

# service name -> "module:Class"; a bridge replaces the simulated device under the same name.
SERVICES: dict[str, str] = {
    "physics": "hilsim.services.physics:PhysicsService",
    "sensors": "hilsim.services.sensors:SensorService",
    "controller": "hilsim.services.controller:ControllerService",
    "planner": "hilsim.services.planner:PlannerService",
    "logger": "hilsim.services.logger:LoggerService",
}


class UnknownService(LookupError):
    pass


def load(table: dict[str, str], name: str, what: str) -> Any:
    try:
        target = table[name]
    except KeyError:
        raise UnknownService(f"unknown {what} {name!r}; available: {', '.join(sorted(table))}") from None
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def service_class(name: str) -> Any:
    return load(SERVICES, name, "service")
