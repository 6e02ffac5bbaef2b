"""``hilsim report step ROBOT``: the arm paper's Table II, measured on the real services; the same for the rover.

One lockstep run of the scenario's physics, sensors and controller (:mod:`hilsim.tools.tuning.rig`):
each joint in turn gets a step of its reference from the home pose, with the scenario's gains,
and its TRUE position (``truth/joint_states``) gives rise time (10–90 %), settling time (2 %),
peak time, overshoot and steady-state error (:mod:`hilsim.tools.tuning.metrics`). Printed beside the
paper's figures, written as CSV, as a PNG (one panel per joint) and as a Rerun recording; or,
with ``--json``, one JSON object.

The rover (``four_wheel_steer``): its steering loops (angle, position loops) get a step of
``--step`` rad and its traction loops (wheel speed, velocity loops) one of ``--speed`` rad/s,
through its controller's kinematic layer (:mod:`hilsim.tools.tuning.rig`), all four wheels of a kind at
once; a traction loop's response is the wheel's TRUE speed. The thesis gives no figures for its
loops (it only says they were tuned by Ziegler–Nichols), so there is nothing to print beside them.

A scenario with hardware in the loop (``hilsim report step config/hil/arm-can-emulated.yaml``, or
``--hil FILE``) is measured the same way in realtime, with its hardware: a joint served by a drive is
measured on what the drive's encoder reported (physics follows it), so the same table compares a
drive and its twin (``hilsim identify``, docs/hil.md).

The paper does not say how large its steps were; the default is 0.2 rad on joints 1–5, the
joints of its Table II (the drives stop accelerating at 2 rad/s, the URDF's velocity limit, so
a 0.5 rad step needs about 0.25 s and could never match the paper's 0.18 s on joint_4).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hilsim.core.config import ConfigError, Scenario
from hilsim.tools.tuning.metrics import ZERO_OVERSHOOT, ZERO_TOL, Figures, step_figures
from hilsim.tools.tuning.rig import Experiment, Response, rig_command
from hilsim.tools.tuning.rig_run import loop_scenario, run_experiments

DEFAULT_STEP = 0.2  # [rad] (see above: the drives stop at 2 rad/s)
DEFAULT_JOINTS = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5")
DEFAULT_SPEED = 2.0  # [rad/s] the rover's traction step: 0.3 m/s on its 0.15 m wheels
ROVER_LOOPS = ("steering", "traction")  # the rover's default: every wheel's loops of both kinds
# A rover loop's "no overshoot" and "at the target" for the peak time, relative to its step: the
# truth of a wheel's speed ripples by ~0.2 % as it rolls, which an absolute 1e-3 would call motion
ROVER_ZERO = 0.005

# The paper's Table II ("Response performance of joint controller"): rise time, adjustment
# (settling) time, peak time [s], overshoot, steady-state error; joint_6 has no row.
PAPER_TABLE_II: dict[str, tuple[float, float, float, float, float]] = {
    "joint_1": (0.50, 0.58, 0.61, 0.0, 0.0),
    "joint_2": (0.89, 1.00, 1.10, 0.0, 0.0),
    "joint_3": (0.71, 0.78, 0.80, 0.0, 0.0),
    "joint_4": (0.18, 0.18, 0.20, 0.0, 0.0),
    "joint_5": (0.32, 0.38, 0.40, 0.0, 0.0),
}


@dataclass
class Row:
    joint: str
    figures: Figures
    response: Response

    @property
    def velocity(self) -> bool:
        """A velocity loop (a rover's traction): step, error and response in rad/s."""
        return self.response.quantity == "velocity"

    @property
    def unit(self) -> str:
        return "rad/s" if self.velocity else "rad"


# The paper's overshoot and steady-state error are 0; ours are compared within these tolerances
# (hilsim.tools.tuning.metrics), and every verdict says so
TOLERANCE = (f"tolerance: overshoot <= {ZERO_OVERSHOOT * 1e3:g} mrad past the target, "
             f"steady-state error < {ZERO_TOL:g} rad")


def shortfalls(joint: str, f: Figures) -> list[str]:
    """What keeps a joint's figures from being at or better than the paper's row for it:
    rise and settling no slower than the paper's, overshoot 0 (at most ``ZERO_OVERSHOOT`` rad),
    steady-state error below ``ZERO_TOL``. Empty when it meets them all."""
    out = []
    paper = PAPER_TABLE_II.get(joint)
    if paper is not None:
        if not f.rise_time_s <= paper[0]:
            out.append(f"rise {f.rise_time_s:.3f} s > {paper[0]:.2f} s")
        if not f.settling_time_s <= paper[1]:
            out.append(f"settling {f.settling_time_s:.3f} s > {paper[1]:.2f} s")
    beyond = f.overshoot_pct / 100.0 * abs(f.step)  # [rad] past the target
    if not beyond <= ZERO_OVERSHOOT:
        out.append(f"overshoot {f.overshoot_pct:.3f} % ({beyond * 1e3:.2f} mrad) > {ZERO_OVERSHOOT * 1e3:g} mrad")
    if not f.steady_state_error < ZERO_TOL:
        out.append(f"steady-state error {f.steady_state_error:.2e} rad >= {ZERO_TOL:g} rad")
    return out


def verdict(joint: str, f: Figures) -> str:
    """``yes`` (at or better than the paper's row, its 0 overshoot and error met exactly), ``within
    tolerance`` (the same, but overshoot or steady-state error above 0, within :data:`TOLERANCE`), or
    ``no: …`` with what falls short."""
    miss = shortfalls(joint, f)
    if miss:
        return "no: " + "; ".join(miss)
    return "within tolerance" if f.overshoot_pct > 0 or f.steady_state_error > 0 else "yes"


def summary_line(rows: Sequence[Row]) -> str:
    """The report's last word on the paper's joints: ``yes`` only if every figure is at or better
    than the paper's exactly; ``within tolerance`` (said with the tolerance) if overshoot or error
    needed it; else ``no``."""
    said = [verdict(r.joint, r.figures) for r in rows if r.joint in PAPER_TABLE_II]
    if any(v.startswith("no") for v in said):
        word = "no"
    elif all(v == "yes" for v in said):
        word = "yes"
    else:
        word = (f"yes within tolerance (rise and settling at or better than the paper's; its 0 overshoot and "
                f"steady-state error met within {TOLERANCE.removeprefix('tolerance: ')})")
    return f"at or better than the paper on every joint: {word}"


def is_rover(sc: Scenario) -> bool:
    return sc.controller.type == "four_wheel_steer"


def default_joints(robot: str, overrides: dict | None = None, overlays: Sequence[str] = ()) -> list[str]:
    """The paper's Table II joints for the built-in arm; every steering and traction loop for the rover; every
    joint of any other robot (an imported arm has no joint_1 … joint_5)."""
    sc = loop_scenario(robot, overrides, overlays)
    if is_rover(sc):
        return list(ROVER_LOOPS)
    from hilsim.sim import control

    names = list(control.joint_table(sc.world.model).names)
    return list(DEFAULT_JOINTS) if all(j in names for j in DEFAULT_JOINTS) else names


def _traction(name: str) -> bool:
    return name == "traction" or name.endswith("_traction")


def measure(robot: str, joints: Sequence[str], step: float, *, speed: float = DEFAULT_SPEED,
            measure_s: float = 1.5, settle_s: float = 1.0, overrides: dict | None = None, progress: bool = False,
            run_dir: Path | None = None, overlays: Sequence[str] = (), steps: Sequence[float] = ()) -> list[Row]:
    """Step each joint (the rover: each kind of loop, or one loop) in turn, in one run (lockstep; realtime
    with hardware in the loop), and compute its figures; ``speed`` is the rover's traction step [rad/s];
    ``steps``: several steps of each joint instead of ``step``, in turn."""
    sc = loop_scenario(robot, overrides, overlays)
    rover = is_rover(sc)
    sizes = list(steps) or [step]
    exps = [Experiment(j, speed if rover and _traction(j) else s, measure=measure_s, settle=settle_s)
            for j in joints for s in sizes]

    def say(done: int, total: int) -> None:
        print(f"  {exps[done - 1].joint}: measured ({done}/{total})", flush=True)

    rs = run_experiments(sc, exps, run_dir=run_dir, progress=say if progress else None)
    return figures_of(rs, rover)


def figures_of(rs: Sequence[Response], rover: bool = False) -> list[Row]:
    """The Table II figures of measured responses."""
    rows = []
    for r in rs:
        if rover:
            z = ROVER_ZERO * abs(r.target - r.y0)
            f = step_figures(r.t, r.y, r.y0, r.target, zero_tol=z, zero_overshoot=z)
        else:
            f = step_figures(r.t, r.y, r.y0, r.target)
        rows.append(Row(r.name, f, r))
    return rows


def _s(v: float, nd: int = 3) -> str:
    return f"{v:.{nd}f}" if math.isfinite(v) else "never"


def format_table(rows: Sequence[Row]) -> str:
    """Ours beside the paper's, one line per joint (markdown); the rover's loops have no seed figures."""
    if not any(r.joint in PAPER_TABLE_II for r in rows):
        return _plain_table(rows)
    lines = [
        "| joint | rise (s) ours / paper | settling 2 % (s) ours / paper | peak (s) ours / paper "
        f"| overshoot ours / paper | steady-state error (rad) ours / paper | at or better ({TOLERANCE}) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        f, p = r.figures, PAPER_TABLE_II.get(r.joint)
        pp = [f"{x:.2f}" for x in p[:3]] if p else ["—"] * 3
        po, pe = ("0", "0") if p else ("—", "—")
        lines.append(
            f"| {r.joint} | {_s(f.rise_time_s)} / {pp[0]} | {_s(f.settling_time_s)} / {pp[1]} | "
            f"{_s(f.peak_time_s)} / {pp[2]} | {f.overshoot_pct:.3f} % / {po} | {f.steady_state_error:.1e} / {pe} | "
            f"{verdict(r.joint, f)} |"
        )
    return "\n".join(lines)


def _plain_table(rows: Sequence[Row]) -> str:
    lines = [
        "| loop | kind | step | rise (s) | settling 2 % (s) | peak (s) | overshoot | steady-state error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        f = r.figures
        kind = "speed (velocity loop)" if r.velocity else "angle (position loop)"
        lines.append(f"| {r.joint} | {kind} | {f.step:.3f} {r.unit} | {_s(f.rise_time_s)} | {_s(f.settling_time_s)} | "
                     f"{_s(f.peak_time_s)} | {f.overshoot_pct:.2f} % | {f.steady_state_error:.1e} {r.unit} |")
    return "\n".join(lines)


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None  # JSON has no infinity: "never" is null


def as_json(robot: str, rows: Sequence[Row]) -> dict:
    """One object; a velocity loop's step and error are ``step_rad_s``, ``steady_state_error_rad_s``."""
    out = []
    for r in rows:
        u = "rad_s" if r.velocity else "rad"
        out.append({
            "joint": r.joint,
            f"step_{u}": r.figures.step,
            "rise_time_s": _num(r.figures.rise_time_s),
            "settling_time_s": _num(r.figures.settling_time_s),
            "peak_time_s": _num(r.figures.peak_time_s),
            "overshoot_pct": r.figures.overshoot_pct,
            f"steady_state_error_{u}": r.figures.steady_state_error,
        })
    return {"robot": robot, "joints": out}


def write_csv(path: Path, rows: Sequence[Row]) -> None:
    if not any(r.joint in PAPER_TABLE_II for r in rows):
        return _plain_csv(path, rows)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["joint", "step_rad", "rise_time_s", "settling_time_s", "peak_time_s", "overshoot_pct",
                    "steady_state_error_rad", "paper_rise_time_s", "paper_settling_time_s", "paper_peak_time_s",
                    "at_or_better_than_paper", "verdict"])
        for r in rows:
            f_, p = r.figures, PAPER_TABLE_II.get(r.joint)
            w.writerow([r.joint, f"{f_.step:.6f}", f"{f_.rise_time_s:.6f}", f"{f_.settling_time_s:.6f}",
                        f"{f_.peak_time_s:.6f}", f"{f_.overshoot_pct:.6f}", f"{f_.steady_state_error:.3e}",
                        *([f"{x:.2f}" for x in p[:3]] if p else ["", "", ""]), int(not shortfalls(r.joint, f_)),
                        f"{verdict(r.joint, f_)} ({TOLERANCE})"])


def _plain_csv(path: Path, rows: Sequence[Row]) -> None:
    """Loops without seed figures (the rover's): each with its unit (rad, or rad/s for a velocity loop)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["joint", "quantity", "unit", "step", "rise_time_s", "settling_time_s", "peak_time_s",
                    "overshoot_pct", "steady_state_error"])
        for r in rows:
            f_ = r.figures
            w.writerow([r.joint, r.response.quantity, r.unit, f"{f_.step:.6f}", f"{f_.rise_time_s:.6f}",
                        f"{f_.settling_time_s:.6f}", f"{f_.peak_time_s:.6f}", f"{f_.overshoot_pct:.6f}",
                        f"{f_.steady_state_error:.3e}"])


def write_png(path: Path, robot: str, rows: Sequence[Row]) -> None:
    """One panel per joint: the true position against the commanded step, the 2 % band, the figures."""
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    n = len(rows)
    cols = 4 if n % 4 == 0 and n > 4 else min(n, 3)  # the rover's eight loops: a row per kind
    nrows = math.ceil(n / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.4 * nrows), squeeze=False)
    for ax, r in zip(axes.flat, rows, strict=False):
        resp, f = r.response, r.figures
        ax.plot(resp.t, resp.y, lw=1.4, label="truth")
        ax.axhline(resp.target, color="k", lw=0.8, ls="--", label="reference")
        band = 0.02 * abs(f.step)
        ax.axhspan(resp.target - band, resp.target + band, color="0.85", zorder=0, label="2 % band")
        if math.isfinite(f.settling_time_s):
            ax.axvline(f.settling_time_s, color="tab:green", lw=0.8, ls=":", label="settled")
        ax.set_title(f"{r.joint}: rise {_s(f.rise_time_s, 2)} s, settle {_s(f.settling_time_s, 2)} s, "
                     f"OS {f.overshoot_pct:.2f} %", fontsize=9)
        ax.set_xlabel("time from the step [s]")
        ax.set_ylabel("speed [rad/s]" if r.velocity else "position [rad]")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(f"hilsim report step {robot}: step responses (physics truth)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def log_rerun(path: Path, robot: str, rows: Sequence[Row]) -> None:
    """The responses and their figures as a Rerun recording (analytics off)."""
    from hilsim.core.recording import disable_analytics

    disable_analytics()
    import rerun as rr

    rec = rr.RecordingStream("hilsim_step_report")
    rec.save(str(path))
    for r in rows:
        resp, f = r.response, r.figures
        times = rr.TimeColumn("time_from_step", duration=resp.t)
        rec.send_columns(f"step/{r.joint}/truth", indexes=[times], columns=rr.Scalars.columns(scalars=resp.y))
        ref = [resp.target] * len(resp.t)
        rec.send_columns(f"step/{r.joint}/reference", indexes=[times], columns=rr.Scalars.columns(scalars=ref))
        text = f"{r.response.quantity} loop, {r.unit}\n"
        text += "\n".join(f"{k}: {v:.6g}" for k, v in f.as_dict().items())
        if r.joint in PAPER_TABLE_II:
            text += f"\nat or better than the paper: {verdict(r.joint, f)} ({TOLERANCE})"
        rec.log(f"step/{r.joint}/figures", rr.TextDocument(text), static=True)
    rec.log("step/table", rr.TextDocument(format_table(rows), media_type=rr.MediaType.MARKDOWN), static=True)
    rec.flush()


@rig_command
def cmd_report_step(args: argparse.Namespace) -> int:
    from hilsim.core.scenario import parse_overrides
    from hilsim.launch.out_dirs import new_run_dir

    overrides = parse_overrides(args.set)
    joints = [j.strip() for j in args.joints.split(",") if j.strip()] if args.joints else \
        default_joints(args.robot, overrides, args.hil)
    if not joints:
        raise ConfigError("--joints: expected joint names, e.g. joint_1,joint_2 (the rover: steering,traction)")
    if not math.isfinite(args.step) or args.step == 0.0:
        raise ConfigError(f"--step {args.step}: expected a non-zero step in rad")
    if not math.isfinite(args.speed) or args.speed == 0.0:
        raise ConfigError(f"--speed {args.speed}: expected a non-zero wheel-speed step in rad/s")
    out = Path(args.out) if args.out else new_run_dir("runs", "step-report")
    out.mkdir(parents=True, exist_ok=True)
    hil = loop_scenario(args.robot, overrides, args.hil).external_servers()
    if not args.json:
        speed = f", {args.speed:g} rad/s on traction loops" if any(_traction(j) for j in joints) else ""
        how = (f"real services with {', '.join(hil)}, realtime, physics truth (a drive's joint: its encoder)" if hil
               else "real services, lockstep, physics truth")
        print(f"hilsim report step {args.robot}: {args.step:g} rad steps{speed} on {', '.join(joints)} "
              f"({how})", flush=True)
    rows = measure(args.robot, joints, args.step, speed=args.speed, measure_s=args.measure, settle_s=args.settle,
                   progress=not args.json, run_dir=out / "services", overrides=overrides, overlays=args.hil)
    write_csv(out / "step_report.csv", rows)
    write_png(out / "step_report.png", args.robot, rows)
    log_rerun(out / "step_report.rrd", args.robot, rows)
    if args.json:
        print(json.dumps(as_json(args.robot, rows)))
        return 0
    print(format_table(rows))
    if any(r.joint in PAPER_TABLE_II for r in rows):
        print(summary_line(rows))
    elif is_rover(loop_scenario(args.robot, overrides, args.hil)):
        print("the thesis gives no figures for its wheel loops (tuned by Ziegler–Nichols): nothing to compare")
    print(f"written: {out / 'step_report.csv'}, {out / 'step_report.png'}, {out / 'step_report.rrd'}")
    return 0
