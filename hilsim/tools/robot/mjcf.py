"""The MJCF of an imported arm, built with MuJoCo's spec API from the parsed URDF (not MuJoCo's own URDF
reader, which drops visuals, fuses static bodies, ignores ``<mimic>`` and adds no motors).

What it makes, in the conventions of the built-in arm (``models/arm/arm.xml``, ``tabletop.xml``):

- a body per link, named as the link; a hinge or slide joint per moving URDF joint, named as the joint,
  with its range (none for a continuous joint), ``<dynamics>`` damping and friction (``frictionloss``);
- the URDF's inertials as they are (rotated into a principal frame); a link without one, or with a
  mass or inertia too small for MuJoCo, gets :data:`MIN_MASS` / :data:`MIN_INERTIA`;
- collision geoms named after their links (``forearm_link``, ``forearm_link_2``: what a planner's
  collision message names) in group 3, visual geoms (``<link>_visual``) drawn only (no contacts);
- a torque motor per actuated joint (``ctrlrange`` ± the URDF's effort limit), named as its joint;
  a mimic joint follows its leader through a joint equality (a gripper is one command);
- the velocity limits as the custom numeric ``arm_joint_velocity_limit`` (the planner caps its
  trajectories with it);
- a ``tool`` site at the tool link and an ``imu`` site there too;
- a world: a floor :data:`FLOOR_DEPTH` below the arm's base and a pedestal under the base, sized to it;
- a ``home`` keyframe (physics starts there: :mod:`hilsim.sim.world`).
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from hilsim.core.geometry import rpy_to_matrix
from hilsim.tools.robot.meshes import MESH_DIR, Meshes
from hilsim.tools.robot.urdf import Geometry, Link, Urdf

MIN_MASS = 1e-3  # [kg] a moving link with less (or none) gets this
MIN_INERTIA = 1e-6  # [kg m²] principal moments at least this
FLOOR_DEPTH = 0.75  # [m] the floor below the base (a table's height, as the built-in arm's world)
DEFAULT_EFFORT = 100.0  # [N m] a motor whose joint gives no effort limit
DEFAULT_VELOCITY = 3.0  # [rad/s] a joint whose URDF gives no velocity limit
ARMATURE = 0.01  # rotor inertia [kg m²], as the built-in arm: steadies light distal links
COLLISION_GROUP, VISUAL_GROUP = 3, 2
TOOL_SITE, IMU_SITE = "tool", "imu"
PEDESTAL = "pedestal"  # the pedestal's geom, in the world body (as the floor)
WORLD = "world"  # MuJoCo's world body: a link excluded from the pedestal is excluded from it (and the floor)
VELOCITY_NUMERIC = "arm_joint_velocity_limit"


def quat_of(m: np.ndarray) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(m, dtype=float).reshape(9))
    return q.tolist()


def _rpy_quat(rpy: tuple[float, float, float]) -> list[float]:
    return quat_of(rpy_to_matrix(*rpy))


def principal(tensor: tuple[float, ...], rpy: tuple[float, float, float]) -> tuple[np.ndarray, list[float]]:
    """Principal moments and the frame's quaternion of a URDF inertia given in a frame rotated by ``rpy``."""
    ixx, iyy, izz, ixy, ixz, iyz = tensor
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    r = rpy_to_matrix(*rpy)
    full = r @ inertia @ r.T
    vals, vecs = np.linalg.eigh(full)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]  # a rotation, not a reflection
    vals = np.maximum(vals, MIN_INERTIA)
    # the triangle inequality MuJoCo checks: each moment at most the sum of the others
    for i in range(3):
        others = vals.sum() - vals[i]
        if vals[i] > others:
            vals[(i + 1) % 3] += (vals[i] - others) / 2 + MIN_INERTIA
            vals[(i + 2) % 3] += (vals[i] - others) / 2 + MIN_INERTIA
    return vals, quat_of(vecs)


def _add_geom(spec: mujoco.MjSpec, body: mujoco.MjsBody, g: Geometry, name: str, meshes: Meshes, where: str,
              visual: bool) -> bool:
    """Add one URDF geometry to ``body``; False if a visual mesh could not be read."""
    kw: dict = {"name": name, "pos": list(g.origin.xyz), "quat": _rpy_quat(g.origin.rpy)}
    if g.kind == "box":
        kw.update(type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2 for s in g.size])
    elif g.kind == "cylinder":
        kw.update(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[g.size[0], g.size[1] / 2, 0])
    elif g.kind == "sphere":
        kw.update(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[g.size[0], 0, 0])
    else:
        mesh = meshes.get(g.uri, where, visual)
        if mesh is None:
            return False
        asset = mesh.name if g.scale == (1.0, 1.0, 1.0) else f"{mesh.name}_{abs(hash(g.scale)) % 10**6}"
        if spec.mesh(asset) is None:
            spec.add_mesh(name=asset, file=mesh.file.name, scale=list(g.scale))
        kw.update(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=asset)
    geom = body.add_geom(**kw)
    geom.mass = 0.0  # the link's inertial is explicit (URDF); geoms add none
    if visual:
        geom.contype = geom.conaffinity = 0
        geom.group = VISUAL_GROUP
        geom.rgba = list(g.rgba or (0.75, 0.75, 0.78, 1.0))
    else:
        geom.contype = geom.conaffinity = 1
        geom.group = COLLISION_GROUP
        geom.condim = 3
        geom.rgba = list(g.rgba or (0.6, 0.6, 0.65, 1.0))
    return True


def _link_geoms(spec: mujoco.MjSpec, body: mujoco.MjsBody, link: Link, meshes: Meshes, path: Path) -> None:
    where = f"{path}: <link name={link.name!r}>"
    for k, g in enumerate(link.collisions):
        _add_geom(spec, body, g, link.name if k == 0 else f"{link.name}_{k + 1}", meshes,
                  f"{where} <collision> {k}", visual=False)
    for k, g in enumerate(link.visuals):
        # a visual mesh that cannot be read is left out here (the URDF written beside draws the
        # collision geometry in its place: hilsim.tools.robot.description)
        _add_geom(spec, body, g, f"{link.name}_visual" if k == 0 else f"{link.name}_visual_{k + 1}",
                  meshes, f"{where} <visual> {k}", visual=True)


def _inertial(body: mujoco.MjsBody, link: Link, moving: bool) -> None:
    body.explicitinertial = True
    ine = link.inertial
    mass = ine.mass if ine is not None else 0.0
    if ine is None or mass <= 0:
        body.mass = MIN_MASS if moving else max(mass, 0.0)
        body.inertia = [MIN_INERTIA] * 3
        body.ipos = list(ine.origin.xyz) if ine is not None else [0.0, 0.0, 0.0]
        return
    vals, q = principal(ine.inertia, ine.origin.rpy)
    body.mass = max(mass, MIN_MASS)
    body.ipos = list(ine.origin.xyz)
    body.iquat = q
    body.inertia = vals.tolist()


def build(urdf: Urdf, meshes: Meshes, tool_link: str, base_half: float) -> mujoco.MjSpec:
    """The arm and its world as a spec (meshes under ``meshes.out / meshes``)."""
    spec = mujoco.MjSpec()
    spec.modelname = urdf.name
    spec.compiler.degree = False
    spec.compiler.autolimits = True
    spec.meshdir = str(meshes.out / MESH_DIR)
    spec.option.timestep = 0.001
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.visual.headlight.diffuse = [0.5, 0.5, 0.5]
    spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
    spec.stat.center = [0.0, 0.0, 0.3]
    spec.stat.extent = 1.5
    world = spec.worldbody
    world.add_light(name="top", pos=[0, 0, 2.0], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8])
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0, 0, -FLOOR_DEPTH], size=[3, 3, 0.05],
                   rgba=[0.3, 0.33, 0.36, 1])
    # the pedestal: under the base, its top at the base's origin (z = 0)
    world.add_geom(name=PEDESTAL, type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0, 0, -FLOOR_DEPTH / 2],
                   size=[base_half, base_half, FLOOR_DEPTH / 2], rgba=[0.45, 0.45, 0.5, 1])

    bodies: dict[str, mujoco.MjsBody] = {}
    root = urdf.root
    if root == "world":  # ROS's convention for a fixed base: the URDF's world link is MuJoCo's world body
        bodies[root] = world
    else:
        bodies[root] = world.add_body(name=root)
        _inertial(bodies[root], urdf.links[root], moving=False)
    _link_geoms(spec, bodies[root], urdf.links[root], meshes, urdf.path)
    below_moving: set[str] = set()
    # parents before children: walk the tree from the root
    pending = [root]
    while pending:
        parent = pending.pop(0)
        for j in [j for j in urdf.joints if j.parent == parent]:
            b = bodies[parent].add_body(name=j.child, pos=list(j.origin.xyz), quat=_rpy_quat(j.origin.rpy))
            bodies[j.child] = b
            if j.moving or parent in below_moving:
                below_moving.add(j.child)
            _inertial(b, urdf.links[j.child], moving=j.child in below_moving)
            if j.moving:
                kind = mujoco.mjtJoint.mjJNT_SLIDE if j.kind == "prismatic" else mujoco.mjtJoint.mjJNT_HINGE
                jt = b.add_joint(name=j.name, type=kind, axis=list(j.axis))
                if j.limited:
                    jt.range = [j.lower, j.upper]
                    jt.limited = mujoco.mjtLimited.mjLIMITED_TRUE
                else:
                    jt.limited = mujoco.mjtLimited.mjLIMITED_FALSE
                jt.damping = [j.damping, 0.0, 0.0]  # MuJoCo 4: linear, quadratic, cubic terms
                jt.frictionloss = j.friction
                jt.armature = ARMATURE
            _link_geoms(spec, b, urdf.links[j.child], meshes, urdf.path)
            pending.append(j.child)

    tool = bodies[tool_link]
    tool.add_site(name=TOOL_SITE, size=[0.006, 0, 0], rgba=[1, 0.2, 0.2, 1])
    tool.add_site(name=IMU_SITE, size=[0.004, 0, 0], rgba=[0.2, 1, 0.2, 1])

    for j in urdf.actuated:
        effort = j.effort if math.isfinite(j.effort) and j.effort > 0 else DEFAULT_EFFORT
        a = spec.add_actuator(name=j.name, target=j.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.gainprm[0] = 1.0
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.ctrlrange = [-effort, effort]
    for j in urdf.joints:
        if j.mimic is not None and j.moving:
            eq = spec.add_equality(name=f"mimic_{j.name}", type=mujoco.mjtEq.mjEQ_JOINT, name1=j.name,
                                   name2=j.mimic.joint)
            eq.data[:5] = [j.mimic.offset, j.mimic.multiplier, 0, 0, 0]
    vel = [j.velocity if math.isfinite(j.velocity) and j.velocity > 0 else DEFAULT_VELOCITY for j in urdf.actuated]
    spec.add_numeric(name=VELOCITY_NUMERIC, data=vel, size=len(vel))
    return spec


def exclude(spec: mujoco.MjSpec, pairs: list[tuple[str, str]]) -> None:
    for a, b in pairs:
        spec.add_exclude(bodyname1=a, bodyname2=b)


def add_home(spec: mujoco.MjSpec, model: mujoco.MjModel, joint_q: dict[str, float], urdf: Urdf) -> None:
    """The ``home`` keyframe: the actuated joints at ``joint_q``, mimic joints following them."""
    qpos = model.qpos0.copy()
    values = dict(joint_q)
    for j in urdf.joints:
        if j.mimic is not None and j.mimic.joint in values:
            values[j.name] = j.mimic.offset + j.mimic.multiplier * values[j.mimic.joint]
    for name, v in values.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0:
            qpos[model.jnt_qposadr[jid]] = v
    spec.add_key(name="home", qpos=qpos.tolist())


def write(spec: mujoco.MjSpec, path: Path) -> None:
    """The MJCF at ``path``, its meshes found in ``meshes/`` beside it wherever the folder moves."""
    xml = spec.to_xml()
    xml = xml.replace(f'meshdir="{spec.meshdir}"', f'meshdir="{MESH_DIR}"')
    path.write_text(xml)
