#!/usr/bin/env python3
"""Generate arm.urdf and arm.xml (MJCF) for the 6-DOF Niryo-One-like arm.

Everything numeric in the two model files comes from the tables below:
joint origins / axes / limits, and per-link primitive shapes with masses.
Link inertial properties (mass, centre of mass, full inertia tensor) are
*computed* here from the primitives (uniform density per primitive, exact
solid formulas, rotated into the link frame and shifted with the
parallel-axis theorem), so nothing in the generated files is hand-typed.

Usage (from anywhere):
    python models/arm/generate.py          # rewrites arm.urdf and arm.xml next to this file

Only numpy is required.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))

# ----------------------------------------------------------------------------
# Kinematics.  Frames (see README.md):
#   base_link, shoulder_link : x forward, y left, z up (world aligned at q=0)
#   arm_link, elbow_link     : x along the upper arm (up at q=0), y forward,
#                              z = +world y  -> pitch axes are "0 0 -1"
#   forearm_link             : z along the forearm (forward at q=0), x up,
#                              y = -world y
#   wrist_link, hand_link    : x along the tool (forward at q=0), y up,
#                              z = -world y  -> pitch axis "0 0 1"
# With these axes a *positive* J2/J3/J5 always tilts "up/backwards" (rotation
# about -world_y at q=0) and the large negative ranges of J2/J3 reach forward
# and down into the workspace, as on the Niryo One.
# `rot` gives the child frame axes (x, y) expressed in the parent frame.
# ----------------------------------------------------------------------------

@dataclass
class Joint:
    name: str
    parent: str
    child: str
    xyz: tuple
    xaxis: tuple          # child x axis in parent frame
    yaxis: tuple          # child y axis in parent frame
    axis: tuple           # joint axis in child frame
    lower: float
    upper: float
    effort: float         # N*m
    velocity: float       # rad/s
    damping: float        # N*m*s/rad
    armature: float = 0.01  # kg*m^2 (reflected rotor inertia)


JOINTS = [
    Joint("joint_1", "base_link", "shoulder_link", (0, 0, 0.103), (1, 0, 0), (0, 1, 0), (0, 0, 1),
          -3.054, 3.054, effort=12.0, velocity=2.0, damping=0.1),
    Joint("joint_2", "shoulder_link", "arm_link", (0, 0, 0.080), (0, 0, 1), (1, 0, 0), (0, 0, -1),
          -1.571, 0.628, effort=15.0, velocity=2.0, damping=0.1),
    Joint("joint_3", "arm_link", "elbow_link", (0.210, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, -1),
          -1.401, 0.995, effort=12.0, velocity=2.0, damping=0.1),
    Joint("joint_4", "elbow_link", "forearm_link", (0.037, 0.032, 0), (1, 0, 0), (0, 0, -1), (0, 0, 1),
          -2.618, 2.618, effort=5.0, velocity=2.0, damping=0.05),
    Joint("joint_5", "forearm_link", "wrist_link", (0, 0, 0.180), (0, 0, 1), (1, 0, 0), (0, 0, 1),
          -2.269, 2.269, effort=4.0, velocity=2.0, damping=0.05),
    Joint("joint_6", "wrist_link", "hand_link", (0.018, 0, 0), (1, 0, 0), (0, 1, 0), (1, 0, 0),
          -2.57, 2.57, effort=3.0, velocity=2.0, damping=0.05),
]

TOOL_SITE = ("hand_link", (0.05, 0.0, 0.0))   # tool tip: 5 cm beyond joint_6 along the tool (x) axis

# ----------------------------------------------------------------------------
# Geometry + mass.  Capsules/cylinders are given by segment end points
# (fromto, link frame) and radius; boxes by centre and half sizes (axis
# aligned with the link frame).  Same primitives are used for visual and
# collision.  Total mass 3.3 kg.
# ----------------------------------------------------------------------------

@dataclass
class Prim:
    name: str
    kind: str                 # capsule | cylinder | box | sphere
    mass: float
    fromto: tuple = None      # capsule / cylinder
    radius: float = None      # capsule / cylinder / sphere
    pos: tuple = None         # box / sphere centre
    half: tuple = None        # box half sizes
    rgba: tuple = (0.85, 0.85, 0.88, 1)


GREY = (0.35, 0.35, 0.38, 1)
WHITE = (0.9, 0.9, 0.92, 1)
BLUE = (0.15, 0.35, 0.75, 1)

LINKS: dict[str, list[Prim]] = {
    "base_link": [
        Prim("base_link_body", "cylinder", 1.00, fromto=(0, 0, 0.0, 0, 0, 0.080), radius=0.065, rgba=GREY)],
    "shoulder_link": [
        Prim("shoulder_link_column", "cylinder", 0.45, fromto=(0, 0, -0.015, 0, 0, 0.060), radius=0.045, rgba=WHITE),
        Prim("shoulder_link_pivot", "cylinder", 0.15, fromto=(0, -0.045, 0.080, 0, 0.045, 0.080),
             radius=0.035, rgba=WHITE)],
    "arm_link": [
        Prim("arm_link_beam", "capsule", 0.70, fromto=(0.035, 0, 0, 0.175, 0, 0), radius=0.026, rgba=WHITE)],
    "elbow_link": [
        Prim("elbow_link_pivot", "cylinder", 0.25, fromto=(0, 0, -0.035, 0, 0, 0.035), radius=0.033, rgba=BLUE),
        Prim("elbow_link_block", "box", 0.10, pos=(0.037, 0.004, 0), half=(0.020, 0.024, 0.028), rgba=BLUE)],
    "forearm_link": [
        Prim("forearm_link_beam", "capsule", 0.35, fromto=(0, 0, 0.030, 0, 0, 0.135), radius=0.022, rgba=WHITE)],
    "wrist_link": [
        Prim("wrist_link_pivot", "cylinder", 0.20, fromto=(0, 0, -0.022, 0, 0, 0.022), radius=0.019, rgba=BLUE)],
    "hand_link": [
        Prim("hand_link_flange", "cylinder", 0.10, fromto=(0.006, 0, 0, 0.044, 0, 0), radius=0.016, rgba=GREY)],
}

# ----------------------------------------------------------------------------
# Inertia maths
# ----------------------------------------------------------------------------

def rot_z_to(d):
    """Rotation matrix whose z column is the unit vector d."""
    d = np.asarray(d, float)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = float(np.dot(z, d))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def prim_frame(p: Prim):
    """(centre, R, length) of a primitive; R's z column is the primitive axis."""
    if p.kind in ("capsule", "cylinder"):
        a, b = np.array(p.fromto[:3], float), np.array(p.fromto[3:], float)
        return (a + b) / 2, rot_z_to(b - a), float(np.linalg.norm(b - a))
    return np.array(p.pos, float), np.eye(3), 0.0


def prim_local_inertia(p: Prim, length: float) -> np.ndarray:
    """Inertia about the primitive's own centre, primitive frame (axis = z)."""
    m = p.mass
    if p.kind == "cylinder":
        r, h = p.radius, length
        ixx = m * (3 * r * r + h * h) / 12.0
        izz = m * r * r / 2.0
        return np.diag([ixx, ixx, izz])
    if p.kind == "capsule":
        r, h = p.radius, length
        vc = math.pi * r * r * h
        vh = 2.0 / 3.0 * math.pi * r ** 3          # one hemisphere
        mc = m * vc / (vc + 2 * vh)
        mh = m * vh / (vc + 2 * vh)
        izz = mc * r * r / 2.0 + 2 * mh * 2.0 * r * r / 5.0
        # hemisphere about the capsule centre: 2/5 m r^2 + m (h^2/4 + 3 h r / 8)
        ixx = mc * (3 * r * r + h * h) / 12.0 + 2 * mh * (2.0 * r * r / 5.0 + h * h / 4.0 + 3.0 * h * r / 8.0)
        return np.diag([ixx, ixx, izz])
    if p.kind == "box":
        a, b, c = p.half
        return np.diag([m * (b * b + c * c) / 3.0, m * (a * a + c * c) / 3.0, m * (a * a + b * b) / 3.0])
    if p.kind == "sphere":
        return np.eye(3) * 0.4 * m * p.radius ** 2
    raise ValueError(p.kind)


def link_inertial(prims):
    """Mass, COM and inertia tensor about the COM (link frame axes)."""
    M = sum(p.mass for p in prims)
    frames = [prim_frame(p) for p in prims]
    com = sum(p.mass * c for p, (c, _, _) in zip(prims, frames, strict=False)) / M
    I = np.zeros((3, 3))
    for p, (c, R, L) in zip(prims, frames, strict=False):
        d = c - com
        I += R @ prim_local_inertia(p, L) @ R.T                       # rotate into link frame
        I += p.mass * (np.dot(d, d) * np.eye(3) - np.outer(d, d))     # parallel-axis theorem
    I = (I + I.T) / 2
    return M, com, I


# ----------------------------------------------------------------------------
# Frame helpers
# ----------------------------------------------------------------------------

def xy_to_R(xaxis, yaxis):
    x = np.array(xaxis, float)
    y = np.array(yaxis, float)
    x /= np.linalg.norm(x)
    y /= np.linalg.norm(y)
    assert abs(np.dot(x, y)) < 1e-12
    return np.column_stack([x, y, np.cross(x, y)])


def rpy_to_R(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx            # URDF convention (fixed axes X, then Y, then Z)


def R_to_rpy(R):
    R = np.asarray(R, float)
    if abs(R[2, 0]) < 1 - 1e-9:
        p = -math.asin(R[2, 0])
        r = math.atan2(R[2, 1], R[2, 2])
        y = math.atan2(R[1, 0], R[0, 0])
    else:                                   # gimbal lock: choose yaw = 0
        y = 0.0
        if R[2, 0] < 0:                     # p = +pi/2
            p = math.pi / 2
            r = math.atan2(R[0, 1], R[0, 2])
        else:                               # p = -pi/2
            p = -math.pi / 2
            r = math.atan2(-R[0, 1], -R[0, 2])
    assert np.allclose(rpy_to_R(r, p, y), R, atol=1e-12), (R, (r, p, y))
    return r, p, y


def fmt(v, nd=8):
    def one(x):
        x = float(x)
        s = f"{x:.{nd}g}" if abs(x) >= 1e-4 or x == 0 else f"{x:.6e}"
        return "0" if s in ("-0", "0", "-0.0") else s
    if np.ndim(v) == 0:
        return one(v)
    return " ".join(one(x) for x in v)


def fmt_rad(v):
    """Angles such as pi/2 are written with full precision."""
    return " ".join(repr(float(round(x, 15))) if x != 0 else "0" for x in v)


# ----------------------------------------------------------------------------
# URDF
# ----------------------------------------------------------------------------

def urdf_shape(p: Prim, indent: str, tag: str) -> list[str]:
    """URDF has no capsule: a capsule becomes a cylinder plus two end spheres."""
    c, R, L = prim_frame(p)
    out = []
    count = [0]

    def elem(origin_xyz, origin_R, geom):
        rpy = R_to_rpy(origin_R)
        suffix = f"_{count[0]}" if count[0] else ""
        count[0] += 1
        out.append(f'{indent}<{tag} name="{p.name}{suffix}">')
        out.append(f'{indent}  <origin xyz="{fmt(origin_xyz)}" rpy="{fmt_rad(rpy)}"/>')
        out.append(f'{indent}  <geometry>{geom}</geometry>')
        if tag == "visual":
            out.append(f'{indent}  <material name="{p.name}_mat"><color rgba="{fmt(p.rgba)}"/></material>')
        out.append(f'{indent}</{tag}>')

    if p.kind == "cylinder":
        elem(c, R, f'<cylinder radius="{fmt(p.radius)}" length="{fmt(L)}"/>')
    elif p.kind == "capsule":
        elem(c, R, f'<cylinder radius="{fmt(p.radius)}" length="{fmt(L)}"/>')
        for end in (np.array(p.fromto[:3], float), np.array(p.fromto[3:], float)):
            elem(end, np.eye(3), f'<sphere radius="{fmt(p.radius)}"/>')
    elif p.kind == "box":
        elem(c, R, f'<box size="{fmt(2 * np.array(p.half))}"/>')
    elif p.kind == "sphere":
        elem(c, R, f'<sphere radius="{fmt(p.radius)}"/>')
    return out


def write_urdf(path):
    L = ['<?xml version="1.0"?>',
         '<!-- GENERATED by models/arm/generate.py - do not edit by hand. -->',
         '<!-- 6-DOF arm with Niryo One geometry; primitives only; inertias derived from primitives. -->',
         '<robot name="hilsim_arm">',
         '  <!-- MuJoCo compiler hints (ignored by ROS/urdfdom) -->',
         '  <mujoco>',
         '    <compiler angle="radian" fusestatic="false" discardvisual="true" balanceinertia="false"/>',
         '  </mujoco>']
    for link, prims in LINKS.items():
        M, com, I = link_inertial(prims)
        L.append(f'  <link name="{link}">')
        L.append('    <inertial>')
        L.append(f'      <origin xyz="{fmt(com)}" rpy="0 0 0"/>')
        L.append(f'      <mass value="{fmt(M)}"/>')
        L.append(f'      <inertia ixx="{fmt(I[0,0])}" ixy="{fmt(I[0,1])}" ixz="{fmt(I[0,2])}" '
                 f'iyy="{fmt(I[1,1])}" iyz="{fmt(I[1,2])}" izz="{fmt(I[2,2])}"/>')
        L.append('    </inertial>')
        for p in prims:
            L += urdf_shape(p, "    ", "visual")
        for p in prims:
            L += urdf_shape(p, "    ", "collision")
        L.append('  </link>')
    for j in JOINTS:
        rpy = R_to_rpy(xy_to_R(j.xaxis, j.yaxis))
        L.append(f'  <joint name="{j.name}" type="revolute">')
        L.append(f'    <parent link="{j.parent}"/>')
        L.append(f'    <child link="{j.child}"/>')
        L.append(f'    <origin xyz="{fmt(j.xyz)}" rpy="{fmt_rad(rpy)}"/>')
        L.append(f'    <axis xyz="{fmt(j.axis)}"/>')
        L.append(f'    <limit lower="{fmt(j.lower)}" upper="{fmt(j.upper)}" '
                 f'effort="{fmt(j.effort)}" velocity="{fmt(j.velocity)}"/>')
        L.append(f'    <dynamics damping="{fmt(j.damping)}" friction="0"/>')
        L.append('  </joint>')
    # tool frame as a fixed child link (massless frames are common in URDF)
    L.append('  <link name="tool_link"/>')
    L.append('  <joint name="tool_joint" type="fixed">')
    L.append(f'    <parent link="{TOOL_SITE[0]}"/>')
    L.append('    <child link="tool_link"/>')
    L.append(f'    <origin xyz="{fmt(TOOL_SITE[1])}" rpy="0 0 0"/>')
    L.append('  </joint>')
    L.append('</robot>')
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


# ----------------------------------------------------------------------------
# MJCF
# ----------------------------------------------------------------------------

def mjcf_geom(p: Prim):
    a = f'name="{p.name}" type="{p.kind}"'
    if p.kind in ("capsule", "cylinder"):
        a += f' fromto="{fmt(p.fromto)}" size="{fmt(p.radius)}"'
    elif p.kind == "box":
        a += f' pos="{fmt(p.pos)}" size="{fmt(p.half)}"'
    else:
        a += f' pos="{fmt(p.pos)}" size="{fmt(p.radius)}"'
    # `mass` is informative only: the explicit <inertial> wins (inertiafromgeom="auto");
    # verify.py recompiles with inertiafromgeom="true" to cross-check the generator.
    return f'<geom {a} mass="{fmt(p.mass)}" rgba="{fmt(p.rgba)}"/>'


def write_mjcf(path):
    children = {j.parent: j for j in JOINTS}
    L = ['<!-- GENERATED by models/arm/generate.py - do not edit by hand. -->',
         '<!-- 6-DOF arm with Niryo One geometry (primitives only). Loadable on its own, and',
         '     included by tabletop.xml (<include file="arm.xml"/>). -->',
         '<mujoco model="hilsim_arm">',
         '  <compiler angle="radian" autolimits="true"/>',
         '  <option timestep="0.001" integrator="implicitfast"/>',
         '  <default>',
         '    <default class="arm">',
         '      <joint type="hinge" limited="true" armature="0.01"/>',
         '      <geom contype="1" conaffinity="1" group="0" condim="3" friction="0.8 0.02 0.001"/>',
         '      <motor gear="1" ctrllimited="true"/>',
         '    </default>',
         '  </default>',
         '  <custom>',
         '    <!-- velocity limits (rad/s), same order as the joints / actuators; MuJoCo does not enforce them -->',
         f'    <numeric name="arm_joint_velocity_limit" data="{fmt([j.velocity for j in JOINTS])}"/>',
         '  </custom>',
         '  <worldbody>']

    def body(link, indent, joint: Joint | None):
        M, com, I = link_inertial(LINKS[link])
        attrs = f'name="{link}" childclass="arm"'
        if joint is not None:
            R = xy_to_R(joint.xaxis, joint.yaxis)
            attrs += f' pos="{fmt(joint.xyz)}"'
            if not np.allclose(R, np.eye(3)):
                attrs += f' xyaxes="{fmt(joint.xaxis)} {fmt(joint.yaxis)}"'
        else:
            attrs += ' pos="0 0 0"'
        L.append(f'{indent}<body {attrs}>')
        L.append(f'{indent}  <inertial pos="{fmt(com)}" mass="{fmt(M)}" '
                 f'fullinertia="{fmt([I[0,0], I[1,1], I[2,2], I[0,1], I[0,2], I[1,2]])}"/>')
        if joint is not None:
            L.append(f'{indent}  <joint name="{joint.name}" axis="{fmt(joint.axis)}" '
                     f'range="{fmt(joint.lower)} {fmt(joint.upper)}" damping="{fmt(joint.damping)}" '
                     f'armature="{fmt(joint.armature)}"/>')
        for p in LINKS[link]:
            L.append(f'{indent}  {mjcf_geom(p)}')
        if link == TOOL_SITE[0]:
            L.append(f'{indent}  <site name="tool" pos="{fmt(TOOL_SITE[1])}" size="0.006" rgba="1 0.2 0.2 1"/>')
        if link in children:
            j = children[link]
            body(j.child, indent + "  ", j)
        L.append(f'{indent}</body>')

    body("base_link", "    ", None)
    L.append('  </worldbody>')
    L.append('  <contact>')
    L.append('    <!-- adjacent links never collide (also MuJoCo\'s default parent/child filter);'
             ' non-adjacent self-collision stays enabled -->')
    for j in JOINTS:
        L.append(f'    <exclude body1="{j.parent}" body2="{j.child}"/>')
    L.append('  </contact>')
    L.append('  <actuator>')
    L.append('    <!-- torque motors, one per joint, same order as the joints; ctrl is N*m -->')
    for j in JOINTS:
        L.append(f'    <motor name="{j.name}" class="arm" joint="{j.name}" gear="1" ctrllimited="true" '
                 f'ctrlrange="{fmt(-j.effort)} {fmt(j.effort)}"/>')
    L.append('  </actuator>')
    L.append('</mujoco>')
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


def main():
    write_urdf(os.path.join(HERE, "arm.urdf"))
    write_mjcf(os.path.join(HERE, "arm.xml"))
    total = 0.0
    for link, prims in LINKS.items():
        M, com, I = link_inertial(prims)
        total += M
        print(f"{link:14s} m={M:.3f} com={np.round(com, 4)} Idiag={np.round(np.diag(I), 6)}")
    print(f"total mass {total:.3f} kg -> wrote arm.urdf, arm.xml")


if __name__ == "__main__":
    main()
