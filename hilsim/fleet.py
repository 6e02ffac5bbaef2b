"""Many robots in one scenario: ``robots: N`` puts N copies of the world model side by side.

A scenario with ``robots: 8`` (and ``robot: arm``) runs robots ``arm0`` … ``arm7``:

- physics loads the world model (``world.model``: the arm *and* its table and obstacle, one work
  cell) N times into one MuJoCo world, copy k moved by k × ``robot_spacing`` and its names
  prefixed ``arm<k>/`` (MuJoCo's ``MjSpec.attach``); one clock, one ``mj_step`` for all;
- each robot's keys are its own namespace, ``<prefix>/arm<k>/…`` (``truth/joint_states``,
  ``joint_commands``, ``joint_states``, ``task/result``, …), with the joint names of the single
  robot (``joint_1`` …), so its sensors, controller and planner are the single robot's code, run
  with a copy of the scenario whose ``robot`` is ``arm<k>`` (:func:`robot_scenario`); every robot
  gets the scenario's task (the same joint targets: each stands in its own copy of the cell),
  unless ``robot_overrides: {arm1: {task.targets: […]}}`` gives it its own; robot k's sensors
  are seeded ``seed + k``;
- physics and the recorder serve the whole fleet under the scenario's own namespace
  (``<prefix>/arm/health/physics``); sim time stays ``<prefix>/clock``.

Services are named per robot ``<service>@<robot>`` (``controller@arm3``: its keys are under
``<prefix>/arm3/``); ``hilsim up`` starts one process per service *kind*, ``controller@*``,
serving every robot in threads that hand each other messages as a composed process does
(:mod:`hilsim.compose`), so 8 arms take as many processes as one. ``hilsim run controller@arm3``
runs one robot's controller alone (e.g. on another machine).

With ``robots: 1`` (the default) nothing of this applies: the robot is ``<robot>`` itself and
every key, process and result is what it always was.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np
from pydantic import ValidationError

if TYPE_CHECKING:
    from hilsim.config import Scenario
    from hilsim.service import Service
    from hilsim.world import World

# the sections a robot may have its own values of (robot_overrides); the world and clock are shared
OVERRIDABLE = ("task", "controller", "planner", "sensors")
FLEET_WIDE = ("physics", "logger")  # one for the whole fleet; every other service runs per robot
ALL = "*"  # <service>@*: the service of every robot, in one process


def robot_names(sc: Scenario) -> list[str]:
    """The robots of a scenario: its ``robot`` alone, or ``<robot>0`` … ``<robot>N-1``."""
    return [sc.robot] if sc.robots == 1 else [f"{sc.robot}{k}" for k in range(sc.robots)]


def per_robot(service: str) -> bool:
    return service not in FLEET_WIDE


def expand_processes(sc: Scenario, base: list[str]) -> list[str]:
    """``processes()`` of a scenario: base names, per-robot ones once per robot when robots > 1."""
    if sc.robots == 1:
        return list(base)
    out: list[str] = []
    for s in base:
        out.extend([f"{s}@{r}" for r in robot_names(sc)] if per_robot(s) else [s])
    return out


def fleet_unit(unit: str) -> str:
    """A launch unit of a fleet: its per-robot members as ``<service>@*``."""
    return "+".join(f"{m}@{ALL}" if per_robot(m) and "@" not in m else m for m in unit.split("+"))


def members(sc: Scenario, unit: str) -> list[str]:
    """The service instances of a launch unit (``a+b@*`` -> ``a, b@arm0, b@arm1, …``)."""
    out: list[str] = []
    for m in unit.split("+"):
        svc, robot = split_id(m)
        out.extend([f"{svc}@{r}" for r in robot_names(sc)] if robot == ALL else [m])
    return out


def split_id(name: str) -> tuple[str, str | None]:
    """``controller@arm3`` -> (``controller``, ``arm3``); ``physics`` -> (``physics``, None)."""
    svc, _, robot = name.partition("@")
    return svc, robot or None


def service_id(sc: Scenario, key: str, kind: str) -> str:
    """Who a key ``<prefix>/<ns>/<kind>/<service>[/…]`` belongs to: ``<service>`` in the
    scenario's own namespace, ``<service>@<ns>`` in a robot's."""
    parts = key.split("/")
    i = parts.index(kind, 2)
    ns, svc = parts[1], parts[i + 1]
    return svc if ns == sc.robot else f"{svc}@{ns}"


def robot_scenario(sc: Scenario, robot: str) -> Scenario:
    """The scenario as one robot of the fleet sees it: ``robot`` is its name, a single robot,
    seed ``seed + k`` for robot k (its sensors' noise is its own), its ``robot_overrides`` applied."""
    from hilsim.config import ConfigError, Scenario, _merge, format_error, set_dotted

    names = robot_names(sc)
    if robot not in names:
        raise ConfigError(f"{sc.source or 'scenario'}: robots: no robot {robot!r} (robots: {', '.join(names)})")
    if sc.robots == 1:
        return sc
    own = {"robot": robot, "robots": 1, "seed": sc.seed + names.index(robot), "robot_overrides": {},
           "fleet_member": True}
    over = sc.robot_overrides.get(robot)
    if not over:
        return sc.model_copy(update=own, deep=True)  # nothing shared: a robot may change its own (live gains)
    layer: dict[str, object] = {}
    for field, value in over.items():  # dotted (task.targets) or nested (task: {targets: …}) alike
        set_dotted(layer, field, value)
    data = _merge(sc.dump(), layer)
    data.update(own)
    try:
        out = Scenario.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_error(sc.source or "scenario", e, prefix=f"robot_overrides.{robot}")) from None
    out.source, out.fleet_member = sc.source, True  # neither is in the dump
    return out


def instantiate(name: str, sc: Scenario) -> Service:
    """The service instance ``name`` (``physics``, ``controller@arm3``) for scenario ``sc``."""
    from hilsim.registry import service_class

    svc, robot = split_id(name)
    rsc = robot_scenario(sc, robot) if robot else sc
    return service_class(svc, rsc)(rsc)  # type: ignore[no-any-return]


# ------------------------------------------------------------------------------- the world
_OPTION_FIELDS = ("timestep", "integrator", "gravity", "cone", "jacobian", "solver", "iterations",
                  "tolerance", "ls_iterations", "noslip_iterations", "impratio", "wind", "density",
                  "viscosity", "disableflags", "enableflags")


def multiply(cells: list[mujoco.MjSpec], robots: list[str], spacing: list[float]) -> mujoco.MjSpec:
    """One world holding each of ``cells`` (copies of a world model), copy k moved by
    k × ``spacing`` and every name in it prefixed ``<robots[k]>/``. The world's simulation
    options are the first copy's (attaching keeps only the parent's)."""
    world = mujoco.MjSpec()
    world.modelname = f"fleet_{len(robots)}"
    for f in _OPTION_FIELDS:
        setattr(world.option, f, getattr(cells[0].option, f))
    off = np.asarray(spacing, dtype=float)
    for k, (cell, robot) in enumerate(zip(cells, robots, strict=True)):
        frame = world.worldbody.add_frame(pos=(k * off).tolist())
        world.attach(cell, frame=frame, prefix=f"{robot}/")
    return world


class FleetWorld:
    """One MuJoCo world of N robots: a :class:`hilsim.world.World` per robot (its joints, truth
    and commands, names without the prefix) over the shared model and data, stepped together."""

    def __init__(self, sc: Scenario) -> None:
        import warnings

        from hilsim.world import World

        self.sc = sc
        self.robots = robot_names(sc)
        cells = [World.load_spec(sc) for _ in self.robots]
        with warnings.catch_warnings():  # the options are copied over: MuJoCo's notes on them are moot
            warnings.simplefilter("ignore")
            self.model = multiply(cells, self.robots, sc.robot_spacing).compile()
        self.model.opt.timestep = sc.clock.dt
        self.data = mujoco.MjData(self.model)
        self.views: list[World] = [World(sc, model=self.model, data=self.data, prefix=f"{r}/")
                                   for r in self.robots]

    @property
    def step_index(self) -> int:
        return self.views[0].step_index

    @property
    def time_ns(self) -> int:
        return self.views[0].time_ns

    def step(self) -> None:
        for v in self.views:
            v.apply_commands()
        mujoco.mj_step(self.model, self.data)
        for v in self.views:
            v.after_step()

    @property
    def clipped(self) -> int:
        return sum(v.clipped for v in self.views)
