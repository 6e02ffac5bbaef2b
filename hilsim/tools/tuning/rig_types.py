"""What step experiments are, what they measure, and how they fail (:mod:`hilsim.tools.tuning.rig` runs them)."""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


class RigError(RuntimeError):
    """A step experiment that could not be run or measured; the message says why, in one line."""


def rig_command(cmd: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A command that runs step experiments: a :class:`RigError` (a run that failed) is said in one
    line, exit status 1, as for a bad scenario."""

    @functools.wraps(cmd)
    def run(args: argparse.Namespace) -> int:
        try:
            return cmd(args)
        except RigError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1

    return run


class LateStep(RigError):
    """A trajectory reached the controller after its stamp: that experiment's timing is not exact."""


@dataclass
class Experiment:
    """One step of a loop's reference, with the gains it is measured with."""

    joint: str  # a joint; on the rover also a kind of loop ("steering", "traction": every wheel's)
    step: float  # [rad] (or m) from the joint's home position; a rover traction loop: [rad/s] of wheel speed
    gains: dict[str, float] = field(default_factory=dict)  # e.g. {"kp": 50.0, "kd": 2.0}; {}: the scenario's
    measure: float = 1.5  # sim seconds recorded after the step
    settle: float = 1.0  # sim seconds back home (scenario gains) before the next experiment
    # a trajectory instead of a step: (time_from_start [s], position [rad], velocity [rad/s]) of the joint
    points: tuple[tuple[float, float, float], ...] = ()
    # one of several repetitions: realtime, a step the controller took too late is not measured (its
    # response says why, in ``lost``) rather than the whole run made again
    spare: bool = False


@dataclass
class Response:
    """What an experiment measured on one joint: its truth from the step on."""

    experiment: Experiment
    t: np.ndarray  # [s] from the step
    y: np.ndarray  # true position of the joint (a velocity loop: its true velocity)
    y0: float  # true value when the step was commanded
    target: float  # the commanded value
    joint: str = ""  # the joint measured ("": the experiment's)
    quantity: str = "position"  # or "velocity" (a rover traction loop)
    start: float = 0.0  # [s] sim time of the step (t = 0)
    lost: str = ""  # a spare experiment that could not be measured: why (t and y are empty)

    @property
    def name(self) -> str:
        return self.joint or self.experiment.joint
