"""Step-response figures as the arm paper's Table II lists them, from a sampled response.

Definitions (``y0`` the value when the step is commanded, ``target`` the commanded value,
``step = target - y0``; times from the step):

- rise time: from the first crossing of 10 % of the step to the first crossing of 90 %
  (crossings interpolated linearly between samples);
- settling time (2 %): the time after which ``|y - target|`` stays within 2 % of ``|step|``
  (interpolated at the last exit of the band); ``inf`` if it is outside at the end;
- overshoot: the largest excursion beyond the target, in percent of ``|step|`` (0 if none);
- peak time: the time of the largest excursion; where a quantised encoder holds it for several samples,
  the middle of that first stretch (the top count is reached early or late by a fraction of a count's
  worth of motion: near the peak, where the response is slow, that is tens of ms). A response that
  does not overshoot (by more than ``zero_overshoot`` rad) has its largest excursion *at* the target,
  so its peak time is the first time it comes within ``zero_tol`` of the target (the paper's peak
  times, just after its settling times, read the same way); ``inf`` if it never does;
- steady-state error: ``|mean(y) - target|`` over the last ``tail`` seconds of the record.

Pure numpy: tested on a second-order plant with known analytic figures.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

ZERO_TOL = 1e-3  # [rad]: the paper's "0" steady-state error (the criterion, < 1e-3 rad)
# The paper's "0" overshoot: the truth at most 0.25 mrad past the target, 2.5 counts of the arm's
# encoders (0.1 mrad): the truth of a loop closed on quantised feedback wanders that much.
ZERO_OVERSHOOT = 2.5e-4  # [rad]
# The tuner's own aim, relative to the step (stricter: 0.05 % of a 0.2 rad step is 0.1 mrad).
ZERO_OVERSHOOT_PCT = 0.05


@dataclass(frozen=True)
class Figures:
    """Table II of one step response."""

    step: float  # commanded step [rad]
    rise_time_s: float
    settling_time_s: float
    peak_time_s: float
    overshoot_pct: float
    steady_state_error: float  # [rad]

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _crossing(t: np.ndarray, frac: np.ndarray, level: float) -> float:
    """First time ``frac`` reaches ``level`` (linear interpolation), inf if never."""
    idx = np.nonzero(frac >= level)[0]
    if not idx.size:
        return math.inf
    i = int(idx[0])
    if i == 0:
        return float(t[0])
    f0, f1 = frac[i - 1], frac[i]
    return float(t[i - 1] + (t[i] - t[i - 1]) * (level - f0) / (f1 - f0))


def step_figures(
    t: np.ndarray,
    y: np.ndarray,
    y0: float,
    target: float,
    *,
    band: float = 0.02,
    zero_tol: float = ZERO_TOL,
    zero_overshoot: float = ZERO_OVERSHOOT,
    tail: float = 0.05,
) -> Figures:
    """The Table II figures of a response ``y(t)`` (``t`` from the step, increasing)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.shape != y.shape or t.size < 3:
        raise ValueError("step_figures: t and y must be 1-D arrays of the same length (at least 3 samples)")
    step = target - y0
    if step == 0.0:
        raise ValueError("step_figures: zero step")
    frac = (y - y0) / step  # 0 at the start, 1 at the target, whatever the step's sign
    c90 = _crossing(t, frac, 0.9)
    rise = c90 - _crossing(t, frac, 0.1) if math.isfinite(c90) else math.inf  # never 90 %: never risen
    err = np.abs(y - target)
    tol = band * abs(step)
    outside = np.nonzero(err > tol)[0]
    if not outside.size:
        settle = float(t[0])
    elif outside[-1] == len(t) - 1:
        settle = math.inf
    else:
        i = int(outside[-1])  # last sample outside; interpolate where it re-entered the band
        settle = float(t[i] + (t[i + 1] - t[i]) * (err[i] - tol) / (err[i] - err[i + 1]))
    k = int(np.argmax(frac))
    overshoot = max(0.0, 100.0 * float(frac[k] - 1.0))
    if overshoot / 100.0 * abs(step) > zero_overshoot:
        held = k
        while held + 1 < frac.size and frac[held + 1] == frac[k]:  # the same count, held
            held += 1
        peak = float(t[k] + t[held]) / 2.0
    else:
        near = np.nonzero(err <= zero_tol)[0]
        peak = float(t[near[0]]) if near.size else math.inf
    last = t >= t[-1] - tail
    sse = abs(float(np.mean(y[last])) - target)
    return Figures(float(step), float(rise), settle, peak, overshoot, sse)
