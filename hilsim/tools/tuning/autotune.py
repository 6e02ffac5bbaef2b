"""``hilsim tune ROBOT JOINT --method ziegler-nichols|relay``: a joint's PID tuned on the real services.

Every measurement is a step experiment of :mod:`hilsim.tools.tuning.rig` (physics, sensors and the
controller as separate processes, in lockstep, the physics truth measured), so a tuning is
reproducible: same scenario and seed, same gains.

1. **The ultimate point** (gain ``Ku`` at which the proportional loop oscillates steadily, and its
   period ``Tu``):

   - ``ziegler-nichols`` (the ultimate-gain method, as the rover thesis tunes its wheel loops):
     proportional control only, ``kp`` doubled from trial to trial; each response's oscillation
     decays by a ratio per period; ``Ku`` is where that ratio reaches ``SUSTAINED`` (interpolated
     in ``log kp``), ``Tu`` the period there;
   - ``relay`` (Åström–Hägglund): the controller made a relay (``kp`` so high that the output is
     always at ``output_limit = h``, ``h`` a fifth of the actuator's limit) after a small kick; the
     limit cycle's amplitude ``a`` and period give ``Ku = 4h/(πa)`` and ``Tu``.

   Ziegler–Nichols' rule turns them into a PID: ``kp = 0.6 Ku``, ``Ti = Tu/2``, ``Td = Tu/8``.

2. **Refinement that removes overshoot.** The classic rule is tuned for a quarter-amplitude decay,
   not for the paper's zero overshoot; and on a gravity-compensated joint (an integrating plant) any
   integral action makes the loop type 2, whose step response must overshoot (the integral of the
   error over a step response is zero). So the refinement measures, in batches of trials:

   a. ``ki = 0``, ``kp`` from the rule's down by halves (ten, then four at a time while even the
      least meets the target), ``kd`` from Ziegler–Nichols' "no
      overshoot" variant (``Td = Tu/3``) scaled as ``√kp`` (the same damping ratio on an inertia);
      while most of a batch overshoots, or only overshooting trials are fast enough, twice the
      damping and again (up to 8 times). Chosen: the *smallest* ``kp`` whose
      response meets the target with a margin (rise and settling within ``MARGIN_T`` of it): the
      least gain that does the job is the least sensitive to encoder noise and to a slower control
      rate (``config/arm-lean.yaml`` runs the same gains at 250 Hz); with no such trial, the fastest;
   b. ``kd`` around that one by factors of √2, only when the target is not met yet: the fastest;
   c. ``ki`` from the rule's integral time at the chosen ``kp`` (``kp/Ti``), in decades down, with
      anti-windup ``i_limit`` at a tenth of the actuator's limit, each watched 2.5 times longer
      (integral action creeps past the target late): the largest that does not overshoot and still
      meets the target (it only mops up coupling between the joints).

   "Without overshoot" is at most half of :data:`~hilsim.tools.tuning.metrics.ZERO_OVERSHOOT_PCT`, and a
   trial must end within half of :data:`~hilsim.tools.tuning.metrics.ZERO_TOL` of the target (margins: the
   chosen gains must stay at the paper's zeros on other steps and longer windows too). Every
   candidate's gains are rounded to four significant digits before they are measured, so the gains
   printed and written are the ones measured.

The result is the figures of the chosen gains on the final step, checked against a target (by
default the paper's Table II row of the joint); ``--write`` puts the gains into the scenario file
(``controller.gains.<joint>``, that line only), ``--all`` tunes every joint in turn.

**The rover** (``hilsim tune rover steering|traction``): a kind of loop is tuned for its four wheels
at once (they share ``controller.gains.steering`` / ``.traction``), each trial stepping all four
through the controller's kinematic layer (:mod:`hilsim.tools.tuning.rig`) and judged by the worst wheel.
The thesis gives no figures, so the default target is :func:`rover_target`; "zero" overshoot and
error are relative to the step (:data:`~hilsim.tools.tuning.step_report.ROVER_ZERO`: a rolling wheel's
true speed ripples by ~0.2 %). The steps alternate in sign from trial to trial, so the rover
shuttles instead of driving into a wall. The traction loop is a speed loop: its PID's derivative
term acts on nothing (``kd`` stays 0, no damping search), and its kick is ``VELOCITY_KICK``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilsim.core.config import ConfigError, Scenario
from hilsim.core.scenario import load_scenario, scenario_path
from hilsim.sim import control
from hilsim.tools import progress
from hilsim.tools.tuning.metrics import ZERO_OVERSHOOT_PCT, ZERO_TOL, Figures, step_figures
from hilsim.tools.tuning.rig import Experiment, Response, rig_command
from hilsim.tools.tuning.rig_run import loop_scenario, run_experiments
from hilsim.tools.tuning.step_report import DEFAULT_SPEED, ROVER_ZERO

SUSTAINED = 0.95  # decay ratio per period counted as a sustained oscillation
RELAY_FRACTION = 0.2  # relay amplitude h as a fraction of the actuator's limit
KICK = 0.01  # [rad] step that starts the identification oscillations
VELOCITY_KICK = 0.5  # [rad/s] the same for a velocity loop (a rover wheel's speed ripples by ~0.005 rad/s)
ROVER_KINDS = ("steering", "traction")
ROVER_ERROR = 0.01  # the rover's "0" steady-state error: half the 2 % band, of the step
MARGIN = 0.5  # a refinement trial counts as without overshoot at half the paper's "0" tolerance
MARGIN_T = 0.8  # and meets a time target at 80 % of it
LONGER = 2.5  # trials of an integral gain are watched this many times longer

Say = Callable[[str], None]


@dataclass(frozen=True)
class Target:
    """What the tuned step response must achieve (None: not required)."""

    rise_s: float | None = 0.89  # the goal where the paper has no row: rise 0.18–0.89 s
    settling_s: float | None = 1.00  # settling <= 1.00 s
    overshoot_pct: float = ZERO_OVERSHOOT_PCT
    steady_state_error: float = ZERO_TOL
    margin: float = MARGIN_T  # the refinement aims at rise and settling this fraction of the target

    def within(self, f: Figures) -> bool:
        """Rise and settling at ``margin`` of the target or faster."""
        return (self.rise_s is None or f.rise_time_s <= self.margin * self.rise_s) and \
            (self.settling_s is None or f.settling_time_s <= self.margin * self.settling_s)

    def misses(self, f: Figures) -> list[str]:
        out = []
        if self.rise_s is not None and not f.rise_time_s <= self.rise_s:
            out.append(f"rise {f.rise_time_s:.3f} s > {self.rise_s:g} s")
        if self.settling_s is not None and not f.settling_time_s <= self.settling_s:
            out.append(f"settling {f.settling_time_s:.3f} s > {self.settling_s:g} s")
        if not f.overshoot_pct <= self.overshoot_pct:
            out.append(f"overshoot {f.overshoot_pct:.3f} % > {self.overshoot_pct:g} %")
        if not f.steady_state_error < self.steady_state_error:
            out.append(f"steady-state error {f.steady_state_error:.1e} >= {self.steady_state_error:g}")
        return out


def paper_target(joint: str) -> Target:
    """The paper's Table II row of the joint (rise and settling no slower); zero overshoot and error."""
    from hilsim.tools.tuning.step_report import PAPER_TABLE_II

    row = PAPER_TABLE_II.get(joint)
    return Target(row[0], row[1]) if row else Target()


def rover_target(step: float) -> Target:
    """The rover's loops (no seed figures): inside the 2 % band within 0.5 s, 10–90 % within 0.25 s,
    overshoot at most 0.5 % and steady-state error at most 1 % of the step (half the band: a speed
    loop on a wheel that carries the rover is an integrating plant, where integral action that
    removes the last of the error must overshoot, as on the arm)."""
    return Target(0.25, 0.5, overshoot_pct=100 * ROVER_ZERO, steady_state_error=ROVER_ERROR * abs(step))


@dataclass(frozen=True)
class Loop:
    """What the tuner needs to know of a loop besides its gains (see the module)."""

    joints: tuple[str, ...]  # the joints whose gains it sets and whose truth it judges
    rover: bool = False
    velocity: bool = False  # a speed loop (the rover's traction)

    @property
    def kick(self) -> float:
        return VELOCITY_KICK if self.velocity else KICK

    def sign(self, i: int) -> float:
        """The rover alternates its steps (it drives: back and forth, not into a wall)."""
        return -1.0 if self.rover and i % 2 else 1.0

    def zeros(self, step: float) -> tuple[float, float]:
        """The "0" of overshoot [% of the step] and of steady-state error [the loop's unit]."""
        if not self.rover:
            return ZERO_OVERSHOOT_PCT, ZERO_TOL
        return 100 * ROVER_ZERO, ROVER_ERROR * abs(step)

    def figures(self, rs: list[Response]) -> Figures:
        """The figures of a trial: of its joint, or the worst of the rover's wheels."""
        fs = []
        for r in rs:
            if self.rover:
                z = ROVER_ZERO * abs(r.target - r.y0)
                fs.append(step_figures(r.t, r.y, r.y0, r.target, zero_tol=z, zero_overshoot=z))
            else:
                fs.append(step_figures(r.t, r.y, r.y0, r.target))
        if len(fs) == 1:
            return fs[0]
        return Figures(float(np.mean([f.step for f in fs])), max(f.rise_time_s for f in fs),
                       max(f.settling_time_s for f in fs), max(f.peak_time_s for f in fs),
                       max(f.overshoot_pct for f in fs), max(f.steady_state_error for f in fs))


def loop_of(sc: Scenario, joint: str) -> Loop:
    """A joint of the arm; on the rover a kind of loop (or one wheel's loop)."""
    names = list(control.joint_table(sc.world.model).names)
    rover = sc.controller.type == "four_wheel_steer"
    if rover and joint in ROVER_KINDS:
        return Loop(tuple(n for n in names if n.endswith(f"_{joint}")), True, joint == "traction")
    if joint not in names:
        extra = f"; or {' or '.join(ROVER_KINDS)}, every wheel's" if rover else ""
        raise ConfigError(f"{joint}: not a joint of {sc.world.model.name} (joints: {', '.join(names)}{extra})")
    return Loop((joint,), rover, rover and joint.endswith("_traction"))


def _grouped(exps: list[Experiment], rs: list[Response]) -> list[list[Response]]:
    """The responses of each experiment (a rover kind's has one per wheel)."""
    return [[r for r in rs if r.experiment is e] for e in exps]


@dataclass(frozen=True)
class Ultimate:
    ku: float
    tu: float
    how: str  # one line: what was measured


@dataclass
class Result:
    joint: str
    method: str
    ultimate: Ultimate
    rule: dict[str, float]  # Ziegler–Nichols' PID from the ultimate point
    gains: dict[str, float]  # after the refinement
    figures: Figures
    misses: list[str]
    trials: int


# ---------------------------------------------------------------- oscillation analysis
def oscillation(t: np.ndarray, y: np.ndarray, centre: float, band: float) -> tuple[list[float], list[float]]:
    """Times of upward crossings of ``centre`` and the peak |excursion| of each half cycle;
    a crossing counts only once the signal has left ``±band`` (hysteresis against chatter)."""
    e = np.asarray(y, float) - centre
    ups: list[float] = []
    peaks: list[float] = []
    sign = 0
    peak = 0.0
    for i in range(len(e)):
        v = e[i]
        s = 1 if v > band else -1 if v < -band else 0
        if s and s != sign:
            if sign:
                peaks.append(peak)
                if s > 0:  # interpolate where it crossed the centre on the way up
                    j = i
                    while j > 0 and e[j - 1] > 0:
                        j -= 1
                    t0, t1, e0, e1 = t[max(j - 1, 0)], t[j], e[max(j - 1, 0)], e[j]
                    ups.append(float(t1 if e1 == e0 else t0 + (t1 - t0) * (0 - e0) / (e1 - e0)))
            sign, peak = s, 0.0
        peak = max(peak, abs(v))
    return ups, peaks


def decay_and_period(r: Response) -> tuple[float, float, float]:
    """(decay ratio per period, period, amplitude of the last whole cycle) of an oscillating
    response; the first half cycle (the step itself) is left out. Ratio 0 when it does not oscillate."""
    band = max(5e-5, 0.02 * abs(r.target - r.y0))
    ups, peaks = oscillation(r.t, r.y, r.target, band)
    peaks = peaks[1:]
    if len(peaks) < 4 or len(ups) < 2:
        return 0.0, math.inf, 0.0
    # peaks alternate sides: compare each with the one a period later
    ratios = [b / a for a, b in zip(peaks[:-2], peaks[2:], strict=False) if a > 0]
    ratio = float(np.exp(np.mean(np.log(np.maximum(ratios, 1e-12))))) if ratios else 0.0
    period = float(np.median(np.diff(ups)))
    return ratio, period, float(np.mean(peaks[-2:]))


# ---------------------------------------------------------------- the ultimate point
def _effort(sc: Scenario, joint: str) -> float:
    t = control.joint_table(sc.world.model)
    lim = float(t.effort_upper[t.names.index(joint)])
    if not math.isfinite(lim):
        raise ConfigError(f"{joint}: the actuator has no effort limit; the tuner needs one (ctrlrange)")
    return lim


def _resolution(sc: Scenario) -> float:
    """The encoders' quantum [rad per count] (0: exact)."""
    return max((float(c.model_dump().get("resolution", 0.0)) for c in sc.sensors.values()
                if c.type == "encoder" and c.enabled), default=0.0)


def _p_only(kp: float, effort: float) -> dict[str, float]:
    return {"kp": kp, "ki": 0.0, "kd": 0.0, "output_limit": effort}


def ultimate_zn(robot: str, joint: str, say: Say, overrides: dict | None = None) -> tuple[Ultimate, int]:
    """Ziegler–Nichols: proportional only, kp doubled until the oscillation no longer decays."""
    sc = loop_scenario(robot, overrides)
    loop = loop_of(sc, joint)
    effort = _effort(sc, loop.joints[0])
    kps = [effort / loop.kick * 2.0**i for i in range(-4, 6)]  # from well below saturation to far above
    exps = [Experiment(joint, loop.sign(i) * loop.kick, _p_only(kp, effort), measure=0.5, settle=0.3)
            for i, kp in enumerate(kps)]
    say(f"  ziegler-nichols: proportional only, kp {kps[0]:.4g} … {kps[-1]:.4g} ({len(kps)} trials)")
    rs = run_experiments(loop_scenario(robot, overrides), exps, progress=_count(say, "ultimate gain"))
    found = [(kp, *_decay(g)) for kp, g in zip(kps, _grouped(exps, rs), strict=True)]
    for kp, ratio, period, _ in found:
        say(f"    kp {kp:9.4g}: decay ratio {ratio:.3f} per period, period {period:.4f} s")
    prev = None
    for kp, ratio, period, _ in found:
        if ratio >= SUSTAINED and math.isfinite(period):
            if prev is None or prev[1] <= 0.0:
                ku, tu = kp, period
            else:  # interpolate log kp between the last decaying trial and this one
                f = (SUSTAINED - prev[1]) / (ratio - prev[1])
                ku = math.exp(math.log(prev[0]) + f * (math.log(kp) - math.log(prev[0])))
                tu = prev[2] + f * (period - prev[2]) if math.isfinite(prev[2]) else period
            return Ultimate(ku, tu, f"proportional only: decay ratio {SUSTAINED} per period at kp {ku:.4g}"), len(kps)
        prev = (kp, ratio, period)
    raise ConfigError(f"{joint}: no sustained oscillation up to kp {kps[-1]:.4g}; try --method relay")


def _decay(rs: list[Response]) -> tuple[float, float, float]:
    """:func:`decay_and_period` of one joint, or the median of the rover's wheels."""
    if len(rs) == 1:
        return decay_and_period(rs[0])
    d = np.array([decay_and_period(r) for r in rs])
    return float(np.median(d[:, 0])), float(np.median(d[:, 1])), float(np.median(d[:, 2]))


def ultimate_relay(robot: str, joint: str, say: Say, overrides: dict | None = None) -> tuple[Ultimate, int]:
    """Åström–Hägglund: the controller as a relay of amplitude h; Ku = 4h/(πa) from the limit cycle."""
    sc = loop_scenario(robot, overrides)
    loop = loop_of(sc, joint)
    h = RELAY_FRACTION * _effort(sc, loop.joints[0])
    relay = {"kp": h / 1e-6, "ki": 0.0, "kd": 0.0, "output_limit": h}  # saturated beyond 1 µrad of error
    say(f"  relay: h = {h:g} (a {RELAY_FRACTION:g} of the actuator's limit), kicked by {loop.kick:g}")
    r, *_ = run_experiments(sc, [Experiment(joint, loop.kick, relay, measure=1.5, settle=0.5)],
                            progress=_count(say, "relay"))  # the rover's kinds: the first wheel's
    half = r.t >= r.t[-1] / 2  # the limit cycle, once the kick's transient is gone
    ups, peaks = oscillation(r.t[half], r.y[half], r.target, 5e-5)
    if len(ups) < 3 or len(peaks) < 4:
        raise ConfigError(f"{joint}: the relay did not make the joint oscillate (amplitude below the "
                          f"encoders' resolution?)")
    a = float(np.mean(peaks[1:]))
    tu = float(np.median(np.diff(ups)))
    ku = 4 * h / (math.pi * a)
    say(f"    limit cycle: amplitude {a:.3g} rad, period {tu:.4f} s")
    counts = a / _resolution(sc) if _resolution(sc) > 0 else math.inf
    if counts < 5:
        say(f"    note: the limit cycle is {counts:.1f} encoder counts: Ku is rough (the refinement measures "
            f"its way down from it)")
    return Ultimate(ku, tu, f"relay h={h:g}: amplitude {a:.3g} rad, period {tu:.4f} s"), 1


def ziegler_nichols_pid(u: Ultimate) -> dict[str, float]:
    """The classic rule: kp = 0.6 Ku, Ti = Tu/2, Td = Tu/8."""
    kp = 0.6 * u.ku
    return {"kp": kp, "ki": kp / (u.tu / 2), "kd": kp * u.tu / 8}


# ---------------------------------------------------------------- refinement
def _count(say: Say, what: str) -> Callable[[int, int], None]:
    def f(done: int, total: int) -> None:
        if total > 1:
            say(f"    {what}: trial {done}/{total}")
    return f


@dataclass
class Trial:
    gains: dict[str, float]
    figures: Figures
    zero_overshoot_pct: float = ZERO_OVERSHOOT_PCT  # the loop's "0"s (Loop.zeros)
    zero_error: float = ZERO_TOL

    def ok(self) -> bool:
        f = self.figures
        return f.overshoot_pct <= MARGIN * self.zero_overshoot_pct and f.steady_state_error < MARGIN * self.zero_error \
            and math.isfinite(f.settling_time_s)

    def over(self) -> bool:
        return self.figures.overshoot_pct > MARGIN * self.zero_overshoot_pct

    def key(self) -> tuple[float, float]:
        return (self.figures.settling_time_s, self.figures.rise_time_s)


def _r4(x: float) -> float:
    return float(f"{x:.4g}")


def _full(g: dict[str, float], effort: float) -> dict[str, float]:
    """A candidate as the controller gets it: every gain set, the actuator's own output limit."""
    return {"kp": g["kp"], "ki": g["ki"], "kd": g["kd"], "i_limit": g["i_limit"], "output_limit": effort}


def run_trials(robot: str, joint: str, step: float, cands: list[dict[str, float]], what: str, say: Say,
               overrides: dict | None, measure: float) -> list[Trial]:
    sc = loop_scenario(robot, overrides)
    loop = loop_of(sc, joint)
    effort = _effort(sc, loop.joints[0])
    cands = [{k: _r4(v) for k, v in {**g, "i_limit": 0.1 * effort}.items()} for g in cands]
    # home again between trials with the scenario's gains, which may be soft: time to settle
    exps = [Experiment(joint, loop.sign(i) * step, _full(g, effort), measure=measure, settle=0.6)
            for i, g in enumerate(cands)]
    rs = run_experiments(sc, exps, progress=_count(say, what))
    zo, ze = loop.zeros(step)
    return [Trial(g, loop.figures(group), zo, ze) for g, group in zip(cands, _grouped(exps, rs), strict=True)]


def _show(say: Say, t: Trial) -> None:
    g, f = t.gains, t.figures
    say(f"    kp {g['kp']:8.4g} ki {g.get('ki', 0.0):8.4g} kd {g['kd']:8.4g}: rise {f.rise_time_s:.3f} s, "
        f"settling {f.settling_time_s:.3f} s, overshoot {f.overshoot_pct:.3f} %, error {f.steady_state_error:.1e}"
        + ("" if t.ok() else "  (rejected)"))


def refine(robot: str, joint: str, rule: dict[str, float], step: float, target: Target, say: Say,
           overrides: dict | None = None, measure: float = 1.0) -> tuple[Trial, int]:
    """Remove the rule's overshoot and make the response as fast as it goes without it (see the module)."""
    kp0, kd0, ki0 = rule["kp"], rule["kd"] * 8 / 3, rule["ki"]  # kd: Td = Tu/3 instead of Tu/8
    speed_loop = loop_of(loop_scenario(robot, overrides), joint).velocity
    if speed_loop:
        kd0 = 0.0  # a speed loop's derivative term acts on nothing (services/rover_controller.py)
    trials = 0
    best: Trial | None = None
    damping = 1.0
    first, attempts = 0, 0
    fastest: Trial | None = None
    while attempts < 6:
        attempts += 1
        n = 10 if first == 0 else 4  # the first batch spans the range; later ones go on down
        cands = [{"kp": kp0 * 2.0**-i, "kd": damping * kd0 * 2.0 ** (-i / 2), "ki": 0.0}
                 for i in range(first, first + n)]
        say(f"  refine a: ki = 0, kp {cands[-1]['kp']:.4g} … {cands[0]['kp']:.4g}, kd ∝ √kp "
            f"(damping x{damping:g})")
        got = run_trials(robot, joint, step, cands, "refine a", say, overrides, measure)
        if speed_loop:
            for t in got:
                # proportional alone leaves a speed loop an offset (the wheel's drag over kp): removing
                # it is refine c's integral's job, where the error counts again
                t.zero_error = math.inf
        trials += len(got)
        for t in got:
            _show(say, t)
        ok = [t for t in got if t.ok()]
        if ok:
            fastest = min([t for t in (fastest, *ok) if t is not None], key=Trial.key)
        good = [t for t in ok if target.within(t.figures)]
        over = [t for t in got if t.over()]
        # more damping first, then choose: when most of the batch overshoots, or when only
        # overshooting trials are fast enough for the target
        fast_but_over = not good and any(target.within(t.figures) for t in over)
        if first == 0 and (len(over) > len(got) // 2 or fast_but_over) and damping < 8.0 and not speed_loop:
            damping *= 2.0
            continue
        if good and target.within(got[-1].figures) and got[-1].ok():
            first += n  # even the least gain meets the target: the least that does lies further down
            best = got[-1]
            continue
        if good:
            best = min(good, key=lambda t: t.gains["kp"])
        break
    best = best or fastest
    if best is None:
        raise ConfigError(f"{joint}: no trial without overshoot; the loop may need a larger step window")
    kp, kd = best.gains["kp"], best.gains["kd"]
    if not target.within(best.figures) and not speed_loop:
        cands = [{"kp": kp, "kd": kd * 2.0 ** (i / 2), "ki": 0.0} for i in (-2, -1, 1, 2)]
        say(f"  refine b: kd around {kd:.4g} (kp {kp:.4g}), the target not met yet")
        got = run_trials(robot, joint, step, cands, "refine b", say, overrides, measure)
        trials += len(got)
        for t in got:
            _show(say, t)
        best = min([best, *[t for t in got if t.ok()]], key=Trial.key)
        kd = best.gains["kd"]
    # the rule's integral time Ti = Tu/2 at the chosen kp, then decades less
    kis = [ki0 * kp / kp0 * 10.0**-i for i in range(1, 6)]
    say(f"  refine c: ki {kis[-1]:.3g} … {kis[0]:.3g} (kp {kp:.4g}, kd {kd:.4g})")
    # integral action shows late (a slow creep past the target): these trials are watched longer
    got = run_trials(robot, joint, step, [{"kp": kp, "kd": kd, "ki": ki} for ki in kis], "refine c", say,
                     overrides, LONGER * measure)
    trials += len(got)
    for t in got:
        _show(say, t)
    slack = best.figures.settling_time_s * 1.02
    keep = [t for t in got if t.ok() and (target.within(t.figures) if target.within(best.figures)
                                          else t.figures.settling_time_s <= slack)]
    if keep:
        best = max(keep, key=lambda t: t.gains["ki"])
    return best, trials


# ---------------------------------------------------------------- the whole tuning
def tune(robot: str, joint: str, method: str, step: float, target: Target, say: Say,
         overrides: dict | None = None, measure: float = 1.0) -> Result:
    loop_of(loop_scenario(robot, overrides), joint)  # a joint (or rover loop) it has: else one line
    say(f"{joint}: {method}")
    if method == "ziegler-nichols":
        u, n0 = ultimate_zn(robot, joint, say, overrides)
    elif method == "relay":
        u, n0 = ultimate_relay(robot, joint, say, overrides)
    else:
        raise ConfigError(f"--method {method}: expected ziegler-nichols or relay")
    rule = ziegler_nichols_pid(u)
    say(f"  ultimate point: Ku {u.ku:.4g}, Tu {u.tu:.4f} s -> Ziegler–Nichols PID: kp {rule['kp']:.4g}, "
        f"ki {rule['ki']:.4g}, kd {rule['kd']:.4g}")
    best, n1 = refine(robot, joint, rule, step, target, say, overrides, measure)
    return Result(joint, method, u, rule, best.gains, best.figures, target.misses(best.figures), n0 + n1)


def write_gains(path: Path, joint: str, gains: dict[str, float]) -> None:
    """Set ``controller.gains.<joint>`` in a scenario file, that line only (comments stay)."""
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    try:
        c = next(i for i, ln in enumerate(lines) if re.match(r"controller:\s*(#.*)?$", ln))
        g = next(i for i in range(c + 1, len(lines)) if re.match(r"\s+gains:\s*(#.*)?$", lines[i]))
    except StopIteration:
        raise ConfigError(f"{path}: no controller.gains block to write {joint}'s gains into") from None
    indent = None
    end = g + 1
    for i in range(g + 1, len(lines)):
        ln = lines[i]
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        ind = len(ln) - len(ln.lstrip())
        if ind <= len(lines[g]) - len(lines[g].lstrip()):
            break
        indent = indent if indent is not None else ind
        end = i + 1
    indent = indent if indent is not None else len(lines[g]) - len(lines[g].lstrip()) + 2
    vals = ", ".join(f"{k}: {gains[k]:g}" for k in ("kp", "ki", "kd", "i_limit") if k in gains)
    new = f"{' ' * indent}{joint}: {{{vals}}}\n"
    for i in range(g + 1, end):
        if re.match(rf"\s*{re.escape(joint)}:", lines[i]):
            lines[i] = new
            break
    else:
        lines.insert(end, new)
    path.write_text("".join(lines))
    try:
        load_scenario(path)
    except ConfigError:
        path.write_text(text)  # never leave a scenario that does not load
        raise


def _print_result(r: Result) -> None:
    g, f = r.gains, r.figures
    print(f"{r.joint} ({r.method}, {r.trials} measured runs): kp {g['kp']:g}, ki {g['ki']:g}, kd {g['kd']:g}, "
          f"i_limit {g['i_limit']:g}")
    print(f"  rise {f.rise_time_s:.3f} s, settling {f.settling_time_s:.3f} s, peak {f.peak_time_s:.3f} s, "
          f"overshoot {f.overshoot_pct:.3f} %, steady-state error {f.steady_state_error:.1e} rad "
          f"(step {f.step:.3f} rad)")
    print("  target: " + ("met" if not r.misses else "NOT met: " + "; ".join(r.misses)))


@rig_command
def cmd_tune(args: argparse.Namespace) -> int:
    sc = loop_scenario(args.robot)
    rover = sc.controller.type == "four_wheel_steer"
    names = list(control.joint_table(sc.world.model).names)
    if args.all:
        joints = list(ROVER_KINDS) if rover else names
    elif args.joint:
        joints = [args.joint]
    else:
        raise ConfigError("hilsim tune: name a JOINT (the rover: steering or traction) or give --all")
    quiet = args.json
    say = progress(quiet)

    results = []
    for j in joints:
        loop = loop_of(sc, j)
        # the step: --step, else 0.2 rad (the rover's traction: 2 rad/s of wheel speed, as its report)
        step = args.step if args.step is not None else DEFAULT_SPEED if loop.velocity else 0.2
        if not math.isfinite(step) or step == 0.0:
            raise ConfigError(f"--step {step}: expected a non-zero step")
        base = rover_target(step) if loop.rover else paper_target(j)
        if not 0 < args.margin <= 1:
            raise ConfigError(f"--margin {args.margin}: expected a fraction in (0, 1]")
        target = Target(args.rise if args.rise is not None else base.rise_s,
                        args.settling if args.settling is not None else base.settling_s,
                        base.overshoot_pct, base.steady_state_error, margin=args.margin)
        r = tune(args.robot, j, args.method, step, target, say, measure=args.measure)
        results.append(r)
        if not quiet:
            _print_result(r)
        if args.write:
            path = scenario_path(args.robot)
            write_gains(path, j, r.gains)
            say(f"  written: controller.gains.{j} in {path}")
    if args.json:
        print(json.dumps({"robot": args.robot, "method": args.method, "joints": [
            {"joint": r.joint, "ku": r.ultimate.ku, "tu_s": r.ultimate.tu, "ziegler_nichols": r.rule,
             "gains": r.gains, "figures": r.figures.as_dict(), "target_met": not r.misses, "misses": r.misses}
            for r in results]}))
    return 0 if all(not r.misses for r in results) else 1
