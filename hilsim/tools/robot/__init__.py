"""``hilsim robot import URDF``: a lab's own arm, from its URDF to a scenario that ``hilsim up`` runs as it
runs the built-in arm (docs/robots.md).

The parts, each a module of this package: reading the URDF (:mod:`.urdf`), making its meshes readable
(:mod:`.meshes`), the MJCF and its world (:mod:`.mjcf`), the self-collision matrix and the SRDF
(:mod:`.collisions`), home and targets (:mod:`.poses`), the URDF written beside (:mod:`.description`), the
scenario and planner library (:mod:`.scenario_file`). The gains come from the project's own tuner
(:mod:`hilsim.tools.tuning.autotune`, relay then Ziegler–Nichols and its refinement), run on the real services.

Everything is written into a temporary folder beside ``--out`` and moved into place only once it is
whole: an import that fails writes nothing (one line naming the file, the element and why; exit 2).
"""

from __future__ import annotations

import argparse
import re
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from hilsim.tools import progress
from hilsim.tools.robot import collisions, description, mjcf, poses, scenario_file
from hilsim.tools.robot.meshes import Meshes
from hilsim.tools.robot.urdf import ImportFailure, Joint, Urdf, package_roots, read

TOOL_NAMES = ("tcp", "tool", "ee", "flange", "end_effector", "eef", "hand")
COLLISION_SAMPLES = 3000
PEDESTAL_SAMPLES = 300  # poses sampled for the links always near the pedestal (collisions.near_pedestal)


def tool_link(u: Urdf, given: str | None, srdf: collisions.Srdf | None) -> tuple[str, str]:
    """The link the ``tool`` site goes on, and why: ``--tool``, the SRDF's end effector, else the last
    link of the arm's chain (most revolute joints to the root, not below a gripper's prismatic joint;
    a tool-like name first among equals, then the deepest)."""
    if given:
        if given not in u.links:
            raise ImportFailure(f"{u.path}: --tool {given}: no <link> of that name")
        return given, "--tool"
    if srdf is not None and srdf.end_effector_link in u.links:
        return srdf.end_effector_link, f"the end effector of {srdf.path.name}"  # type: ignore[return-value]

    def score(link: str) -> tuple[int, int, int]:
        chain = u.chain(link)
        turns = sum(j.kind in ("revolute", "continuous") for j in chain)
        below_slide = any(j.kind == "prismatic" for j in chain)
        named = any(t in link.lower() for t in TOOL_NAMES)
        return (turns if not below_slide else -1, int(named), len(chain))

    return max(u.links, key=score), "the last link of the chain"


def _name(u: Urdf, given: str | None) -> str:
    name = given or re.sub(r"[^A-Za-z0-9_]", "_", u.name)
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
        raise ImportFailure(f"--name {name!r}: expected a ROS name (a letter, then letters, digits or _)")
    return name


def _pedestal(model: mujoco.MjModel, root: str) -> float:
    """Half the side of a pedestal under the root link: its collision geometry's footprint, 2 cm more."""
    d = mujoco.MjData(model)
    mujoco.mj_kinematics(model, d)
    rid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root)
    half = 0.06
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != rid:
            continue
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            mid = model.geom_dataid[g]
            v = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
            w = v @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
            half = max(half, float(np.abs(w[:, :2]).max()))
        else:
            half = max(half, float(np.abs(d.geom_xpos[g][:2]).max() + model.geom_rbound[g]))
    return half + 0.02


def _compile(spec: mujoco.MjSpec, where: Path) -> mujoco.MjModel:
    try:
        return spec.compile()
    except Exception as e:
        raise ImportFailure(f"{where}: MuJoCo cannot compile the arm: {' '.join(str(e).split())}") from None


def import_robot(urdf_path: Path, out: Path | None = None, *, package_paths: list[Path] | None = None,
                 name: str | None = None, tool: str | None = None, srdf_path: Path | None = None,
                 tune: bool = True, seed: int = 0, force: bool = False, say: Callable[[str], None] = print) -> Path:
    """Import; the scenario's path (``out/NAME.yaml``)."""
    t0 = time.monotonic()
    u = read(urdf_path)
    name = _name(u, name)
    out = out if out is not None else Path("robots") / name
    if out.exists() and any(out.iterdir()) and not force:
        raise ImportFailure(f"--out {out}: not empty (give --force to replace it)")
    srdf = None
    if srdf_path is not None:
        srdf = collisions.read_srdf(srdf_path, u.name)
        if srdf is None:
            raise ImportFailure(f"{srdf_path}: <robot name>: not {u.name!r}, the URDF's robot")
    else:
        srdf = collisions.find_srdf(u)
    joints = u.actuated
    say(f"{urdf_path}: robot {u.name!r}, {len(u.links)} links, {len(joints)} driven joints "
        f"({', '.join(j.name for j in joints)})" + (f", {sum(j.mimic is not None for j in u.joints)} mimic"
                                                       if any(j.mimic for j in u.joints) else ""))
    if srdf is not None:
        say(f"  SRDF: {srdf.path} ({len(srdf.disabled)} disabled pairs, group states: "
            f"{', '.join(srdf.states) or 'none'})")
    link, why = tool_link(u, tool, srdf)
    say(f"  tool site on {link} ({why})")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.importing"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        scenario = _write_all(u, name, tmp, link, srdf, package_paths or [], tune, seed, say, t0)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    say(f"imported {name} into {out} in {time.monotonic() - t0:.0f} s; run it: hilsim up {out / scenario.name}")
    return out / scenario.name


def _write_all(u: Urdf, name: str, tmp: Path, link: str, srdf: collisions.Srdf | None, package_paths: list[Path],
               tune: bool, seed: int, say: Callable[[str], None], t0: float) -> Path:
    joints = u.actuated
    meshes = Meshes(u.path, tmp, package_roots(package_paths), say)
    say(f"[{time.monotonic() - t0:4.0f} s] meshes and model")
    spec = mjcf.build(u, meshes, link, 0.1)
    model = _compile(spec, u.path)
    spec.geom("pedestal").size = [_pedestal(model, u.root)] * 2 + [mjcf.FLOOR_DEPTH / 2]
    converted = sum(m.source.suffix.lower() not in (".stl", ".obj") for m in meshes.by_source.values())
    say(f"  {len(meshes.by_source)} meshes ({converted} converted)")
    say(f"[{time.monotonic() - t0:4.0f} s] self-collision matrix")
    model = _compile(spec, u.path)
    zero = poses.zero_pose(joints)
    adjacent = collisions.adjacent(u)
    if srdf is not None and srdf.disabled:
        pairs = {frozenset(p) for p in srdf.disabled if all(x in u.links for x in p)} | adjacent
        say(f"  from the SRDF: {len(pairs)} pairs disabled (with the adjacent ones)")
    else:
        why = collisions.matrix(model, u, zero, COLLISION_SAMPLES, seed)
        pairs = set(why)
        counts = {r: sum(v == r for v in why.values()) for r in ("adjacent", "default", "always", "never")}
        say(f"  {COLLISION_SAMPLES} sampled poses: " + ", ".join(f"{n} {r}" for r, n in counts.items()) + " disabled")
    near = collisions.near_pedestal(model, u, mjcf.PEDESTAL, poses.CLEARANCE, PEDESTAL_SAMPLES, seed)
    if near:
        say(f"  always within {poses.CLEARANCE * 1000:.0f} mm of the pedestal, never touching it: {', '.join(near)} "
            "(not checked against the pedestal and floor)")
    pairs |= {frozenset((mjcf.WORLD, link)) for link in near}
    mjcf.exclude(spec, sorted(tuple(sorted(p)) for p in pairs if len(p) == 2))  # type: ignore[misc]
    model = _compile(spec, u.path)
    xml = tmp / f"{name}.xml"
    mjcf.write(spec, xml)

    from hilsim.planning.collision import ArmModel

    arm = ArmModel(xml, clearance=poses.CLEARANCE, joint_names=[j.name for j in joints])
    say(f"[{time.monotonic() - t0:4.0f} s] home and targets")
    home, home_how = poses.choose_home(arm, joints, srdf.states if srdf else {}, seed, say)
    say(f"  home: {home_how}: [{', '.join(f'{v:.3f}' for v in home)}]")
    library = tmp / "planners.yaml"
    scenario_file.write_library(library, joints)
    planner = scenario_file.DEFAULT_PLANNER
    targets = poses.choose_targets(arm, joints, home, library, planner, seed, say)
    d = mujoco.MjData(model)
    mjcf.add_home(spec, model, {j.name: float(v) for j, v in zip(joints, home, strict=True)}, u)
    model = _compile(spec, u.path)
    mjcf.write(spec, xml)
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, 0)
    description.write(u.path, meshes, tmp / f"{name}.urdf")
    gains = scenario_file.model_gains(model, d.qpos.copy(), joints)
    scenario = tmp / f"{name}.yaml"
    how = ("found by hilsim tune (relay, Ziegler–Nichols, refined) at import; a joint it could not tune keeps "
           f"a model-based PD (critically damped at {scenario_file.BANDWIDTH_HZ} Hz at home)" if tune else
           f"model-based PD (critically damped at {scenario_file.BANDWIDTH_HZ} Hz at home), not tuned: "
           f"hilsim tune {name}.yaml --all --method relay --write")
    scenario_file.write_scenario(scenario, name, u.path, joints, gains, home, home_how, targets, planner, how)
    from hilsim.core.scenario import load_scenario

    load_scenario(scenario)  # a scenario that does not load is never written
    hil = tmp / "hil-can.yaml"
    scenario_file.write_hil_overlay(hil, scenario.name, joints[0], float(home[0]),
                                    scenario_file.joint_inertia(model, d.qpos.copy(), joints[0]))
    load_scenario(scenario, overlays=[hil])
    if tune:
        say(f"[{time.monotonic() - t0:4.0f} s] tuning {len(joints)} joints on the real services (hilsim tune)")
        _tune(scenario, joints, [float(v) for v in home], say)
    return scenario


# physics, sensors and controller in one process while tuning: the same results as apart (a composed lockstep run
# is bit-identical to the distributed one), in less time
TUNING_COMPOSE = {"compose": [["physics", "sensors", "controller"]]}
TUNING_WORKERS = 2  # joints tuned at once (each its own run of the services, the others held at home)


def tuning_step(joint: Joint, home: float) -> float:
    """The tuner's step from home: 0.2 rad (a prismatic joint: 0.01 m), towards the side of the joint's range
    with room for it (a gripper closed at home, at its upper limit, steps down)."""
    size = 0.01 if joint.kind == "prismatic" else 0.2
    return size if not joint.limited or home + size <= joint.upper or home - size < joint.lower else -size


def _tune_one(scenario: Path, joint: str, step: float) -> tuple[str, dict[str, float] | None, str]:
    """One joint tuned (in a worker process): its gains (None: the tuner could not, the starting gains stay)
    and the line that says how they do."""
    from hilsim.core.config import ConfigError
    from hilsim.tools.tuning.autotune import Target, tune
    from hilsim.tools.tuning.rig import RigError

    try:
        r = tune(str(scenario), joint, "relay", step, Target(),
                 lambda s: print(f"    {joint}: {s.strip()}", flush=True), overrides=TUNING_COMPOSE)
    except (ConfigError, RigError) as e:
        return joint, None, f"  {joint}: not tuned ({e}): the model-based gains stay (hilsim tune to try again)"
    f = r.figures
    line = (f"  {joint}: kp {r.gains['kp']:g}, ki {r.gains['ki']:g}, kd {r.gains['kd']:g}: rise {f.rise_time_s:.3f} s, "
            f"settling {f.settling_time_s:.3f} s, overshoot {f.overshoot_pct:.2f} %"
            + ("" if not r.misses else f" (target missed: {'; '.join(r.misses)})"))
    return joint, r.gains, line


def _tune(scenario: Path, joints: list[Joint], home: list[float], say: Callable[[str], None]) -> None:
    """Every joint tuned, :data:`TUNING_WORKERS` at a time, each with the others held by the starting gains (so
    the result does not depend on the order); the gains written once all are found."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from hilsim.tools.tuning.autotune import write_gains

    found: dict[str, dict[str, float] | None] = {}
    # spawn: fresh interpreters. A fork copies the caller's threads' locks mid-call (a Zenoh session's native
    # runtime: a fork of a pytest worker that held one deadlocked in open_router); its resource tracker ends
    # with this process
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(TUNING_WORKERS, mp_context=ctx) as pool:
        futures = [pool.submit(_tune_one, scenario, j.name, tuning_step(j, q))
                   for j, q in zip(joints, home, strict=True)]
        for fut in futures:
            joint, gains, line = fut.result()
            found[joint] = gains
            say(line)
    for j in joints:
        if found[j.name] is not None:
            write_gains(scenario, j.name, found[j.name])


def cmd_robot_import(args: argparse.Namespace) -> int:
    say = progress(False)
    import_robot(Path(args.urdf), Path(args.out) if args.out else None,
                 package_paths=[Path(p) for p in args.package_path or []], name=args.name, tool=args.tool,
                 srdf_path=Path(args.srdf) if args.srdf else None, tune=not args.no_tune, seed=args.seed,
                 force=args.force, say=say)
    return 0
