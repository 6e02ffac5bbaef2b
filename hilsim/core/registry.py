"""The one registry: services, bridges, sensors and controllers found by name.

Each kind has a built-in table (name -> ``"module:attr"``) and an entry-point group through
which another installed package adds its own, with no file of hilsim changed::

    [project.entry-points."hilsim.services"]
    my-service = "my_pkg.service:MyService"

Groups: ``hilsim.services`` (services and bridges: anything ``hilsim run NAME`` starts,
including external joint servers), ``hilsim.sensors`` (sensor kinds of the sensor emulator,
by ``type``), ``hilsim.controllers`` (control laws, by ``controller.type``). Planners have
their own library (``config/planners.yaml`` plus the ``hilsim.planners`` group, see
:mod:`hilsim.planning.library`). Names are listed without importing anything; a class is
imported only when chosen. A built-in name wins over an entry point of the same name.
"""

from __future__ import annotations

import importlib
from functools import cache
from importlib.metadata import entry_points
from typing import Any

from hilsim.core.config import ConfigError

GROUPS = {
    "services": "hilsim.services",
    "sensors": "hilsim.sensors",
    "controllers": "hilsim.controllers",
}

BUILTIN: dict[str, dict[str, str]] = {
    "services": {
        "physics": "hilsim.services.physics:PhysicsService",
        "sensors": "hilsim.services.sensors:SensorService",
        "controller": "hilsim.services.controller:ControllerService",
        "planner": "hilsim.services.planner:PlannerService",
        "navigator": "hilsim.services.navigator:NavigatorService",
        "logger": "hilsim.services.logger:LoggerService",
        "motor-model": "hilsim.services.motor_model:MotorModelService",
        "bridge-can": "hilsim.bridges.can_bridge:CanBridgeService",
        "drive-emulator": "hilsim.bridges.drive_emulator:DriveEmulatorService",
        "bridge-mavlink": "hilsim.bridges.mavlink_bridge:MavlinkBridgeService",
        "gps-emulator": "hilsim.bridges.gps_emulator:GpsEmulatorService",
        "bridge-ros2-dds": "hilsim.bridges.ros2_dds:Ros2DdsBridgeService",
    },
    # sensor kinds register themselves in hilsim.sim.sensing (imported when a sensor is built)
    "sensors": {
        "encoder": "hilsim.sim.sensing:Encoder",
        "imu": "hilsim.sim.sensing:ImuSensor",
        "laser": "hilsim.sim.sensors_mobile:Laser",
        "gps": "hilsim.sim.sensors_mobile:Gps",
    },
    "controllers": {
        "joint_trajectory": "hilsim.services.controller:ControllerService",
        "four_wheel_steer": "hilsim.services.rover_controller:FourWheelSteerController",
    },
}


class UnknownName(ConfigError, LookupError):
    """A name that is neither built in nor offered by an installed plug-in."""


UnknownService = UnknownName  # the name the CLI has used


@cache
def _plugins(kind: str) -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=GROUPS[kind])}


def names(kind: str) -> list[str]:
    """Every name of a kind: built in, then plug-ins (sorted), without importing them."""
    builtin = BUILTIN[kind]
    return [*builtin, *sorted(n for n in _plugins(kind) if n not in builtin)]


def load(kind: str, name: str) -> Any:
    """The object registered as ``name`` (imported now); :class:`UnknownName` if there is none."""
    target = BUILTIN[kind].get(name)
    if target is not None:
        module, _, attr = target.partition(":")
        return getattr(importlib.import_module(module), attr)
    ep = _plugins(kind).get(name)
    if ep is None:
        singular = kind.rstrip("s")
        raise UnknownName(f"unknown {singular} {name!r}; available: {', '.join(names(kind))}")
    try:
        return ep.load()
    except Exception as e:  # a broken plug-in is its author's error, said in one line
        raise UnknownName(f"plug-in {name!r} ({ep.value}) cannot be loaded: {type(e).__name__}: {e}") from None


def service_class(name: str, scenario: Any = None) -> Any:
    """The class that runs service ``name``; with a scenario, the one it picks (e.g. the
    controller by ``controller.type``)."""
    cls = load("services", name)
    return cls.resolve(scenario) if scenario is not None and hasattr(cls, "resolve") else cls


def lockstep_participants(scenario: Any) -> dict[str, int]:
    """Services of a scenario that physics will wait for in lockstep, with their periods (steps),
    as their classes declare them (physics itself learns them from their announcements)."""
    out: dict[str, int] = {}
    for name in scenario.processes():
        period = service_class(name.split("@")[0], scenario).lockstep_period(scenario)  # controller@arm3
        if period is not None:
            out[name] = int(period)
    return out
