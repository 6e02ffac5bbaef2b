"""The proof: the drive and its twin on motions the fit never saw, compared.

- **Steps** (0.2 and 1.0 rad): ``hilsim report step``'s figures (:mod:`hilsim.tools.tuning.metrics`) of the
  drive (measured on its encoder, realtime) and of the twin (lockstep), each step size taken three
  times (+, −, +) and each figure the median of the three: a realtime run on a loaded machine delays
  a report now and then by tens of ms, which one step alone would count as the drive's response.
  The twin matches when its rise, peak and settling times are within 5 % of the drive's or 10 ms,
  whichever is larger, and its overshoot within 1 percentage point.
- **The task's trajectory** (the joint's part of the arm's three targets): the twin's motion against
  the drive's. The twin matches when the RMS of the difference between the two is at most 10 % of
  the RMS of the drive's motion (its displacement from where it started). Each one's tracking error
  (against the reference both were given) is said beside it: how much of what the drive lags the
  twin lags too.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.tools.tuning.identify.plan import reference
from hilsim.tools.tuning.metrics import Figures
from hilsim.tools.tuning.rig import Response
from hilsim.tools.tuning.step_report import figures_of

TIME_REL, TIME_ABS = 0.05, 0.010  # a time figure: within 5 % or 10 ms, whichever is larger
OVERSHOOT_PP = 1.0  # [percentage points]
TRACKING_REL = 0.10  # the trajectory: twin − drive within 10 % of the drive's motion (RMS)
TIMES = ("rise_time_s", "peak_time_s", "settling_time_s")


@dataclass
class StepComparison:
    """One step size of one joint: each of its repetitions (both signs) on the drive and on the twin;
    a figure is the median of its repetitions (one late report of the drive does not make a step)."""

    joint: str
    step: float
    drive: list[Figures]
    twin: list[Figures]
    unit: str = "rad"  # a velocity loop's (the rover's traction): rad/s

    def figure(self, which: str, k: str) -> float:
        vals = [getattr(f, k) for f in (self.drive if which == "drive" else self.twin)]
        return float(np.median(vals))

    def checks(self) -> dict[str, dict[str, Any]]:
        out = {}
        for k in TIMES:
            a, b = self.figure("drive", k), self.figure("twin", k)
            tol = max(TIME_REL * abs(a), TIME_ABS) if math.isfinite(a) else math.inf
            ok = (math.isfinite(a) and math.isfinite(b) and abs(b - a) <= tol) or (math.isinf(a) and math.isinf(b))
            out[k] = {"drive": _num(a), "twin": _num(b), "tolerance": _num(tol), "ok": ok,
                      "drive_each": [_num(getattr(f, k)) for f in self.drive]}
        a, b = self.figure("drive", "overshoot_pct"), self.figure("twin", "overshoot_pct")
        out["overshoot_pct"] = {"drive": a, "twin": b, "tolerance": OVERSHOOT_PP, "ok": abs(b - a) <= OVERSHOOT_PP,
                                "drive_each": [f.overshoot_pct for f in self.drive]}
        return out

    @property
    def ok(self) -> bool:
        return all(c["ok"] for c in self.checks().values())


@dataclass
class TrackComparison:
    joint: str
    motion_rms: float  # [rad] RMS of the drive's displacement from where it started
    difference_rms: float  # [rad] RMS of twin − drive
    drive_error_rms: float  # [rad] RMS of each one's tracking error (said, not judged)
    twin_error_rms: float

    def checks(self) -> dict[str, dict[str, Any]]:
        tol = TRACKING_REL * self.motion_rms
        return {
            "difference_rms_rad": {"drive": self.motion_rms, "twin": self.difference_rms, "tolerance": tol,
                                   "ok": self.difference_rms <= tol},
        }

    @property
    def ok(self) -> bool:
        return all(c["ok"] for c in self.checks().values())


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


def compare_steps(drive: list[Response], twin: list[Response], rover: bool = False) -> StepComparison:
    """The repetitions of one step size (any sign) of one joint, on the drive and on the twin; the figures
    as ``hilsim report step`` reads them (a rover's loop: "no overshoot" and "at the target" relative to
    its step)."""
    return StepComparison(drive[0].name, abs(drive[0].experiment.step), [r.figures for r in figures_of(drive, rover)],
                          [r.figures for r in figures_of(twin, rover)],
                          "rad/s" if drive[0].quantity == "velocity" else "rad")


def compare_tracks(drive: Response, twin: Response) -> TrackComparison:
    """The two motions on the twin's steps (the drive's interpolated onto them), against the reference."""
    t = twin.t[twin.t <= min(drive.t[-1], twin.t[-1])]
    yd = np.interp(t, drive.t, drive.y)
    yt = twin.y[: t.size]
    ref = reference(drive.experiment, t)
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    return TrackComparison(drive.name, rms(yd - yd[0]), rms(yt - yd), rms(yd - ref), rms(yt - ref))


def table(steps: list[StepComparison], tracks: list[TrackComparison]) -> str:
    """The comparisons as a markdown table: the drive's figure, the twin's, the tolerance, the verdict."""
    lines = ["| joint | motion | figure | drive | twin | tolerance | match |", "|---|---|---|---|---|---|---|"]
    for s in steps:
        for k, c in s.checks().items():
            unit = " pp" if k == "overshoot_pct" else " s"
            what = k.removesuffix("_s").removesuffix("_pct")
            lines.append(f"| {s.joint} | step {s.step:.2f} {s.unit} (median of {len(s.drive)}) | {what} | "
                         f"{_fmt(c['drive'])} | {_fmt(c['twin'])} | ±{_fmt(c['tolerance'])}{unit} | "
                         f"{'yes' if c['ok'] else 'NO'} |")
    for tr in tracks:
        c = tr.checks()["difference_rms_rad"]
        ok = "yes" if c["ok"] else "NO"
        lines.append(f"| {tr.joint} | task trajectory | RMS of twin − drive [rad] (drive: of its motion) | "
                     f"{_fmt(c['drive'])} | {_fmt(c['twin'])} | ≤{_fmt(c['tolerance'])} | {ok} |")
        lines.append(f"| {tr.joint} | task trajectory | tracking error RMS [rad] (said, not judged) | "
                     f"{_fmt(tr.drive_error_rms)} | {_fmt(tr.twin_error_rms)} | | |")
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    if v is None:
        return "never"
    return f"{v:.4f}" if abs(v) >= 1e-3 or v == 0 else f"{v:.2e}"


def write_responses(out: Path, drive: Sequence[Response], twin: Sequence[Response]) -> None:
    """Every validation response of the drive and of the twin: ``comparison.csv`` (one row per step of
    each: experiment, joint, its step or trajectory, time from its start, drive, twin) and
    ``comparison.png`` (one panel per experiment, the two over each other)."""
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    with open(out / "comparison.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["experiment", "joint", "motion", "quantity", "t_s", "drive", "twin"])
        for i, (d, t) in enumerate(zip(drive, twin, strict=True)):
            what = "trajectory" if d.experiment.points else f"step {d.experiment.step:+g}"
            yd = np.interp(t.t, d.t, d.y)
            for k in range(t.t.size):
                w.writerow([i, d.name, what, d.quantity, f"{t.t[k]:.6f}", f"{yd[k]:.9g}", f"{t.y[k]:.9g}"])
    n = len(drive)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.2 * rows), squeeze=False)
    for ax, d, t in zip(axes.flat, drive, twin, strict=False):
        ax.plot(d.t, d.y, lw=1.4, label="drive (its encoder)")
        ax.plot(t.t, t.y, lw=1.0, ls="--", label="twin (lockstep)")
        what = "task trajectory" if d.experiment.points else f"step {d.experiment.step:+g}"
        ax.set_title(f"{d.name}: {what}", fontsize=9)
        ax.set_xlabel("time from the start [s]")
        ax.set_ylabel("speed [rad/s]" if d.quantity == "velocity" else "position [rad]")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("hilsim identify: the drive and its twin on motions the fit never saw")
    fig.tight_layout()
    fig.savefig(out / "comparison.png", dpi=100)
    plt.close(fig)

