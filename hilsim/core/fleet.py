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
(:mod:`hilsim.launch.compose`), so 8 arms take as many processes as one. ``hilsim run controller@arm3``
runs one robot's controller alone (e.g. on another machine).

Robots as arrays (``fleet.arrays: true``): a process serving every robot of a kind (``sensors@*``,
``controller@*``, composed or not) also runs that kind's *fleet driver*, a service named like the kind
in the scenario's own namespace (``<prefix>/arm/alive/controller``), which steps every robot's
encoders or PID as numpy arrays and trades one sample per step with physics:
``/<robot>/fleet/truth/joint_states`` (physics → sensors), ``/<robot>/fleet/joint_states`` (sensors →
controller) and ``/<robot>/fleet/joint_commands`` (controller → physics; in lockstep the controller
driver's acknowledgement of every robot at once), their joints named ``arm<k>/<joint>``, robot by
robot; ``/<robot>/fleet/controller/reference`` (every robot's reference, for the recorder) only while
subscribed. The per-robot services of the process stay (health, liveliness, trajectories, actions,
parameters, the IMU) but leave the per-step joint path to the driver, which still publishes every
robot's ``joint_states``, ``joint_commands`` and ``controller/reference`` from the same values
whenever someone subscribes them (the recorder, a ROS 2 node). The planners of ``planner@*`` take
``fleet/joint_states_throttle`` (the fleet samples of their decision steps) through their own
driver, which hands each planner its robot's slice
as the JointState it would have received; they acknowledge their ticks themselves, per robot, as
before. ``hilsim run controller@arm3`` (one robot alone) keeps the per-robot path; physics serves
both.

With ``robots: 1`` (the default) nothing of this applies: the robot is ``<robot>`` itself and
every key, process and result is what it always was.
"""

from __future__ import annotations

from typing import Protocol


class _Fleet(Protocol):
    """What the naming rules read of a scenario (:class:`hilsim.core.config.Scenario` has it)."""

    robot: str
    robots: int


# the sections a robot may have its own values of (robot_overrides); the world and clock are shared
OVERRIDABLE = ("task", "controller", "planner", "sensors")
FLEET_WIDE = ("physics", "logger")  # one for the whole fleet; every other service runs per robot
ALL = "*"  # <service>@*: the service of every robot, in one process
# the kinds a process serving every robot steps as arrays (fleet.arrays), and the fleet topics
ARRAY_KINDS = ("sensors", "controller", "planner")


def robot_names(sc: _Fleet) -> list[str]:
    """The robots of a scenario: its ``robot`` alone, or ``<robot>0`` … ``<robot>N-1``."""
    return [sc.robot] if sc.robots == 1 else [f"{sc.robot}{k}" for k in range(sc.robots)]


def joint_names(sc: _Fleet, joints: list[str]) -> list[str]:
    """The joints of a fleet-wide sample: ``<robot>/<joint>``, robot by robot, each in model order."""
    return [f"{r}/{j}" for r in robot_names(sc) for j in joints]


def per_robot(service: str) -> bool:
    return service not in FLEET_WIDE


def expand_processes(sc: _Fleet, base: list[str]) -> list[str]:
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


def members(sc: _Fleet, unit: str) -> list[str]:
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


def service_id(sc: _Fleet, key: str, kind: str) -> str:
    """Who a key belongs to: ``<service>`` in the scenario's own namespace, ``<service>@<ns>`` in a robot's.
    A data key ``<domain>/<ns>/<kind>/<service>[/…]/<type>/<hash>`` or a liveliness token
    ``<prefix>/<ns>/<kind>/<service>[/…]`` (hilsim.core.keys spells both)."""
    parts = key.split("/")
    parts = parts[1:-2] if parts[-1].startswith("RIHS") else parts[1:]
    i = parts.index(kind, 1)
    ns, svc = parts[0], parts[i + 1]
    return svc if ns == sc.robot else f"{svc}@{ns}"
