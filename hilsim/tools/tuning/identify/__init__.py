"""``hilsim identify SCENARIO|RUN_DIR --joints J[,…] [--write FILE] [--json]``: a real drive's response,
fitted from data, and a twin that responds the same (docs/hil.md).

With a scenario whose joints are served by hardware (e.g. ``config/hil/arm-can-emulated.yaml``, or a real
ODrive on ``can0``):

1. **the drive** (:mod:`.plan`, :mod:`hilsim.tools.tuning.rig`): one realtime run of the scenario's physics,
   sensors, controller and hardware, recorded like any run (``<out>/drive/``, its bag): each joint's
   excitation (steps of several sizes and both signs, a chirp) through the normal command path, then
   the motions the twin is proved on (steps of 0.2 and 1.0 rad, the joint's part of the task's targets);
2. **the fit** (:mod:`.data`, :mod:`.fit`): from the bag, on the excitation only: dead time, closed-loop
   order and dynamics, velocity and acceleration limits, the encoder's quantum and period, with the
   residuals and each parameter's uncertainty;
3. **the twin** (:mod:`.twin`): a scenario file (``--write FILE``, default ``<out>/twin.yaml``) that
   extends the scenario, without hardware, each joint simulated in lockstep by physics as its drive;
4. **the proof** (:mod:`.compare`): the same validation motions on the twin file, lockstep; the figures
   of both, compared (exit status 1 when the twin does not match).

With a run directory (``hilsim identify runs/<run> --joints joint_1``), a past HIL run's bag is fitted
as it is (whatever motion it holds; a limit it never reached is said so), and ``--write`` writes the
twin of that run's scenario.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from hilsim.core.config import SIM, ConfigError, Scenario
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario, parse_overrides
from hilsim.sim import control
from hilsim.tools.tuning.identify.compare import (
    StepComparison,
    TrackComparison,
    compare_steps,
    compare_tracks,
    table,
    write_responses,
)
from hilsim.tools.tuning.identify.data import read_joints, run_scenario
from hilsim.tools.tuning.identify.fit import LIMITS, Fit, FitError, fit_record
from hilsim.tools.tuning.identify.plan import excitation, is_rover, validation
from hilsim.tools.tuning.identify.twin import twin_data, write_twin
from hilsim.tools.tuning.rig import Response, RigError, rig_command
from hilsim.tools.tuning.rig_run import loop_scenario, run_experiments


def _joints(text: str) -> list[str]:
    joints = [j.strip() for j in text.split(",") if j.strip()]
    if not joints:
        raise ConfigError("--joints: expected joint names, e.g. joint_1")
    return joints


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.json:
        print(text, flush=True)


def fit_summary(f: Fit) -> str:
    """One joint's fit in a few lines: the model, each parameter ± 1σ, the limits, the residual."""
    d = f.drive
    law = (f"order 2: natural frequency {d.natural_frequency:.4g} ± {f.sigma.get('natural_frequency', 0):.2g} rad/s, "
           f"damping ratio {d.damping_ratio:.4g} ± {f.sigma.get('damping_ratio', 0):.2g}" if d.order == 2 else
           f"order 1: time constant {d.time_constant * 1e3:.4g} ± {f.sigma.get('time_constant', 0) * 1e3:.2g} ms")
    dead = f"dead time {d.dead_time * 1e3:.4g} ± {f.sigma['dead_time'] * 1e3:.2g} ms"
    if f.own_dead_time is not None and f.way is not None:
        dead += (f" (the drive's own {f.own_dead_time * 1e3:.3g} ms, the way to it {f.way[0] * 1e3:.3g} ms: its "
                 f"median; 95 % within {f.way[1] * 1e3:.3g} ms)")
    out = [f"{f.joint} ({f.interface}): {dead}, {law}"]
    unit = {"max_velocity": ("velocity", "rad/s"), "max_acceleration": ("acceleration", "rad/s²")}
    lims = []
    for k in LIMITS:
        what, u = unit[k]
        lims.append(f"{what} limit {getattr(d, k):.4g} ± {f.sigma[k]:.2g} {u}" if f.reached[k] else
                    f"no {what} limit reached (largest seen {f.seen[what]:.3g} {u})")
    out.append("  " + "; ".join(lims))
    enc = f"quantum {d.resolution:.3g} rad" if d.resolution else "no quantum (exact to 1e-6 rad)"
    out.append(f"  encoder: {enc}, a report every {d.period * 1e3:.3g} ms; residual RMS {f.rms:.3g} "
               f"(max {f.residual_max:.3g}) over {f.n} reports, against a motion of RMS {f.motion_rms:.3g}")
    if (why := f.starved()) is not None:
        out.append(f"  warning: {why}")
    return "\n".join(out)


@rig_command
def cmd_identify(args: argparse.Namespace) -> int:
    joints = _joints(args.joints)
    for name in ("scale", "measure"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"--{name} {v}: expected a positive number")
    source = Path(args.scenario)
    if source.is_dir():
        return _from_run(args, source, joints)
    return _from_scenario(args, joints)


def _fit_all(args: argparse.Namespace, recs: dict[str, Any]) -> list[Fit]:
    fits = []
    for j, r in recs.items():
        _say(args, f"fitting {j} ({r.out_t.size} steps, {r.cmd_t.size} setpoints):")
        try:
            fits.append(fit_record(r, progress=lambda s: _say(args, f"  {s}")))
        except FitError as e:
            raise RigError(str(e)) from None
        _say(args, fit_summary(fits[-1]))
    return fits


def _from_run(args: argparse.Namespace, run_dir: Path, joints: list[str]) -> int:
    """A past run's bag, fitted as it is; ``--write``: the twin of that run's scenario."""
    sc = run_scenario(run_dir)
    if args.write:
        _all_hardware(sc, joints)
    _say(args, f"hilsim identify {run_dir}: {', '.join(joints)} from the run's bag")
    fits = _fit_all(args, read_joints(run_dir, joints))
    written = None
    if args.write:
        written = Path(args.write)
        write_twin(written, twin_data(sc, fits, [run_dir / "scenario.yaml"], written, from_run=True), fits,
                   str(run_dir))
        _say(args, f"written: {written}")
    if args.json:
        print(json.dumps({"run": str(run_dir), "fits": [f.as_json() for f in fits],
                          "twin": str(written) if written else None}))
    return 0


def _from_scenario(args: argparse.Namespace, joints: list[str]) -> int:
    from hilsim.launch.out_dirs import new_run_dir

    overrides = parse_overrides(args.set)
    full = load_scenario(args.scenario, overrides, args.hil)
    names = control.joint_table(full.world.model).names
    for j in joints:
        if j not in names:
            raise ConfigError(f"--joints: {j} is not a joint of {full.world.model.name} (joints: {', '.join(names)})")
        if full.joint(j).server == SIM:
            raise ConfigError(f"{full.source}: joints.{j}.server: sim; hilsim identify needs the joint served by its "
                              f"drive (a scenario with hardware in the loop, e.g. config/hil/arm-can-emulated.yaml)")
    _all_hardware(full, joints)
    # the bridge says when each setpoint went on the bus: the drive's own dead time, apart from the way to it
    extra = {"bridge-can.setpoints": True} if "bridge-can" in full.external_servers() else {}
    sc = loop_scenario(args.scenario, {**overrides, **extra}, args.hil, record=True)
    sc.logger.record = record_keys(sc)
    out = Path(args.out) if args.out else new_run_dir("runs", "identify")
    for d in ("drive", "twin"):
        if (out / d).exists():
            raise ConfigError(f"--out {out}: {out / d} exists (a previous identify's run): give a new directory")
    home = _homes(sc, joints)
    exc = [e for j in joints for e in excitation(sc, j, home[j], args.scale)]
    val = validation(full, joints, home, args.measure)
    _say(args, f"hilsim identify {args.scenario}: {', '.join(joints)} on {', '.join(full.external_servers())}; "
               f"the drive in {out / 'drive'} (realtime, recorded)")
    drive = run_experiments(sc, [*exc, *val], run_dir=out / "drive", progress=_progress(args, len(exc) + len(val)))
    recs = read_joints(out / "drive", joints)
    windows: dict[str, tuple[float, float]] = {}  # each joint's excitation: from its first start to its last end
    for r in drive[: len(exc)]:
        t0, t1 = windows.get(r.name, (r.start, r.start))
        windows[r.name] = (min(t0, r.start), max(t1, r.start + float(r.t[-1])))
    fits = _fit_all(args, {j: recs[j].window(*windows[j]) for j in joints})
    twin_path = Path(args.write) if args.write else out / "twin.yaml"
    bases = [Path(full.source or args.scenario), *map(Path, args.hil)]
    write_twin(twin_path, twin_data(full, fits, bases, twin_path, overrides), fits, str(args.scenario))
    _say(args, f"written: {twin_path}; the twin measured in {out / 'twin'} (lockstep)")
    tsc = loop_scenario(str(twin_path))
    twin = run_experiments(tsc, val, run_dir=out / "twin", progress=_progress(args, len(val)))
    steps, tracks = _compare(drive[len(exc):], twin, is_rover(full))
    for r in drive[len(exc):]:
        if r.lost:
            _say(args, f"not measured: {r.lost}")
    write_responses(out, *zip(*[(d, t) for d, t in zip(drive[len(exc):], twin, strict=True)
                                if not (d.lost or t.lost)], strict=True))
    ok = all(s.ok for s in steps) and all(t.ok for t in tracks)
    if args.json:
        lost = [r.lost for r in drive[len(exc):] if r.lost] + [r.lost for r in twin if r.lost]
        print(json.dumps({**_as_json(args, out, twin_path, fits, steps, tracks, ok), "not_measured": lost}))
    else:
        print(table(steps, tracks))
        print(f"the twin responds as the drive did: {'yes' if ok else 'no'}")
        print(f"written: {out / 'comparison.csv'}, {out / 'comparison.png'}")
    return 0 if ok else 1


def record_keys(sc: Scenario) -> list[str]:
    """What the drive's run records: what the fit and the proof read, and the services' health and logs
    (the recorder's load kept small: on a busy machine it would delay the drive's reports)."""
    k = Keys.of(sc)
    names = ("joint_commands", "truth/joint_states", "controller/reference", "joint_trajectory",
             "planner/joint_trajectory", "hw", "health", "log")
    return [f"{k.topic_name(n).strip('/')}/**" for n in names]


def _all_hardware(sc: Scenario, joints: list[str]) -> None:
    """Every joint served by hardware is one to identify: the twin holds no hardware."""
    others = [n for n in sc.joints if n != "default" and sc.joint(n).server != SIM and n not in joints]
    if others:
        raise ConfigError(f"{sc.source}: joints {', '.join(others)} are served by hardware too: identify them as "
                          f"well (--joints {','.join([*joints, *others])}), so that the twin has no hardware")


def _homes(sc: Scenario, joints: list[str]) -> dict[str, float]:
    from hilsim.tools.tuning.rig import _home

    names = list(control.joint_table(sc.world.model).names)
    h = _home(sc, names)
    return {j: float(h[names.index(j)]) for j in joints}


def _compare(drive: list[Response], twin: list[Response], rover: bool = False) -> tuple[
        list[StepComparison], list[TrackComparison]]:
    """Each step size of each joint (its repetitions together), each trajectory, drive against twin."""
    steps: dict[tuple[str, float], tuple[list[Response], list[Response]]] = {}
    tracks = []
    for d, t in zip(drive, twin, strict=True):
        if d.experiment.points:
            tracks.append(compare_tracks(d, t))
            continue
        pair = steps.setdefault((d.name, abs(d.experiment.step)), ([], []))
        if d.lost or t.lost:  # a repetition the controller took too late (realtime): the others decide
            continue
        pair[0].append(d)
        pair[1].append(t)
    for (j, size), (d, _) in steps.items():
        if not d:
            raise RigError(f"{j}: every repetition of the {size:g} step was taken too late by the controller "
                           f"(a busy machine): nothing to compare; run again")
    return [compare_steps(d, t, rover) for d, t in steps.values()], tracks


def _progress(args: argparse.Namespace, total: int) -> Any:
    if args.json:
        return None
    return lambda done, _n: print(f"  experiment {done}/{total} done", flush=True)


def _as_json(args: argparse.Namespace, out: Path, twin: Path, fits: list[Fit], steps: list[StepComparison],
             tracks: list[TrackComparison], ok: bool) -> dict[str, Any]:
    return {
        "scenario": args.scenario, "out": str(out), "drive_run": str(out / "drive"), "twin": str(twin),
        "comparison": str(out / "comparison.csv"),
        "fits": [f.as_json() for f in fits],
        "steps": [{"joint": s.joint, "step_rad": s.step, "checks": s.checks(), "match": s.ok} for s in steps],
        "trajectories": [{"joint": t.joint, "checks": t.checks(), "match": t.ok,
                          "tracking_error_rms_rad": {"drive": t.drive_error_rms, "twin": t.twin_error_rms}}
                         for t in tracks],
        "match": ok,
    }
