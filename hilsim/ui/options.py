"""What the panel can run: the scenarios of ``config/`` (not the overlays) and the arms a lab
imported (``robots/NAME/NAME.yaml`` beside where the panel runs: ``hilsim robot import``'s default
place), with their worlds, services, joints and joint limits (:class:`ScenarioOption`, what goals
and gains are checked against), and the planner library's names.

No Zenoh keys: read from YAML files only.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from hilsim.core.config import CONFIG_DIR, ConfigError, Scenario
from hilsim.core.scenario import load_scenario

log = logging.getLogger("hilsim.ui")


@dataclass
class ScenarioOption:
    name: str
    robot: str
    prefix: str
    mobile: bool  # a navigator takes map goals (the rover), else a planner joint/pose goals (the arm)
    worlds: list[str]
    services: list[str]
    clock: str
    targets: int
    planner: str  # the scenario's default planner ("" without a planner service)
    joints: list[str] = field(default_factory=list)
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        # JSON has no infinity: an unlimited joint gets ±π on its slider (it is a revolute joint)
        d["lower"] = [v if math.isfinite(v) else -math.pi for v in self.lower]
        d["upper"] = [v if math.isfinite(v) else math.pi for v in self.upper]
        return d


def _is_scenario_file(p: Path) -> bool:
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and ("services" in data or "extends" in data) and "planners" not in data


IMPORTED_DIR = Path("robots")  # hilsim robot import's default --out parent (hilsim.tools.robot)


def scenario_options(config_dir: Path = CONFIG_DIR, imported_dir: Path = IMPORTED_DIR) -> dict[str, ScenarioOption]:
    """The scenarios of ``config/`` (not the overlays), with their worlds, joints and limits; then the
    imported arms (``imported_dir/NAME/NAME.yaml``; its overlays, such as ``hil-can.yaml``, are not
    offered), named by their path, which is what ``hilsim up`` is given."""
    out: dict[str, ScenarioOption] = {}
    files = sorted(p for p in config_dir.glob("*.yaml") if _is_scenario_file(p))
    for p in files:
        try:
            sc = load_scenario(p)
        except ConfigError as e:
            log.warning("scenario %s not offered: %s", p, e)
            continue
        own = sc.world.model.stem
        variants = [q.stem[len(p.stem) + 1:] for q in files if q.stem.startswith(p.stem + "-")]
        worlds = [own, *[w for w in variants if _world_stem(config_dir / f"{p.stem}-{w}.yaml") == w]]
        opt = option_of(sc, p.stem, worlds)
        out[p.stem] = opt
    for p in sorted(imported_dir.glob("*/*.yaml")) if imported_dir.is_dir() else []:
        if p.stem != p.parent.name or not _is_scenario_file(p):
            continue
        try:
            out[str(p)] = option_of(load_scenario(p), str(p))
        except ConfigError as e:
            log.warning("imported arm %s not offered: %s", p, e)
    return out


def option_of(sc: Scenario, name: str, worlds: list[str] | None = None) -> ScenarioOption:
    """What the panel needs of a scenario: its robot, services, joints and their limits."""
    from hilsim.sim.control import joint_table

    opt = ScenarioOption(
        name=name, robot=sc.robot, prefix=sc.prefix, mobile="navigator" in sc.services,
        worlds=worlds or [sc.world.model.stem], services=sc.processes(), clock=sc.clock.mode,
        targets=len(sc.task.targets), planner=sc.planner.planner if "planner" in sc.services else "",
    )
    if not opt.mobile:
        jt = joint_table(sc.world.model)
        opt.joints, opt.lower, opt.upper = list(jt.names), jt.lower.tolist(), jt.upper.tolist()
    return opt


def _world_stem(path: Path) -> str | None:
    try:
        return load_scenario(path).world.model.stem
    except ConfigError:
        return None


def planner_names(config_dir: Path = CONFIG_DIR) -> list[str]:
    """The planner library's names (read as YAML: the panel does not load OMPL)."""
    try:
        data = yaml.safe_load((config_dir / "planners.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return []
    return sorted((data.get("planners") or {}).keys())
