"""``hilsim gains ROBOT joint_2.kp=80 …``: change controller gains of a running simulation.

Sends a SetParameters request to ``<prefix>/<robot>/controller/set_parameters``; the
controller applies all changes at its next control step, or none (with the reason).
"""

from __future__ import annotations

import argparse
import math

import zenoh

from hilsim.core import msgs, runs, transport
from hilsim.core.keys import Keys


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


def cmd_gains(args: argparse.Namespace) -> int:
    values: dict[str, float] = {}
    for item in args.assignments:
        name, sep, val = item.partition("=")
        try:
            v = float(val)
        except ValueError:
            v = math.nan
        if not sep or not math.isfinite(v):
            print(f"hilsim gains: {item!r}: expected JOINT.GAIN=NUMBER, e.g. joint_2.kp=80")
            return 2
        values[name.strip()] = v
    keys = runs.tool_keys(args.robot, args.prefix)
    with runs.open_tool_session(args.connect, run=getattr(args, "run", None), tool="hilsim gains") as ses:
        res = set_parameters(ses, keys, values)
    print(("set: " if res.successful else "not set: ") + res.reason)
    return 0 if res.successful else 1
