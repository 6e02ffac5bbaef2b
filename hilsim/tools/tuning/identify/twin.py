"""The twin: a scenario file in which each identified joint is simulated as its drive responded.

The file ``extends:`` the scenario the drive was identified with (and its overlays), so it changes
nothing else, and holds no hardware: each identified joint is served by ``sim`` with its
``drive:`` (:class:`hilsim.core.config.DriveConfig`, simulated by physics in lockstep,
:mod:`hilsim.sim.drive`), the clock is lockstep, and the services that stood in for the drives
(``drive-emulator``, ``motor-model``) are not started. Overrides given on the command line are
carried over, except those of the hardware's own sections.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from hilsim.core.config import DEFAULT_SERVICES, ConfigError, Scenario
from hilsim.core.scenario import set_dotted
from hilsim.tools.tuning.identify.fit import Fit

# the services that stand in for a joint's drive, and the hardware bridges: not in a twin
JOINT_HARDWARE = ("drive-emulator", "motor-model", "bridge-can")
HARDWARE_SECTIONS = (*JOINT_HARDWARE, "bridge-mavlink", "gps-emulator")


def twin_data(sc: Scenario, fits: Sequence[Fit], bases: Sequence[Path], at: Path,
              overrides: dict[str, Any] | None = None, from_run: bool = False) -> dict[str, Any]:
    """The twin file's content, for a file written at ``at``."""
    where = at.resolve().parent
    # relative to the twin (a twin beside its scenario moves with it); absolute when they share no folder
    ext = [os.path.relpath(b, where) if os.path.commonpath([b, where]) != os.sep else str(b)
           for b in (Path(x).resolve() for x in bases)]
    services = [s for s in sc.services if s not in JOINT_HARDWARE] or list(DEFAULT_SERVICES)
    data: dict[str, Any] = {"extends": ext[0] if len(ext) == 1 else ext, "name": f"{sc.name}-twin",
                            "clock": {"mode": "lockstep"}, "services": services}
    for k, v in (overrides or {}).items():
        head = k.split(".")[0]
        if head in HARDWARE_SECTIONS or k.startswith("joints.") or head in ("zenoh", "logger", "clock"):
            continue
        set_dotted(data, k, v)
    if from_run:  # a run's own scenario.yaml: its router and run directory were that run's
        data["zenoh"] = {"auth": None, "connect": ["tcp/127.0.0.1:7447"]}
        data["logger"] = {"run_dir": None}
        data["duration"] = None
    joints: dict[str, Any] = {}
    for f in fits:
        d = f.drive
        drive: dict[str, Any] = {"order": d.order, "dead_time": _r(d.dead_time)}
        if d.order == 2:
            drive.update(natural_frequency=_r(d.natural_frequency), damping_ratio=_r(d.damping_ratio))
        else:
            drive["time_constant"] = _r(d.time_constant)
        for k in ("max_velocity", "max_acceleration"):
            if math.isfinite(getattr(d, k)):
                drive[k] = _r(getattr(d, k))
        drive.update(resolution=_r(d.resolution), period=_r(d.period))
        joints[f.joint] = {"interface": f.interface, "server": "sim", "drive": drive}
    data["joints"] = joints
    return data


def _r(x: float) -> float:
    """Six significant digits: the fit's uncertainty is far larger."""
    return float(f"{x:.6g}")


def write_twin(path: Path, data: dict[str, Any], fits: Sequence[Fit], source: str) -> None:
    """Write the twin file with a header saying what it is and where it came from."""
    lines = [
        f"# The twin of {source}: {', '.join(f.joint for f in fits)} simulated in lockstep by physics as the",
        f"# drive responded (hilsim identify, {_dt.datetime.now().isoformat(timespec='seconds')}; docs/hil.md).",
        "# No hardware: each joint's drive is a model (hilsim/sim/drive.py) with the fitted parameters;",
    ]
    for f in fits:
        fitted = ", ".join(f"{k} {getattr(f.drive, k):.4g} ± {f.sigma.get(k, math.nan):.2g}" for k in f.fitted_names())
        lines.append(f"#   {f.joint}: {fitted}; residual RMS {f.rms:.2e}")
    lines.append("")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + yaml.safe_dump(data, sort_keys=False))
    except OSError as e:
        raise ConfigError(f"--write {path}: cannot write: {e.strerror}") from None
