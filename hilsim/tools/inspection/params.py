"""``hilsim gains ROBOT [JOINT.GAIN=VALUE …]``: read or change the controller gains of a running simulation.

- Without assignments: the gains the controller runs with, per joint (``kp ki kd i_limit output_limit
  feedforward``), read from the run's files: its resolved ``scenario.yaml`` and the live changes its
  controller keeps (``<run dir>/state/controller.json``, written at each change for a restart).
- With assignments: each is checked against the run's joints and the controller's own rule for gains
  (:func:`hilsim.sim.control.check_gain`) before anything is sent (exit code 2, as every tool's usage
  error); then a SetParameters request goes to ``<prefix>/<robot>/controller/set_parameters``, the
  controller applies all changes at its next control step, or none (with the reason), and each change is
  printed ``  joint_2.kp: 32.81 -> 80``.

No run of yours up: exit code 2 (``hilsim goal`` and ``topic`` alike). The controller not answering: 1.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import zenoh

from hilsim.core import msgs, run_finder, transport
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys
from hilsim.core.restart import STATE_DIR
from hilsim.sim.control import GAIN_FIELDS, check_gain, check_parameter, gains_for

USAGE = "expected JOINT.GAIN=NUMBER, a joint's name first, e.g. joint_2.kp=80"


def set_parameters(session: zenoh.Session, keys: Keys, values: dict[str, float],
                   timeout: float = 10.0) -> msgs.SetParametersResult:
    if not transport.wait_for_service(session, keys, "controller", timeout):
        return msgs.SetParametersResult(successful=False, reason="no controller is running")
    req = msgs.SetParameters(parameters=[msgs.Parameter(name=k, value=v) for k, v in values.items()])
    for reply in session.get(keys.topic("controller/set_parameters"), payload=msgs.encode(req), timeout=timeout):
        if reply.ok is not None:
            return msgs.decode(msgs.SetParametersResult, reply.ok.payload.to_bytes())
        return msgs.SetParametersResult(successful=False, reason=reply.err.payload.to_string())
    return msgs.SetParametersResult(successful=False, reason="the controller did not answer")


def run_gains(run_dir: Path, robot: str) -> dict[str, dict[str, float | None]]:
    """The gains ``robot``'s controller runs with in the run in ``run_dir``, per joint in model order: the
    scenario's, then the live changes its controller kept. ConfigError if the run's files cannot say."""
    from hilsim.core.scenario import load_scenario, model_joints

    try:
        sc = load_scenario(str(run_dir / "scenario.yaml"))
    except (OSError, ConfigError) as e:
        raise ConfigError(f"the gains of {run_dir}: {str(e).splitlines()[0]}") from None
    names = model_joints(sc)
    table = {n: {f: getattr(g, f) for f in GAIN_FIELDS} for n, g in zip(names, gains_for(sc.controller.gains, names),
                                                                         strict=True)}
    for state in (run_dir / STATE_DIR / f"controller@{robot}.json", run_dir / STATE_DIR / "controller.json"):
        try:
            live = json.loads(state.read_text()).get("gains", {})
        except (OSError, ValueError):
            continue
        for name, value in live.items():
            joint, _, field = name.rpartition(".")
            if joint in table and field in GAIN_FIELDS:
                table[joint][field] = float(value)
        break
    return table


def _parse(assignments: list[str]) -> dict[str, float] | str:
    values: dict[str, float] = {}
    for item in assignments:
        name, sep, val = item.partition("=")
        try:
            v = float(val)
        except ValueError:
            v = math.nan
        joint, dot, field = name.strip().rpartition(".")
        if not sep or not dot or not joint or not field or not math.isfinite(v):
            return f"{item!r}: {USAGE}"
        why = check_gain(name.strip(), field, v)  # the controller's own rule, before connecting anywhere
        if why is not None:
            return why
        values[name.strip()] = v
    return values


def _show(v: float | None) -> str:
    return "none" if v is None else f"{v:g}"


def cmd_gains(args: argparse.Namespace) -> int:
    parsed = _parse(args.assignments)
    if isinstance(parsed, str):
        print(f"hilsim gains: {parsed}", file=sys.stderr)
        return 2
    target = run_finder.tool_target(args.connect, getattr(args, "run", None), "hilsim gains")
    table = run_gains(target.run.run_dir, args.robot) if target.run is not None else None
    if not parsed:  # read back
        if table is None:
            print("hilsim gains: no run of yours is up (start one: hilsim up arm --interactive; or name it with "
                  "--run DIR): the gains are read from its files", file=sys.stderr)
            return 2
        print(f"hilsim gains: {target.describe()}", file=sys.stderr)
        print("joint      " + " ".join(f"{f:>12}" for f in GAIN_FIELDS))
        for joint, gains in table.items():
            print(f"{joint:<10} " + " ".join(f"{_show(gains[f]):>12}" for f in GAIN_FIELDS))
        return 0
    if table is not None:  # the run is known: every joint checked before anything is sent
        for name, value in parsed.items():
            why = check_parameter(name, value, list(table))
            if isinstance(why, str):
                print(f"hilsim gains: {why}", file=sys.stderr)
                return 2
    keys = run_finder.tool_keys(args.robot, args.prefix)
    with run_finder.open_tool_session(args.connect, run=target.run.run_dir if target.run else None,
                                tool="hilsim gains") as ses:
        res = set_parameters(ses, keys, parsed)
    if not res.successful:
        print("not set: " + res.reason)
        return 1
    print("set: " + res.reason)
    for name, value in parsed.items():
        joint, _, field = name.rpartition(".")
        if table is not None and joint in table:
            print(f"  {name}: {_show(table[joint][field])} -> {value:g}")
        else:  # a run not of yours (--connect to another router): its files are not here to say the old value
            print(f"  {name}: -> {value:g}")
    return 0
