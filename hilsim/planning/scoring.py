"""How good a planner's run on a query is: the criterion, normalised per query, plus planning time.

For the runs on one query (every planner, every seed), the criterion of ``hilsim plan evaluate``
(:func:`hilsim.tools.evaluate.common.choose` defines it for targets) gives each successful run a cost:

- ``length``: ΣP, the paper's joint path length summed over the joints;
- ``smoothness``: ΣA, the joints' acceleration variances summed;
- ``weighted``: 0.5·ΣP/min ΣP + 0.5·ΣA/min ΣA, the minima over the query's successful runs.

A run's **score** is that cost divided by the smallest cost on the query (1 = as good as the best
run), plus ``TIME_WEIGHT`` per second of planning — the paper's "high precision and low response
time". A failed run scores ``FAIL_SCORE`` plus its planning time. Planning time here is the run's
collision checks at ``CHECK_S`` each: checks are what a run spends its time on (the median run of the
shipped data set spent that per check, CPU time included everything else), and they are counted,
not timed, so a score is the same on a busy machine and a quiet one, and a data set built twice is
the same bit for bit. Measured CPU seconds are kept beside it (``cpu_s``) and reported.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

CRITERIA = ("length", "smoothness", "weighted")
FAIL_SCORE = 3.0  # a failed run: as bad as a path three times the best one
TIME_WEIGHT = 2.0  # score per second of planning: 100 ms cost as much as a path 20 % longer than the best
CHECK_S = 12e-6  # seconds per collision check (the planning-time unit of the score)


def check_criterion(criterion: str) -> str:
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, not {criterion!r}")
    return criterion


def costs(success: Sequence[int], sum_P: Sequence[float], sum_A: Sequence[float], criterion: str) -> np.ndarray:
    """The criterion's cost of each run on one query (nan for a failed run)."""
    ok = np.asarray(success, bool)
    p, a = np.asarray(sum_P, float), np.asarray(sum_A, float)
    out = np.full(len(ok), np.nan)
    if not ok.any():
        return out
    if check_criterion(criterion) == "length":
        out[ok] = p[ok]
    elif criterion == "smoothness":
        out[ok] = a[ok]
    else:
        out[ok] = 0.5 * p[ok] / max(p[ok].min(), 1e-12) + 0.5 * a[ok] / max(a[ok].min(), 1e-12)
    return out


def planning_seconds(checks: Sequence[int] | np.ndarray) -> np.ndarray:
    return np.asarray(checks, float) * CHECK_S


def scores(success: Sequence[int], sum_P: Sequence[float], sum_A: Sequence[float], checks: Sequence[int],
           criterion: str, time_weight: float = TIME_WEIGHT) -> np.ndarray:
    """Each run's score on one query (smaller is better; see the module docstring)."""
    c = costs(success, sum_P, sum_A, criterion)
    ok = ~np.isnan(c)
    best = c[ok].min() if ok.any() else math.nan
    quality = np.where(ok, c / max(best, 1e-12) if ok.any() else 1.0, FAIL_SCORE)
    return quality + time_weight * planning_seconds(checks)
