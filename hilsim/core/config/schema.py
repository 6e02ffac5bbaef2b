"""The scenario itself: its top-level fields, one section per concern (the modules beside this one), the checks
across sections, and what the launcher and the services ask of it (processes, units, rates); and the one
message of a scenario that needs the wall clock (:func:`require_realtime`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationInfo, field_validator, model_validator

from hilsim.core import fleet
from hilsim.core.config.base import DEFAULT_SERVICES, SIM, _Model, known_services
from hilsim.core.config.clock import ClockConfig
from hilsim.core.config.errors import ConfigError
from hilsim.core.config.network import Ros2Config, ZenohConfig
from hilsim.core.config.processes import FleetConfig, RestartConfig
from hilsim.core.config.recorder import LoggerConfig
from hilsim.core.config.robot import ControllerConfig, JointConfig, PhysicsConfig, SensorConfig, WorldConfig
from hilsim.core.config.task import PlannerConfig, TaskConfig


class Scenario(_Model):
    """A scenario. Besides the fields below, a top-level section named after a service (e.g.
    ``motor-model:``) holds that service's own settings; its class validates them."""

    model_config = ConfigDict(extra="allow", validate_assignment=True)
    name: str
    robot: str = "arm"
    robots: int = Field(1, ge=1, le=64, description="copies of the robot, side by side in one world: "
                        "robots <robot>0 … <robot>N-1, each under its own key namespace (hilsim.core.fleet)")
    robot_spacing: list[float] = Field(
        default_factory=lambda: [0.0, 1.5, 0.0], min_length=3, max_length=3,
        description="robots > 1: offset [m] of each copy of the world model from the previous one",
    )
    robot_overrides: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="robots > 1: per robot (arm0, …), its own settings as dotted fields under "
                    "task, controller, planner or sensors, e.g. {arm1: {task.targets: [[…]]}}",
    )
    prefix: str = "hilsim"
    seed: int = 0
    duration: float | None = Field(None, gt=0, description="sim seconds; None = until the task ends")
    services: list[str] = Field(default_factory=lambda: list(DEFAULT_SERVICES))
    compose: list[list[str]] = Field(
        default_factory=list,
        description="groups of services run in one process each, e.g. [[physics, sensors, controller]]",
    )
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    clock: ClockConfig = Field(default_factory=ClockConfig)
    world: WorldConfig
    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)
    joints: dict[str, JointConfig] = Field(
        default_factory=dict, description="per joint name, or 'default' for the others: interface and server"
    )
    sensors: dict[str, SensorConfig] = Field(default_factory=dict)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    task: TaskConfig = Field(default_factory=TaskConfig)
    logger: LoggerConfig = Field(default_factory=LoggerConfig)
    ros2: Ros2Config = Field(default_factory=Ros2Config)
    fleet: FleetConfig = Field(default_factory=FleetConfig)
    restart: RestartConfig = Field(default_factory=RestartConfig)
    source: Path | None = Field(None, exclude=True, description="file this came from")
    fleet_member: bool = Field(False, exclude=True, description="set by hilsim.core.fleet: one robot's view of a "
                               "scenario with robots > 1 (its files in the run directory carry its name)")

    @field_validator("prefix", "robot")
    @classmethod
    def _key_safe(cls, v: str) -> str:
        if not v or any(c in v for c in "/*?#$ "):
            raise ValueError("must be a non-empty name without '/', '*', '?', '#', '$' or spaces")
        return v

    @field_validator("services")
    @classmethod
    def _known_services(cls, v: list[str], info: ValidationInfo) -> list[str]:
        known = known_services(info)
        for s in v:
            if known is not None and s not in known:
                raise ValueError(f"unknown service {s!r}; available: {', '.join(known)}")
        if len(set(v)) != len(v):
            raise ValueError("a service is listed twice")
        return v

    @model_validator(mode="after")
    def _recorder_off(self) -> Scenario:
        if not self.logger.enabled and "logger" in self.services:  # the same as `hilsim up --no-logger`
            self.services = [s for s in self.services if s != "logger"]
        return self

    @model_validator(mode="after")
    def _fleet(self) -> Scenario:
        if self.robots > 1 and self.external_servers():
            raise ValueError(f"robots: {self.robots} robots need every joint served by sim "
                             f"(external servers: {', '.join(self.external_servers())})")
        names = fleet.robot_names(self)
        for robot, over in self.robot_overrides.items():
            if self.robots == 1 or robot not in names:
                raise ValueError(f"robot_overrides.{robot}: no such robot (robots: {', '.join(names)}; "
                                 f"overrides need robots > 1)")
            for field in over:
                if field.split(".")[0] not in fleet.OVERRIDABLE:
                    raise ValueError(f"robot_overrides.{robot}.{field}: a robot may change only fields under "
                                     f"{', '.join(fleet.OVERRIDABLE)} (the world and clock are shared)")
        # a bad value in an override is said by the loader (hilsim.core.scenario), which builds each robot's view
        return self

    @model_validator(mode="after")
    def _drives(self) -> Scenario:
        for name in self.joints:
            j = self.joint(name)
            if j.drive is None:
                continue
            if j.server != SIM:
                raise ValueError(f"joints.{name}.drive: a simulated drive is physics' (server: sim), but the joint's "
                                 f"server is {j.server!r}")
            if j.interface == "effort":
                raise ValueError(f"joints.{name}.drive: a simulated drive takes a position or velocity setpoint "
                                 f"(interface: position or velocity), not effort")
        return self

    @model_validator(mode="after")
    def _compose_groups(self) -> Scenario:
        seen: set[str] = set()
        base = self._base_processes()
        for i, g in enumerate(self.compose):
            for s in g:
                if s not in base:
                    raise ValueError(f"compose[{i}]: {s!r} is not one of this scenario's services "
                                     f"({', '.join(base)})")
                if s in seen:
                    raise ValueError(f"compose[{i}]: {s!r} is in two groups")
                seen.add(s)
            if len(g) < 2:
                raise ValueError(f"compose[{i}]: a group needs at least two services, got {g}")
        return self

    @model_validator(mode="after")
    def _service_sections(self, info: ValidationInfo) -> Scenario:
        known = known_services(info)
        if known is None:
            return self
        for k in self.model_extra or {}:
            if k not in known:
                raise ValueError(f"unknown field {k!r} (not a scenario field, nor a service's section; "
                                 f"services: {', '.join(known)})")
        return self

    def joint(self, name: str) -> JointConfig:
        """The interface and server of a joint: the fields its own entry sets, over ``default``'s,
        over effort/sim."""
        base = self.joints.get("default") or JointConfig()
        own = self.joints.get(name)
        if own is None:
            return base
        return base.model_copy(update={f: getattr(own, f) for f in own.model_fields_set})

    def served_by(self, server: str) -> list[str]:
        """The joints ``server`` serves, named one by one in ``joints`` (one-line ConfigError if
        it serves none, or is the server of ``default``: it must know its joints by name)."""
        where = self.source or "scenario"
        if self.joint("default").server == server:
            raise ConfigError(f"{where}: joints.default.server: name the joints {server} serves one by one")
        mine = [n for n in self.joints if n != "default" and self.joint(n).server == server]
        if not mine:
            raise ConfigError(f"{where}: joints: no joint has server: {server}, so {server} has nothing to serve")
        return mine

    def external_servers(self) -> list[str]:
        """External joint servers named in ``joints`` (in order of first mention)."""
        out: list[str] = []
        for j in self.joints.values():
            if j.server != SIM and j.server not in out:
                out.append(j.server)
        return out

    def _base_processes(self) -> list[str]:
        return [*self.services, *(s for s in self.external_servers() if s not in self.services)]

    def processes(self) -> list[str]:
        """Every service this scenario runs: ``services`` plus the external joint servers. With
        ``robots`` > 1, a per-robot service once per robot, as ``<service>@<robot>`` (hilsim.core.fleet)."""
        return fleet.expand_processes(self, self._base_processes())

    def launch_units(self) -> list[str]:
        """The OS processes ``hilsim up`` starts: one per service, except the services of a
        ``compose`` group, which share one named ``a+b+c`` (:mod:`hilsim.launch.compose`). With
        ``robots`` > 1, a per-robot service's unit is ``<service>@*``: one process serving every robot."""
        procs = self._base_processes()
        grouped = {s: "+".join(m for m in g if m in procs) for g in self.compose for s in g}
        if self.robots > 1:
            return [fleet.fleet_unit(u) for u in self._units(procs, grouped)]
        return self._units(procs, grouped)

    def _units(self, procs: list[str], grouped: dict[str, str]) -> list[str]:
        out: list[str] = []
        for s in procs:
            unit = grouped.get(s, s)
            if unit not in out:
                out.append(unit)
        return out

    def section(self, name: str) -> dict[str, Any]:
        """Raw settings of a plug-in or server section (validated by the service that owns it)."""
        v = (self.model_extra or {}).get(name, {})
        return v if isinstance(v, dict) else {}

    @model_validator(mode="after")
    def _control_rate(self) -> Scenario:
        steps = 1.0 / (self.controller.rate_hz * self.clock.dt)
        if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
            raise ValueError(
                f"controller.rate_hz ({self.controller.rate_hz}) must divide "
                f"the physics rate ({1 / self.clock.dt:g} Hz)"
            )
        return self

    @model_validator(mode="after")
    def _planner_rate(self) -> Scenario:
        ratio = self.controller.rate_hz / self.planner.rate_hz
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ValueError(
                f"planner.rate_hz ({self.planner.rate_hz:g}) must divide controller.rate_hz "
                f"({self.controller.rate_hz:g}): the planner decides on joint_states of its own steps"
            )
        return self

    @property
    def planner_decimation(self) -> int:
        """Physics steps per planner decision (the planner acknowledges only those steps)."""
        return round(1.0 / (self.planner.rate_hz * self.clock.dt))

    def planner_tick(self, t_ns: int) -> bool:
        """Whether the step at sim time ``t_ns`` is one the planner decides on (and the sensors'
        ``joint_states_throttle`` carries)."""
        return (t_ns // self.dt_ns) % self.planner_decimation == 0

    @property
    def dt_ns(self) -> int:
        return round(self.clock.dt * 1e9)

    @property
    def control_decimation(self) -> int:
        return round(1.0 / (self.controller.rate_hz * self.clock.dt))

    def dump(self) -> dict[str, Any]:
        return self.model_dump(mode="json", exclude={"source"})


def require_realtime(sc: Scenario, field: str, why: str, where: str | Path | None = None) -> None:
    """Hardware (a drive, a GPS, an autopilot, an external joint server) lives on the wall clock and cannot wait
    for a lockstep step: a scenario that puts one in lockstep is refused in one line, the same for every kind
    (``field``: the field that brings the hardware in; ``why``: what it is, e.g. ``bridge-mavlink talks to a
    device on the wall clock``)."""
    if sc.clock.mode != "realtime":
        raise ConfigError(f"{where or sc.source or 'scenario'}: {field}: {why}, so the scenario needs clock.mode: "
                          f"realtime (got {sc.clock.mode!r}; pass --clock realtime)")
