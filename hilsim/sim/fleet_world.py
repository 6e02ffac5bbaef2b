"""One MuJoCo world of many robots (``robots: N``): the world model loaded N times side by side.

Copy k of the world model is moved by k × ``robot_spacing`` and its names are prefixed
``<robot k>/`` (MuJoCo's ``MjSpec.attach``); one clock and one ``mj_step`` for all. Which robots
there are and how their services are named is :mod:`hilsim.core.fleet`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilsim.core.config import Scenario
from hilsim.core.fleet import robot_names
from hilsim.sim.world import World

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
    """One MuJoCo world of N robots: a :class:`hilsim.sim.world.World` per robot (its joints, truth
    and commands, names without the prefix) over the shared model and data, stepped together."""

    def __init__(self, sc: Scenario) -> None:
        import warnings

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
