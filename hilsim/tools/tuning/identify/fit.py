"""The fit: a drive's response from setpoint to encoder, by nonlinear least squares (scipy.optimize).

The model is :mod:`hilsim.sim.drive`'s (what a twin's joint is then simulated with): dead time, a
closed position loop of order 2 (ω_n, ζ) or 1 (τ), a velocity and an acceleration limit. Each
candidate is simulated over the recorded setpoints (:func:`hilsim.sim.drive.simulate`; with the
setpoints as the bridge put them on the bus, at those times: the fitted dead time is then the
drive's own, and the twin's is that plus the median way from the controller's step to the bus,
:meth:`JointRecord.inputs`) and compared
with what the drive's encoder reported, at the sim time each report came from the drive
(:meth:`JointRecord.measured`); ``scipy.optimize.least_squares`` (trust region reflective, bounded)
moves the parameters, ω_n, ζ, τ and the limits on a log scale. Its loss is robust (``soft_l1``, the
residual taken linearly beyond three times its typical size, 1.4826·MAD): on a busy machine a report
now and then reaches the simulation tens of ms late, and the fit must not bend the drive to it.

Which model: order 2 with both limits first, from the best of a coarse grid of dead times and
bandwidths; then each limit is dropped in turn and kept only if dropping it makes the fit worse by
Akaike's criterion (``AIC = n·ln(C/n) + 2k``, ``C`` the robust sum of squares): a limit the motion
never reached is not fitted (it is reported as not reached, with the largest velocity or
acceleration seen). Order 1 is fitted with the limits kept (from order 2's lag, τ = 2ζ/ω_n) and
chosen if its AIC is lower. A velocity drive (velocity interface) is fitted on its velocity, order 1
(its loop's τ).

The uncertainty of each parameter is the square root of the diagonal of ``s²·(JᵀJ)⁻¹`` at the
solution (``J`` the residuals' Jacobian as the robust loss weighs them, ``s²`` the residual variance,
``C/(n − k)``): the usual asymptotic 1σ. The
residuals of a drive are correlated in time (jitter of the reports, the encoder's quantum), so the
true uncertainty is larger; the residual RMS beside it says how well the model explains the data.

The encoder's quantum is read from the reported positions (the smallest step between distinct
values, if every value is a multiple of it), its period from the reports' count over their span.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy.optimize import least_squares

from hilsim.core.config import DriveConfig
from hilsim.sim.drive import simulate
from hilsim.tools.tuning.identify.data import JointRecord

MAX_POINTS = 3000  # samples the fit compares (the reports, evenly thinned)
MAX_SPAN = 20.0  # [s] of a record the fit simulates at most: the stretches with the most motion
SEGMENT = 2.0  # [s] the stretches a longer record is cut into
LIMITS = ("max_velocity", "max_acceleration")
SAME_COUNT = 1e-6  # [rad] reported positions closer than this are the same encoder count


class FitError(RuntimeError):
    """A record that cannot be fitted (the message says why, in one line)."""


# s: the way to the drive's 95th percentile this far above its median says the run was starved: one
# command in twenty waited ten control periods of the arm (500 Hz) beyond the usual. (docs/hil.md's run,
# on a machine shared with other runs, had 1.4 and 7.3 ms, and its twin matched every figure.)
WAY_SPREAD = 0.020


@dataclass
class Fit:
    """One joint's identified drive."""

    joint: str
    interface: str
    drive: DriveConfig  # the model: what a twin's joint is simulated with
    sigma: dict[str, float]  # 1σ of each fitted parameter (same units)
    rms: float  # residual RMS [rad] (a velocity drive: [rad/s])
    residual_max: float
    motion_rms: float  # RMS of the measured output about its mean: what the residual is small against
    n: int  # samples compared
    seen: dict[str, float]  # the largest |velocity| and |acceleration| the record shows
    reached: dict[str, bool]  # whether each limit was fitted (the motion reached it)
    # with the setpoints as the server sent them: the drive's own dead time [s], and the way from the
    # controller's step to the bus [s]: its median (in drive.dead_time, with the own) and 95th percentile
    own_dead_time: float | None = None
    way: tuple[float, float] | None = None
    candidates: list[dict[str, Any]] = field(default_factory=list)  # each model tried: order, limits, rms, aic

    def as_json(self) -> dict[str, Any]:
        d = self.drive
        params = {k: getattr(d, k) for k in self.fitted_names()}
        return {
            "joint": self.joint, "interface": self.interface, "order": d.order,
            "parameters": {k: _num(v) for k, v in params.items()},
            "sigma": {k: _num(v) for k, v in self.sigma.items()},
            "limits_reached": self.reached, "seen": self.seen,
            "encoder": {"resolution": d.resolution, "period": d.period},
            "residual_rms": self.rms, "residual_max": self.residual_max, "motion_rms": self.motion_rms,
            "dead_time_own": self.own_dead_time,
            "way_to_the_drive": {"median": self.way[0], "p95": self.way[1]} if self.way else None,
            "samples": self.n, "candidates": self.candidates, "warning": self.starved(),
        }

    def starved(self) -> str | None:
        """A warning when the way from the controller's step to the drive varied much (its 95th percentile
        more than ``WAY_SPREAD`` above its median): a run starved by other work, whose fit may not hold."""
        if self.way is None or self.way[1] - self.way[0] <= WAY_SPREAD:
            return None
        return (f"the way to the drive varied: median {self.way[0] * 1e3:.3g} ms, 95 % within {self.way[1] * 1e3:.3g} "
                "ms (a busy machine?); the twin's dead time takes the median: identified on a quiet machine, "
                "it fits closer")

    def fitted_names(self) -> list[str]:
        return _names(self.drive.order, tuple(k for k in LIMITS if self.reached[k]))


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _names(order: int, limits: tuple[str, ...]) -> list[str]:
    return ["dead_time", *(("natural_frequency", "damping_ratio") if order == 2 else ("time_constant",)), *limits]


@dataclass
class _Segment:
    """A stretch of the record simulated on its own, from the state measured at its start."""

    cmd_t: list[float]
    cmd_p: list[float]
    cmd_v: list[float]
    t: np.ndarray
    p0: float
    v0: float


class _Problem:
    """The record prepared for the fit: setpoints, the samples compared, the start. A record longer than
    MAX_SPAN (a long past run) is cut into SEGMENT-long stretches and the ones with the most motion are
    kept, MAX_SPAN of them, each simulated from the state measured at its start: the fit's cost is
    linear in the time simulated."""

    def __init__(self, rec: JointRecord, max_points: int = MAX_POINTS) -> None:
        self.velocity_mode = rec.interface == "velocity"
        mt, mp, mv = rec.measured()
        it, ip, iv, self.way = rec.inputs()  # the setpoints as the drive got them, and the way to it
        idx = np.arange(mt.size)
        if mt.size and mt[-1] - mt[0] > MAX_SPAN:
            seg = np.floor((mt - mt[0]) / SEGMENT).astype(int)
            y_all = mv if self.velocity_mode else mp
            motion = {k: float(np.ptp(y_all[seg == k])) for k in np.unique(seg)}
            best = sorted(sorted(motion, key=lambda k: -motion[k])[: int(MAX_SPAN / SEGMENT)])
            idx = idx[np.isin(seg, best)]
        if idx.size > max_points:
            idx = idx[np.linspace(0, idx.size - 1, max_points).round().astype(int)]
        self.t = mt[idx]
        self.y = (mv if self.velocity_mode else mp)[idx]
        self.segments: list[_Segment] = []
        # a new segment wherever the kept samples jump over a cut-out stretch
        cuts = np.concatenate([[0], np.nonzero(np.diff(self.t) > SEGMENT / 2)[0] + 1, [self.t.size]])
        for a, b in itertools.pairwise(cuts):
            if b - a < 2:
                continue
            k = idx[a]
            c = (it >= self.t[a] - 1.0) & (it <= self.t[b - 1])
            self.segments.append(_Segment(it[c].tolist(), ip[c].tolist(), iv[c].tolist(),
                                          self.t[a:b], float(mp[k]), float(mv[k])))
        keep = np.concatenate([np.arange(a, b) for a, b in itertools.pairwise(cuts) if b - a >= 2]) \
            if self.segments else np.arange(0)
        self.t, self.y = self.t[keep], self.y[keep]
        if len(self.t) < 20:
            raise FitError(f"{rec.joint}: only {len(self.t)} reports reached the simulation: nothing to fit")
        if float(np.ptp(self.y)) <= 0.0:
            raise FitError(f"{rec.joint}: it never moved in the record: nothing to fit")
        # what the record shows: the limits' starting points and, if not reached, the report
        v, ta = mv, mt
        dv = np.abs(np.diff(v)) / np.maximum(np.diff(ta), 1e-3)
        self.v_seen = float(np.max(np.abs(v)))
        self.a_seen = float(np.percentile(dv, 99.5)) if dv.size else 0.0

    def simulate(self, cfg: DriveConfig) -> np.ndarray:
        return np.concatenate([simulate(cfg, g.cmd_t, g.cmd_p, g.cmd_v, g.t, g.p0, g.v0, self.velocity_mode)
                               for g in self.segments])


class _Model:
    """A candidate's parameters <-> the optimiser's vector (log scale for the positive ones)."""

    LOG: ClassVar[frozenset[str]] = frozenset({"natural_frequency", "damping_ratio", "time_constant", *LIMITS})
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {
        "dead_time": (0.0, 0.5), "natural_frequency": (0.5, 2000.0), "damping_ratio": (0.05, 20.0),
        "time_constant": (1e-4, 5.0), "max_velocity": (1e-3, 1e4), "max_acceleration": (1e-2, 1e6)}

    def __init__(self, order: int, limits: tuple[str, ...], base: DriveConfig) -> None:
        self.order, self.limits, self.base = order, limits, base
        self.names = _names(order, limits)

    def vector(self, values: dict[str, float]) -> np.ndarray:
        return np.array([math.log(values[n]) if n in self.LOG else values[n] for n in self.names])

    def values(self, x: np.ndarray) -> dict[str, float]:
        return {n: math.exp(v) if n in self.LOG else float(v) for n, v in zip(self.names, x, strict=True)}

    def drive(self, x: np.ndarray) -> DriveConfig:
        unset = {k: math.inf for k in LIMITS if k not in self.limits}
        return self.base.model_copy(update={"order": self.order, **unset, **self.values(x)})

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = [math.log(self.BOUNDS[n][0]) if n in self.LOG else self.BOUNDS[n][0] for n in self.names]
        hi = [math.log(self.BOUNDS[n][1]) if n in self.LOG else self.BOUNDS[n][1] for n in self.names]
        return np.array(lo), np.array(hi)


@dataclass
class _Result:
    model: _Model
    x: np.ndarray
    cost: float  # the robust sum of squares (2 × least_squares' cost)
    jac: np.ndarray
    n: int
    residual: np.ndarray

    @property
    def aic(self) -> float:
        return self.n * math.log(max(self.cost, 1e-300) / self.n) + 2 * len(self.x)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residual ** 2)))


def _scale(residual: np.ndarray) -> float:
    """Where the robust loss turns linear: three times the residual's typical size (1.4826·MAD ≈ σ)."""
    mad = float(np.median(np.abs(residual - np.median(residual))))
    return max(3.0 * 1.4826 * mad, 1e-6)


def _solve(prob: _Problem, model: _Model, start: dict[str, float], f_scale: float, budget: int = 100) -> _Result:
    lo, hi = model.bounds()
    x0 = np.clip(model.vector(start), lo + 1e-9, hi - 1e-9)

    def residual(x: np.ndarray) -> np.ndarray:
        return prob.simulate(model.drive(x)) - prob.y

    r = least_squares(residual, x0, bounds=(lo, hi), method="trf", loss="soft_l1", f_scale=f_scale,
                      diff_step=1e-3, x_scale="jac", xtol=1e-6, ftol=1e-8, max_nfev=budget)
    return _Result(model, r.x, 2.0 * float(r.cost), r.jac, len(prob.y), r.fun)


def _grid_start(prob: _Problem, order: int, limits: tuple[str, ...], base: DriveConfig) -> dict[str, float]:
    """The best of a coarse grid of dead times and bandwidths, the limits at what the record shows."""
    lim = {"max_velocity": max(prob.v_seen, 1e-3) * 1.05, "max_acceleration": max(prob.a_seen, 1e-2) * 1.05}
    best: tuple[float, dict[str, float]] | None = None
    shapes = ([{"natural_frequency": w, "damping_ratio": z} for w in (10.0, 30.0, 100.0) for z in (0.5, 1.0)]
              if order == 2 else [{"time_constant": tau} for tau in (0.004, 0.015, 0.05, 0.15)])
    for d in (0.0, 0.006, 0.015, 0.035, 0.08):
        for shape in shapes:
            values = {"dead_time": d, **shape, **{k: lim[k] for k in limits}}
            m = _Model(order, limits, base)
            rss = float(np.sum((prob.simulate(m.drive(m.vector(values))) - prob.y) ** 2))
            if best is None or rss < best[0]:
                best = (rss, values)
    assert best is not None
    return best[1]


def _sigma(res: _Result) -> dict[str, float]:
    """1σ of each parameter from s²·(JᵀJ)⁻¹ (inf where the data do not determine it)."""
    dof = max(res.n - len(res.x), 1)
    s2 = res.cost / dof
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * s2
        sx = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sx = np.full(len(res.x), math.inf)
    vals = res.model.values(res.x)
    return {n: (vals[n] * float(s) if n in _Model.LOG else float(s)) for n, s in zip(res.model.names, sx, strict=True)}


def encoder_quantum(positions: np.ndarray) -> float:
    """The encoder's quantum [rad] read from reported positions: the smallest step between distinct
    values when every value is (within 5 %) a multiple of it; 0 when they are not (an exact encoder)."""
    u = np.unique(np.asarray(positions, float))
    if u.size < 3:
        return 0.0
    # values closer than SAME_COUNT are one count sent twice (float32 turns on the wire round differently)
    u = u[np.concatenate([[True], np.diff(u) > SAME_COUNT])]
    d = np.diff(u)
    if not d.size:
        return 0.0
    q0 = float(d.min())
    r = (u - u[0]) / q0
    if np.percentile(np.abs(r - np.round(r)), 95) > 0.05:
        return 0.0
    counts = np.round(d / q0)
    return float(np.sum(d) / np.sum(counts))  # every step's own estimate, weighted by its counts


def report_period(rec: JointRecord) -> float:
    """[s] between the drive's reports that reached the simulation (0 when there are none)."""
    if rec.hw_t.size < 2:
        return 0.0
    span = float(rec.hw_t[-1] - rec.hw_t[0])
    return span / (rec.hw_t.size - 1) if span > 0 else 0.0


def fit_record(rec: JointRecord, progress: Callable[[str], None] | None = None,
               limits: tuple[str, ...] = LIMITS) -> Fit:
    """The drive of one joint's record; ``limits``: those the fit may consider (all, unless told otherwise)."""
    prob = _Problem(rec)
    base = DriveConfig(resolution=encoder_quantum(rec.hw_p), period=report_period(rec))
    say = progress or (lambda _: None)
    tried: list[_Result] = []
    orders = (1,) if prob.velocity_mode else (2, 1)

    f_scale = 0.0

    def run(order: int, lims: tuple[str, ...], start: dict[str, float] | None, budget: int = 100) -> _Result:
        m = _Model(order, lims, base)
        if start is None:
            start = _grid_start(prob, order, lims, base)
        res = _solve(prob, m, {k: v for k, v in start.items() if k in m.names}, f_scale, budget)
        tried.append(res)
        say(f"order {order}, limits {', '.join(lims) or 'none'}: residual RMS {res.rms:.2e}")
        return res

    # the loss's scale: from the grid's best start, then once more from the first solution (fixed after:
    # the candidates' costs are compared at one scale)
    m0 = _Model(orders[0], limits, base)
    g = _grid_start(prob, orders[0], limits, base)
    f_scale = _scale(prob.simulate(m0.drive(m0.vector(g))) - prob.y)
    first = _solve(prob, m0, g, f_scale)
    f_scale = _scale(first.residual)
    best = run(orders[0], limits, m0.values(first.x))
    for lim in limits:  # a limit stays only if the fit needs it
        if lim not in best.model.limits:
            continue
        fewer = tuple(k for k in best.model.limits if k != lim)
        alt = run(best.model.order, fewer, best.model.values(best.x), budget=15)
        if alt.aic <= best.aic + 10.0:  # Akaike: not worth its parameter (10: clearly, not by noise)
            best = alt
    for order in orders[1:]:  # order 1 from order 2's lag: τ ≈ 2ζ/ω_n
        v = best.model.values(best.x)
        tau = 2 * v.get("damping_ratio", 1.0) / v.get("natural_frequency", 50.0)
        alt = run(order, best.model.limits, {**v, "time_constant": tau} if best.model.order == 2 else None, 40)
        if alt.aic < best.aic - 10.0:
            best = alt
    drive = best.model.drive(best.x)
    res = prob.simulate(drive) - prob.y
    own = way = None
    if prob.way is not None and prob.way.size:  # the twin's dead time counts from the controller's step
        own, way = drive.dead_time, (float(np.median(prob.way)), float(np.percentile(prob.way, 95)))
        drive = drive.model_copy(update={"dead_time": own + way[0]})
    return Fit(
        joint=rec.joint, interface=rec.interface, drive=drive, sigma=_sigma(best),
        rms=float(np.sqrt(np.mean(res ** 2))), residual_max=float(np.max(np.abs(res))),
        motion_rms=float(np.std(prob.y)), n=len(prob.y),
        seen={"velocity": prob.v_seen, "acceleration": prob.a_seen},
        reached={k: k in best.model.limits for k in LIMITS},
        candidates=[{"order": r.model.order, "limits": list(r.model.limits), "residual_rms": r.rms,
                     "aic": r.aic, "chosen": r is best} for r in tried],
        own_dead_time=own, way=way,
    )
