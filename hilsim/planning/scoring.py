"""The criterion, in one place: how good a plan is, and a planner's run on a query.

For the plans of one target or the runs on one query (every planner, every seed), the criterion gives each
successful one a cost (:func:`costs`; ``hilsim plan evaluate --targets`` picks the smallest, and the
planner choice scores by it):

- ``length``: ΣP, the paper's joint path length summed over the joints;
- ``smoothness``: ΣA, the joints' acceleration variances summed;
- ``weighted``: W_LENGTH·ΣP/min ΣP + (1 − W_LENGTH)·ΣA/min ΣA, the minima over the successful ones.

A run's **score** (:func:`scores`) is that cost divided by the smallest cost on the query (1 = as good as
the best run), plus ``TIME_WEIGHT`` per second of planning — the paper's "high precision and low
response time". A failed run scores ``FAIL_SCORE`` plus its planning time. Planning time is the run's
collision checks times its planner's CPU seconds per check (:data:`CHECK_S_BY_PLANNER`, calibrated: the
median over a data set's runs of that planner of measured CPU over checks, :func:`calibrate`): checks
are what a run spends its time on, and counted, not timed, so a score is the same on a busy machine and
a quiet one, and a data set built twice scores the same bit for bit; the calibration per planner makes a
check of each planner cost what it costs (the improved RRT*'s 7.5 µs, BIT*'s 14.5 µs). The calibration
is a constant, not measured anew by every build (a model would then differ from build to build):
``hilsim plan learn`` measures it on its own runs and writes both into the manifest. :data:`CONSTANTS`
go into the planner choice's manifest; a model trained under other constants is refused.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import get_args

import numpy as np

from hilsim.core.config import DEFAULT_CRITERION as DEFAULT_CRITERION  # re-exported with the names
from hilsim.core.config import Criterion

# the names are spelled once, in the scenario's schema (the lowest layer that needs them)
CRITERIA: tuple[str, ...] = get_args(Criterion)
FAIL_SCORE = 3.0  # a failed run: as bad as a path three times the best one
TIME_WEIGHT = 2.0  # score per second of planning: 100 ms cost as much as a path 20 % longer than the best
W_LENGTH = 0.5  # weighted: the share of the normalised length (the rest: the normalised smoothness)
CHECK_S = 12e-6  # seconds per collision check of a planner with no calibration
# CPU seconds per collision check, per planner: measured on the 910 runs of models/planner_choice/data.csv
# as built in the first round (calibrate(); the held-out runs gave the same within 5 %)
CHECK_S_BY_PLANNER = {"aorrtc": 11.1e-6, "bitstar": 14.5e-6, "improved_rrtstar": 7.5e-6, "informed_rrtstar": 12.2e-6,
                      "rrtconnect": 13.5e-6, "rrtstar": 12.5e-6, "sorrtstar": 12.5e-6}
CONSTANTS = {"fail_score": FAIL_SCORE, "time_weight_per_s": TIME_WEIGHT, "weighted_w_length": W_LENGTH,
             "default_check_s": CHECK_S, "check_s": CHECK_S_BY_PLANNER}


def check_criterion(criterion: str) -> str:
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, not {criterion!r}")
    return criterion


def costs(success: Sequence[int] | Sequence[bool], sum_P: Sequence[float], sum_A: Sequence[float],
          criterion: str) -> np.ndarray:
    """The criterion's cost of each plan or run on one target or query (nan for a failed one)."""
    ok = np.asarray(success, bool)
    p, a = np.asarray(sum_P, float), np.asarray(sum_A, float)
    out = np.full(len(ok), np.nan)
    if check_criterion(criterion) and not ok.any():
        return out
    if criterion == "length":
        out[ok] = p[ok]
    elif criterion == "smoothness":
        out[ok] = a[ok]
    else:
        out[ok] = W_LENGTH * p[ok] / max(p[ok].min(), 1e-12) + (1 - W_LENGTH) * a[ok] / max(a[ok].min(), 1e-12)
    return out


def best(success: Sequence[bool], sum_P: Sequence[float], sum_A: Sequence[float], criterion: str) -> int | None:
    """The index of the best successful one by the criterion (None if none succeeded)."""
    c = costs(success, sum_P, sum_A, criterion)
    return None if np.all(np.isnan(c)) else int(np.nanargmin(c))


def calibrate(planners: Sequence[str], cpu_s: Sequence[float], checks: Sequence[int]) -> dict[str, float]:
    """CPU seconds per collision check of each planner: the median over its runs (with checks) of measured
    CPU over checks, rounded to 0.1 µs (the calibration a model keeps in its manifest)."""
    per: dict[str, list[float]] = {}
    for p, t, n in zip(planners, cpu_s, checks, strict=True):
        if n > 0 and t > 0:
            per.setdefault(p, []).append(t / n)
    return {p: round(float(np.median(v)), 7) for p, v in sorted(per.items())}


def planning_seconds(checks: Sequence[int] | np.ndarray, planners: Sequence[str] | None = None) -> np.ndarray:
    """Each run's planning time: its checks times its planner's seconds per check (CHECK_S for a planner
    without a calibration, or when the planners are not given)."""
    n = np.asarray(checks, float)
    if planners is None:
        return n * CHECK_S
    return n * np.array([CHECK_S_BY_PLANNER.get(p, CHECK_S) for p in planners])


def scores(success: Sequence[int], sum_P: Sequence[float], sum_A: Sequence[float], checks: Sequence[int],
           criterion: str, time_weight: float = TIME_WEIGHT, planners: Sequence[str] | None = None,
           extra_s: Sequence[float] | None = None) -> np.ndarray:
    """Each run's score on one query (smaller is better; see the module docstring). ``planners``: the
    planner that planned each run (for its calibration); ``extra_s``: time to add (a choice's decision)."""
    c = costs(success, sum_P, sum_A, criterion)
    ok = ~np.isnan(c)
    low = c[ok].min() if ok.any() else math.nan
    quality = np.where(ok, c / max(low, 1e-12) if ok.any() else 1.0, FAIL_SCORE)
    t = planning_seconds(checks, planners)
    if extra_s is not None:
        t = t + np.asarray(extra_s, float)
    return quality + time_weight * t
