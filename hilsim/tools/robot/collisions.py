"""The self-collision matrix of an imported arm, as MoveIt's Setup Assistant computes it: a pair of
links is disabled when the links are adjacent (a joint between them, or welded through fixed joints),
in contact at the default pose, in contact in (nearly) every sampled pose, or in none of them. A MoveIt
SRDF that names the robot gives its own ``disable_collisions`` instead (and its group states, read here
too).

Poses are sampled within the joint limits (continuous joints over one turn) with a seeded generator:
the same URDF gives the same matrix.
"""

from __future__ import annotations

import itertools
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from hilsim.tools.robot.urdf import ImportFailure, Urdf

ALWAYS = 0.95  # a pair in contact in at least this fraction of the samples is "always" in contact


@dataclass
class Srdf:
    path: Path
    disabled: list[tuple[str, str]] = field(default_factory=list)
    states: dict[str, dict[str, float]] = field(default_factory=dict)  # group state name -> joint values
    end_effector_link: str | None = None


def read_srdf(path: Path, robot: str) -> Srdf | None:
    """The SRDF at ``path`` if it describes ``robot`` (its ``<robot name>``), else None."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise ImportFailure(f"{path}: cannot read the SRDF: {e}") from None
    if root.tag != "robot" or root.get("name") != robot:
        return None
    s = Srdf(path)
    for d in root.findall("disable_collisions"):
        s.disabled.append((d.get("link1", ""), d.get("link2", "")))
    for gs in root.findall("group_state"):
        vals: dict[str, float] = {}
        for j in gs.findall("joint"):
            try:
                vals[j.get("name", "")] = float((j.get("value") or "0").split()[0])
            except ValueError:
                raise ImportFailure(f"{path}: <group_state name={gs.get('name')!r}> <joint name={j.get('name')!r}> "
                                    f"value: expected a number") from None
        s.states.setdefault(gs.get("name", ""), {}).update(vals)
    ee = root.find("end_effector")
    if ee is not None:
        s.end_effector_link = ee.get("parent_link")
    return s


def find_srdf(urdf: Urdf) -> Srdf | None:
    """A MoveIt SRDF in the package's ``srdf/`` folder (beside the URDF's folder) naming the same robot and
    only its links: the one named as the URDF first (``ur5_robot.srdf``), then the longest name the URDF's
    starts with (``ur5.srdf``), then any other (packages copy SRDFs between variants: ``ur3_gripper.srdf``
    may say ``<robot name="ur5">``)."""
    found: list[Path] = []
    for folder in (urdf.path.parent.parent / "srdf", urdf.path.parent / "srdf", urdf.path.parent):
        if folder.is_dir():
            found += sorted(folder.glob("*.srdf"))
    stem = urdf.path.stem
    found.sort(key=lambda p: (p.stem != stem, not stem.startswith(p.stem), -len(p.stem)))
    for p in found:
        s = read_srdf(p, urdf.name)
        if s is not None and all(a in urdf.links and b in urdf.links for a, b in s.disabled):
            return s
    return None


def weld_groups(urdf: Urdf) -> dict[str, str]:
    """link -> the first link of its rigid group (links joined by fixed joints move as one)."""
    group = {urdf.root: urdf.root}
    pending = [urdf.root]
    while pending:
        p = pending.pop(0)
        for j in [j for j in urdf.joints if j.parent == p]:
            group[j.child] = group[p] if not j.moving else j.child
            pending.append(j.child)
    return group


def adjacent(urdf: Urdf) -> set[frozenset[str]]:
    """Pairs of links adjacent as MoveIt counts them: joined by a joint, or in one rigid group, or a
    rigid group and the groups joined to it."""
    group = weld_groups(urdf)
    members: dict[str, list[str]] = {}
    for link, g in group.items():
        members.setdefault(g, []).append(link)
    out: set[frozenset[str]] = set()
    for ms in members.values():
        out |= {frozenset(p) for p in itertools.combinations(ms, 2)}
    for j in urdf.joints:
        for a in members[group[j.parent]]:
            for b in members[group[j.child]]:
                if a != b:
                    out.add(frozenset((a, b)))
    return out


class Sampler:
    """Random poses of the arm in a compiled model (mimic joints following their leaders)."""

    def __init__(self, model: mujoco.MjModel, urdf: Urdf, seed: int = 0) -> None:
        self.m, self.urdf = model, urdf
        self.d = mujoco.MjData(model)
        self.rng = np.random.default_rng(seed)
        self.joints = urdf.actuated
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j.name) for j in self.joints]
        self.adr = np.array([model.jnt_qposadr[i] for i in ids])
        self.lo = np.array([j.lower if j.limited else -np.pi for j in self.joints])
        self.hi = np.array([j.upper if j.limited else np.pi for j in self.joints])
        self.mimics = []
        for j in urdf.joints:
            if j.mimic is not None and j.moving:
                me = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j.name)]
                lead = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j.mimic.joint)]
                self.mimics.append((me, lead, j.mimic.multiplier, j.mimic.offset))

    def random(self) -> np.ndarray:
        return self.lo + self.rng.random(len(self.lo)) * (self.hi - self.lo)

    def set(self, q: np.ndarray) -> None:
        d = self.d
        d.qpos[:] = self.m.qpos0
        d.qpos[self.adr] = q
        for me, lead, mult, off in self.mimics:
            d.qpos[me] = off + mult * d.qpos[lead]
        mujoco.mj_kinematics(self.m, d)

    def body_pairs_in_contact(self, q: np.ndarray) -> set[frozenset[str]]:
        self.set(q)
        mujoco.mj_collision(self.m, self.d)
        out = set()
        for c in self.d.contact[: self.d.ncon]:
            if c.dist >= 0:
                continue
            b1, b2 = self.m.geom_bodyid[c.geom1], self.m.geom_bodyid[c.geom2]
            out.add(frozenset((self.m.body(b1).name, self.m.body(b2).name)))
        return out


def matrix(model: mujoco.MjModel, urdf: Urdf, default_q: np.ndarray, samples: int, seed: int = 0,
           ) -> dict[frozenset[str], str]:
    """Disabled pairs of links (with collision geometry) and why: adjacent, default, always, never."""
    links_with_geoms = sorted({model.body(model.geom_bodyid[g]).name for g in range(model.ngeom)
                               if model.geom_contype[g] and model.body(model.geom_bodyid[g]).name in urdf.links})
    pairs = [frozenset(p) for p in itertools.combinations(links_with_geoms, 2)]
    why: dict[frozenset[str], str] = {}
    adj = adjacent(urdf)
    for p in pairs:
        if p in adj:
            why[p] = "adjacent"
    s = Sampler(model, urdf, seed)
    for p in s.body_pairs_in_contact(default_q):
        if p in pairs and p not in why:
            why[p] = "default"
    counts: dict[frozenset[str], int] = dict.fromkeys(pairs, 0)
    for _ in range(samples):
        for p in s.body_pairs_in_contact(s.random()):
            if p in counts:
                counts[p] += 1
    for p in pairs:
        if p in why:
            continue
        if counts[p] >= ALWAYS * samples:
            why[p] = "always"
        elif counts[p] == 0:
            why[p] = "never"
    return why


def near_pedestal(model: mujoco.MjModel, urdf: Urdf, pedestal: str, clearance: float, samples: int,
                  seed: int = 0) -> list[str]:
    """The links always nearer the pedestal than the planner's ``clearance`` (in at least :data:`ALWAYS` of
    ``samples`` random poses) and never touching it: a small arm's shoulder turning just above its mount
    (the SO-101's, 16 mm). Checked against the pedestal, they would leave no pose valid; they cannot hit it.
    The planner's check (ArmModel, each geom's margin the clearance) reports a pair within the sum of the two
    margins in MuJoCo: twice the clearance, as here."""
    within = 2 * clearance
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, pedestal)
    geoms: dict[str, list[int]] = {}
    for g in range(model.ngeom):
        name = model.body(model.geom_bodyid[g]).name
        if model.geom_contype[g] and name in urdf.links and name != urdf.root:
            geoms.setdefault(name, []).append(g)
    near = dict.fromkeys(geoms, 0)
    touched: set[str] = set()
    s = Sampler(model, urdf, seed)
    fromto = np.zeros(6)
    for _ in range(samples):
        s.set(s.random())
        for link, gs in geoms.items():
            d = min(mujoco.mj_geomDistance(model, s.d, gid, g, within, fromto) for g in gs)
            near[link] += d < within
            if d <= 0:
                touched.add(link)
    return sorted(k for k, n in near.items() if n >= ALWAYS * samples and k not in touched)
