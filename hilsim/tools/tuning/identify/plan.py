"""What ``hilsim identify`` commands a joint to do: the excitation it fits on, and the motions it proves the twin on.

Both go through the normal command path: the rig (:mod:`hilsim.tools.tuning.rig`) hands the controller a
trajectory, the controller sends the joint's setpoint with its velocity feed-forward every control
step, and the drive (or the twin's simulated drive) follows it.

- **Excitation** (:func:`excitation`): steps of several sizes and both signs, each held until the drive
  has settled (the small ones for the loop's linear dynamics, the large ones so that the acceleration
  and velocity limits show), then a chirp (0.5 to 4 Hz, with its velocity as feed-forward, as any
  trajectory) for the dead time and the bandwidth. Its steps are ``0.05, -0.1, 0.35, -0.6, 1.7, -1.4``
  times ``scale`` rad: none is a validation step.
- **Validation** (:func:`validation`): steps of 0.2 and 1.0 rad from home, each three times (up, down,
  up: :data:`REPEATS`), and the joint's part of the arm's three targets (``task.targets``,
  :func:`targets_trajectory`), home → each target in turn → home, each leg a minimum-jerk motion at
  80 % of the joint's URDF velocity limit, held 0.5 s at each target: motions the fit never saw.

**The rover** (``four_wheel_steer``) takes no trajectory per joint: its loops are stepped through its
controller's kinematic layer, as ``hilsim report step rover`` steps them (:mod:`hilsim.tools.tuning.rig`). A
steering loop's excitation is steps of the wheels' angle of 0.05, 0.3 and 0.8 rad, a traction loop's
steps of their speed of 0.5, 2.5 and 5 rad/s, each both ways (:data:`ROVER_EXCITATION`); the proof is
report step's own steps, 0.2 rad and 2 rad/s, three times each (the rover's targets are places, not
joint positions: no trajectory).
"""

from __future__ import annotations

import math

import numpy as np

from hilsim.core.config import ConfigError, Scenario
from hilsim.sim import control
from hilsim.sim.world import urdf_limits
from hilsim.tools.tuning.rig import Experiment

VALIDATION_STEPS = (0.2, 1.0)  # [rad] the (and report step's) steps
REPEATS = (1.0, -1.0, 1.0)  # each validation step from home, in these directions (the figures' median)
# the excitation: (level relative to its centre [× scale], hold [s]); the steps between levels are its steps
LEVELS = ((0.05, 0.35), (-0.05, 0.35), (0.3, 0.5), (-0.3, 0.6), (1.4, 1.0), (0.0, 1.0))
CHIRP = (0.05, 0.5, 4.0, 2.0)  # amplitude [× scale, rad], start and end frequency [Hz], duration [s]
SAMPLE = 0.01  # [s] between the points of a smooth trajectory (cubic Hermite between: exact enough)
# the rover's loops, by kind: (excitation steps, validation steps) [rad, or rad/s of wheel speed]
ROVER_EXCITATION = {"steering": (0.05, -0.05, 0.3, -0.3, 0.8, -0.8), "traction": (0.5, -0.5, 2.5, -2.5, 5.0, -5.0)}
ROVER_VALIDATION = {"steering": (0.2,), "traction": (2.0,)}


def is_rover(sc: Scenario) -> bool:
    return sc.controller.type == "four_wheel_steer"


def _kind(joint: str) -> str:
    return "traction" if joint.endswith("traction") else "steering"


def _limits(sc: Scenario, joint: str) -> tuple[float, float]:
    t = control.joint_table(sc.world.model)
    if joint not in t.names:
        raise ConfigError(f"--joints: {joint} is not a joint of {sc.world.model.name} (joints: {', '.join(t.names)})")
    j = t.names.index(joint)
    return float(t.lower[j]), float(t.upper[j])


def excitation(sc: Scenario, joint: str, home: float, scale: float = 1.0) -> list[Experiment]:
    """The excitation of ``joint`` from ``home``: one trajectory experiment (steps, then the chirp); the
    rover: its loop's steps, one experiment each."""
    if is_rover(sc):
        _limits(sc, joint)
        return [Experiment(joint, s * scale, measure=0.8, settle=0.4) for s in ROVER_EXCITATION[_kind(joint)]]
    lo, hi = _limits(sc, joint)
    reach = max(abs(x) for x, _ in LEVELS) * scale
    if hi - lo < 2 * reach:
        raise ConfigError(f"{joint}: its range [{lo:.3f}, {hi:.3f}] is too small for the excitation's ±{reach:g} rad "
                          f"(give --scale below {(hi - lo) / (2 * reach / scale):.2f})")
    centre = min(max(home, lo + reach), hi - reach)
    dt_c = 1.0 / sc.controller.rate_hz  # a step: two points one control period apart, on the control grid
    pts: list[tuple[float, float, float]] = [(0.0, home, 0.0)]
    t, level = 0.3, home
    for x, hold in LEVELS:
        new = centre + x * scale
        pts += [(t, level, 0.0), (t + dt_c, new, 0.0)]
        t, level = _on_grid(t + dt_c + hold, dt_c), new
    amp, f0, f1, dur = CHIRP
    n = round(dur / SAMPLE)
    for k in range(1, n + 1):
        s = k * SAMPLE
        phase = 2 * math.pi * (f0 * s + (f1 - f0) * s * s / (2 * dur))
        w = 2 * math.pi * (f0 + (f1 - f0) * s / dur)
        # a window that rises and falls over 0.2 s: the chirp starts and ends at rest
        g, dg = _ramp(s, dur)
        p = amp * scale * g * math.sin(phase)
        v = amp * scale * (dg * math.sin(phase) + g * w * math.cos(phase))
        pts.append((t + s, level + p, v))
    pts.append((t + dur + 0.3, level, 0.0))
    return [Experiment(joint, 0.0, measure=pts[-1][0] + 0.2, settle=0.3, points=tuple(pts))]


def _on_grid(t: float, dt: float) -> float:
    return round(t / dt) * dt


def _ramp(s: float, dur: float, edge: float = 0.2) -> tuple[float, float]:
    """A cosine window (0 → 1 in ``edge`` s, 1 → 0 in the last ``edge`` s) and its derivative."""
    for x, sign in ((s, 1.0), (dur - s, -1.0)):
        if x < edge:
            return 0.5 - 0.5 * math.cos(math.pi * x / edge), sign * 0.5 * math.pi / edge * math.sin(math.pi * x / edge)
    return 1.0, 0.0


def validation(sc: Scenario, joints: list[str], home: dict[str, float], measure: float = 1.0) -> list[Experiment]:
    """Every joint's validation motions: its steps (each size :data:`REPEATS` times), then its task trajectory."""
    out = []
    for j in joints:
        sizes = ROVER_VALIDATION[_kind(j)] if is_rover(sc) else VALIDATION_STEPS
        # back home as long as out: the next step starts from rest, as the first did
        out += [Experiment(j, sign * s, measure=measure, settle=measure, spare=True) for s in sizes for sign in REPEATS]
        if not is_rover(sc):
            out.append(targets_trajectory(sc, j, home[j]))
    return out


def targets_trajectory(sc: Scenario, joint: str, home: float) -> Experiment:
    """``joint``'s part of the arm's task: home → each of ``task.targets`` → home, minimum-jerk legs."""
    names = list(control.joint_table(sc.world.model).names)
    j = names.index(joint)
    targets = [t[j] for t in sc.task.targets]
    if not targets:
        raise ConfigError(f"{sc.source}: task.targets: none, so there is no task trajectory to prove the twin on")
    vlim = urdf_limits(sc.world.urdf).get(joint, (math.inf, math.inf))[1] if sc.world.urdf else math.inf
    vmax = 0.8 * (vlim if math.isfinite(vlim) else 2.0)
    pts: list[tuple[float, float, float]] = [(0.0, home, 0.0)]
    t, p = 0.2, home
    for goal in [*targets, home]:
        d = goal - p
        dur = max(0.3, 1.875 * abs(d) / vmax)  # a minimum-jerk leg peaks at 1.875·d/T
        n = max(2, math.ceil(dur / SAMPLE))
        pts.append((t, p, 0.0))
        for k in range(1, n + 1):
            u = k / n
            pts.append((t + u * dur, p + d * (10 * u**3 - 15 * u**4 + 6 * u**5),
                        d / dur * (30 * u**2 - 60 * u**3 + 30 * u**4)))
        t, p = t + dur + 0.5, goal
    return Experiment(joint, 0.0, measure=t, settle=0.3, points=tuple(pts))


def reference(exp: Experiment, t: np.ndarray) -> np.ndarray:
    """The trajectory's reference position at times ``t`` [s from its start], as the controller samples it."""
    from hilsim.core import msgs

    traj = msgs.JointTrajectory(joint_names=[exp.joint], points=[
        msgs.JointTrajectoryPoint(positions=[p], velocities=[v], time_from_start=msgs.duration(s))
        for s, p, v in exp.points])
    sampler = control.TrajectorySampler(traj, [exp.joint], 0, np.zeros(1))
    return np.array([sampler.sample(round(x * 1e9))[0][0] for x in t])
