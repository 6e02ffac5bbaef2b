"""What both evaluations share: the targets file, the criteria and the choice of the best plan, where
the CSV goes, and sending the chosen goal to a running system."""

from __future__ import annotations

from collections.abc import Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import yaml

from hilsim.core.config import ConfigError, Scenario
from hilsim.launch.out_dirs import new_run_dir
from hilsim.planning.scoring import best, check_criterion

if TYPE_CHECKING:
    from hilsim.core import msgs



class Scored(Protocol):
    """One planned target: whether it succeeded, and its two figures (smaller is better)."""

    @property
    def ok(self) -> bool: ...

    @property
    def length(self) -> float: ...

    @property
    def smoothness(self) -> float: ...


def read_targets(path: str | Path, *, what: str, form: str, lengths: Collection[int], each: str,
                 default_name: str) -> tuple[list[str], list[list[float]], dict[str, Any]]:
    """A targets file (YAML): ``targets: [form, …]`` (each a list of numbers, as long as one of
    ``lengths``; ``each`` says so in the error) and optional ``target_names`` (default
    ``<default_name>1``, ``<default_name>2``, …). Returns the names, the targets and the whole
    mapping (for the caller's own keys, e.g. ``start``)."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{p}: cannot read {what}: {e}") from None
    if not isinstance(data, dict) or not isinstance(data.get("targets"), list) or not data["targets"]:
        raise ConfigError(f"{p}: expected 'targets: [{form}, …]'")
    targets = []
    for i, t in enumerate(data["targets"]):
        if not isinstance(t, list) or len(t) not in lengths or not all(isinstance(v, int | float) for v in t):
            raise ConfigError(f"{p}: targets[{i}]: expected {each}")
        targets.append([float(v) for v in t])
    names = data.get("target_names") or [f"{default_name}{i + 1}" for i in range(len(targets))]
    if len(names) != len(targets):
        raise ConfigError(f"{p}: target_names has {len(names)} names for {len(targets)} targets")
    return [str(n) for n in names], targets, data


def choose(evals: Sequence[Scored], criterion: str) -> int | None:
    """Index of the best successful evaluation by the criterion (None if none succeeded): the one
    criterion of :mod:`hilsim.planning.scoring` (the smallest ``length``, ``smoothness``, or their
    normalised weighted sum)."""
    check_criterion(criterion)
    return best([e.ok for e in evals], [e.length if e.ok else np.nan for e in evals],
                [e.smoothness if e.ok else np.nan for e in evals], criterion)


def output_csv(sc: Scenario, csv: str | None, out: str | None) -> Path:
    """Where the CSV goes (the recording goes next to it): ``csv`` if given, else
    ``plan_evaluate.csv`` in ``out`` or in a new ``runs/<timestamp>-plan-evaluate/``."""
    if csv:
        path = Path(csv)
    else:
        d = Path(out) if out else new_run_dir(sc.logger.out_dir, "plan-evaluate")
        path = d / "plan_evaluate.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def execute(sc: Scenario, goal: msgs.MoveGoal, timeout: float, service: str) -> int:
    """Send the chosen goal to the running system's ``service`` (the planner or the navigator), print
    its feedback, and wait up to ``timeout`` s for its result: 0 if it succeeded."""
    from hilsim.core.keys import Keys
    from hilsim.core.transport import open_session
    from hilsim.planning.client import MoveClient

    session = open_session(sc.zenoh)
    client = MoveClient(session, Keys.of(sc), service=service)
    try:
        resp = client.send(goal)
        if not resp.accepted:
            print(f"execute: rejected: {resp.reason}")
            return 1
        res = client.wait(goal.goal_id, timeout,
                          on_feedback=lambda f: print(f"  {f.state:<10} {100 * f.progress:5.1f} %", flush=True))
        print(f"execute: {'succeeded' if res and res.success else 'failed'}: {res.message if res else 'no result'}")
        return 0 if res is not None and res.success else 1
    finally:
        client.close()
        session.close()
