#!/usr/bin/env python3
"""Generate arm.urdf and arm.xml (MJCF) for the 6-DOF Niryo-One-like arm.

Everything numeric in the two model files comes from the tables below:
joint origins / axes / limits, and per-link primitive shapes with masses.
Link inertial properties (mass, centre of mass, full inertia tensor) are
*computed* from the primitives (uniform density per primitive, exact
solid formulas, rotated into the link frame and shifted with the
parallel-axis theorem; the maths in models/modelgen.py, shared with the
rover's generator), so nothing in the generated files is hand-typed.

Usage (from anywhere):
    python models/arm/generate.py          # rewrites arm.urdf and arm.xml next to this file

Only numpy is required.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
if os.path.dirname(HERE) not in sys.path:
    sys.path.insert(0, os.path.dirname(HERE))  # models/: modelgen, what the generators share
from modelgen import (  # noqa: E402
    Prim,
    R_to_rpy,
    fmt,
    fmt_rad,
    generate,
    mjcf_geom,
    mjcf_inertial,
    urdf_fixed_frame,
    urdf_joint,
    urdf_link,
    write_lines,
)

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
# aligned with the link frame), as modelgen.Prim.  Same primitives are used
# for visual and collision.  Total mass 3.3 kg.
# ----------------------------------------------------------------------------

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
# Frame helpers
# ----------------------------------------------------------------------------

def xy_to_R(xaxis, yaxis):
    x = np.array(xaxis, float)
    y = np.array(yaxis, float)
    x /= np.linalg.norm(x)
    y /= np.linalg.norm(y)
    assert abs(np.dot(x, y)) < 1e-12
    return np.column_stack([x, y, np.cross(x, y)])


# ----------------------------------------------------------------------------
# URDF
# ----------------------------------------------------------------------------

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
        L += urdf_link(link, prims)
    for j in JOINTS:
        rpy = R_to_rpy(xy_to_R(j.xaxis, j.yaxis))
        L += urdf_joint(j.name, "revolute", j.parent, j.child, j.xyz, j.axis, j.effort, j.velocity, j.damping,
                        rpy=fmt_rad(rpy), lower=j.lower, upper=j.upper)
    # tool frame as a fixed child link (massless frames are common in URDF)
    L += urdf_fixed_frame("tool", TOOL_SITE[0], TOOL_SITE[1])
    L.append('</robot>')
    write_lines(path, L)


# ----------------------------------------------------------------------------
# MJCF
# ----------------------------------------------------------------------------

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
        attrs = f'name="{link}" childclass="arm"'
        if joint is not None:
            R = xy_to_R(joint.xaxis, joint.yaxis)
            attrs += f' pos="{fmt(joint.xyz)}"'
            if not np.allclose(R, np.eye(3)):
                attrs += f' xyaxes="{fmt(joint.xaxis)} {fmt(joint.yaxis)}"'
        else:
            attrs += ' pos="0 0 0"'
        L.append(f'{indent}<body {attrs}>')
        L.append(mjcf_inertial(LINKS[link], indent + "  "))
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
    write_lines(path, L)


def main():
    generate(HERE, "arm", write_urdf, write_mjcf, LINKS, width=14, decimals=6)


if __name__ == "__main__":
    main()
