#!/usr/bin/env python3
"""Generate rover.urdf and rover.xml (MJCF) for the four-wheel-steer rover (thesis seed 000).

One source, two files: the tables below give the chassis, the four steering knuckles and
wheels, the sensor frames and every joint; masses and inertias are *computed* from the
primitives (uniform density, exact solid formulas, parallel-axis theorem), as the arm's
generator does. The MJCF gives the chassis a free joint; the URDF leaves base_link floating
(a URDF root link has no joint to the world).

Frames: base_link = chassis centre, x forward, y left, z up. Wheel i sits under its steering
axis (z); its traction axis is the knuckle's y, so a positive traction speed drives the wheel
forward when its steering angle is 0.

Usage:  python models/rover/generate.py     # rewrites rover.urdf and rover.xml next to this file
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))

# ----------------------------------------------------------------------------
# Geometry (metres, kilograms)
# ----------------------------------------------------------------------------
WHEEL_RADIUS = 0.15
WHEEL_WIDTH = 0.10
WHEEL_X = 0.35            # half wheelbase (front +x, rear -x)
WHEEL_Y = 0.40            # half track (left +y, right -y)
AXLE_Z = -0.10            # wheel centre below the chassis centre
CHASSIS_HALF = (0.45, 0.22, 0.08)
START_Z = WHEEL_RADIUS - AXLE_Z + 0.005   # chassis centre above the ground at rest (5 mm drop)

STEER_LIMIT = math.pi / 2  # ± steering range [rad]
STEER_EFFORT = 15.0        # N·m
STEER_VELOCITY = 3.0       # rad/s
STEER_DAMPING = 0.5        # N·m·s/rad
TRACTION_EFFORT = 20.0     # N·m
TRACTION_VELOCITY = 12.0   # rad/s (1.8 m/s at the rim)
TRACTION_DAMPING = 0.05
ARMATURE = 0.01            # kg·m² (reflected rotor inertia)

WHEELS = ("fl", "fr", "rl", "rr")
WHEEL_POS = {"fl": (WHEEL_X, WHEEL_Y), "fr": (WHEEL_X, -WHEEL_Y), "rl": (-WHEEL_X, WHEEL_Y), "rr": (-WHEEL_X, -WHEEL_Y)}

# sensor frames on the chassis: name -> position in base_link (axes aligned with base_link)
SITES = {
    "imu": (0.0, 0.0, 0.0),
    "laser": (0.38, 0.0, 0.16),
    "gps": (-0.30, 0.0, 0.45),
}

GREY = (0.3, 0.3, 0.32, 1)
ORANGE = (0.9, 0.5, 0.1, 1)
BLACK = (0.08, 0.08, 0.08, 1)


@dataclass
class Prim:
    name: str
    kind: str                 # cylinder | box
    mass: float
    fromto: tuple = None      # cylinder
    radius: float = None      # cylinder
    pos: tuple = None         # box centre
    half: tuple = None        # box half sizes
    rgba: tuple = GREY
    collide: bool = True      # False: visual only (no contact)


LINKS: dict[str, list[Prim]] = {
    "base_link": [
        Prim("chassis", "box", 40.0, pos=(0, 0, 0), half=CHASSIS_HALF, rgba=ORANGE),
        Prim("laser_head", "cylinder", 0.5, fromto=(0.38, 0, 0.08, 0.38, 0, 0.18), radius=0.04, rgba=BLACK,
             collide=False),
        Prim("gps_mast", "cylinder", 0.3, fromto=(-0.30, 0, 0.08, -0.30, 0, 0.45), radius=0.012, rgba=GREY,
             collide=False),
    ],
}
for _w in WHEELS:
    LINKS[f"{_w}_steering_link"] = [
        Prim(f"{_w}_knuckle", "cylinder", 1.0, fromto=(0, 0, -AXLE_Z - 0.08, 0, 0, 0.06), radius=0.03, rgba=GREY,
             collide=False)]
    LINKS[f"{_w}_wheel_link"] = [
        Prim(f"{_w}_wheel", "cylinder", 2.5, fromto=(0, -WHEEL_WIDTH / 2, 0, 0, WHEEL_WIDTH / 2, 0),
             radius=WHEEL_RADIUS, rgba=BLACK)]


@dataclass
class Joint:
    name: str
    kind: str            # revolute | continuous
    parent: str
    child: str
    xyz: tuple
    axis: tuple
    effort: float
    velocity: float
    damping: float
    limit: float | None = None


JOINTS: list[Joint] = []
for _w in WHEELS:
    _x, _y = WHEEL_POS[_w]
    JOINTS.append(Joint(f"{_w}_steering", "revolute", "base_link", f"{_w}_steering_link", (_x, _y, AXLE_Z),
                        (0, 0, 1), STEER_EFFORT, STEER_VELOCITY, STEER_DAMPING, STEER_LIMIT))
    JOINTS.append(Joint(f"{_w}_traction", "continuous", f"{_w}_steering_link", f"{_w}_wheel_link", (0, 0, 0),
                        (0, 1, 0), TRACTION_EFFORT, TRACTION_VELOCITY, TRACTION_DAMPING))

# ----------------------------------------------------------------------------
# Inertia maths (as models/arm/generate.py)
# ----------------------------------------------------------------------------

def rot_z_to(d):
    d = np.asarray(d, float) / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = float(np.dot(z, d))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def prim_frame(p: Prim):
    if p.kind == "cylinder":
        a, b = np.array(p.fromto[:3], float), np.array(p.fromto[3:], float)
        return (a + b) / 2, rot_z_to(b - a), float(np.linalg.norm(b - a))
    return np.array(p.pos, float), np.eye(3), 0.0


def prim_local_inertia(p: Prim, length: float) -> np.ndarray:
    m = p.mass
    if p.kind == "cylinder":
        r, h = p.radius, length
        ixx = m * (3 * r * r + h * h) / 12.0
        return np.diag([ixx, ixx, m * r * r / 2.0])
    a, b, c = p.half
    return np.diag([m * (b * b + c * c) / 3.0, m * (a * a + c * c) / 3.0, m * (a * a + b * b) / 3.0])


def link_inertial(prims):
    M = sum(p.mass for p in prims)
    frames = [prim_frame(p) for p in prims]
    com = sum(p.mass * c for p, (c, _, _) in zip(prims, frames, strict=True)) / M
    I = np.zeros((3, 3))
    for p, (c, R, L) in zip(prims, frames, strict=True):
        d = c - com
        I += R @ prim_local_inertia(p, L) @ R.T
        I += p.mass * (np.dot(d, d) * np.eye(3) - np.outer(d, d))
    return M, com, (I + I.T) / 2


def fmt(v, nd=8):
    def one(x):
        x = float(x)
        s = f"{x:.{nd}g}" if abs(x) >= 1e-4 or x == 0 else f"{x:.6e}"
        return "0" if s in ("-0", "0", "-0.0") else s
    if np.ndim(v) == 0:
        return one(v)
    return " ".join(one(x) for x in v)


def R_to_rpy(R):
    p = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    return math.atan2(R[2, 1], R[2, 2]), p, math.atan2(R[1, 0], R[0, 0])


def fmt_rad(v):
    return " ".join(repr(float(round(x, 15))) if abs(x) > 1e-15 else "0" for x in v)


# ----------------------------------------------------------------------------
# URDF
# ----------------------------------------------------------------------------

def urdf_shape(p: Prim, indent: str, tag: str) -> list[str]:
    c, R, L = prim_frame(p)
    geom = (f'<cylinder radius="{fmt(p.radius)}" length="{fmt(L)}"/>' if p.kind == "cylinder"
            else f'<box size="{fmt(2 * np.array(p.half))}"/>')
    out = [f'{indent}<{tag} name="{p.name}">',
           f'{indent}  <origin xyz="{fmt(c)}" rpy="{fmt_rad(R_to_rpy(R))}"/>',
           f'{indent}  <geometry>{geom}</geometry>']
    if tag == "visual":
        out.append(f'{indent}  <material name="{p.name}_mat"><color rgba="{fmt(p.rgba)}"/></material>')
    out.append(f'{indent}</{tag}>')
    return out


def write_urdf(path):
    L = ['<?xml version="1.0"?>',
         '<!-- GENERATED by models/rover/generate.py - do not edit by hand. -->',
         '<!-- Four-wheel-steer rover (thesis seed 000): steering + traction motor per wheel. base_link floats. -->',
         '<robot name="hilsim_rover">']
    for link, prims in LINKS.items():
        M, com, I = link_inertial(prims)
        L.append(f'  <link name="{link}">')
        L.append('    <inertial>')
        L.append(f'      <origin xyz="{fmt(com)}" rpy="0 0 0"/>')
        L.append(f'      <mass value="{fmt(M)}"/>')
        L.append(f'      <inertia ixx="{fmt(I[0, 0])}" ixy="{fmt(I[0, 1])}" ixz="{fmt(I[0, 2])}" '
                 f'iyy="{fmt(I[1, 1])}" iyz="{fmt(I[1, 2])}" izz="{fmt(I[2, 2])}"/>')
        L.append('    </inertial>')
        for p in prims:
            L += urdf_shape(p, "    ", "visual")
        for p in prims:
            if p.collide:
                L += urdf_shape(p, "    ", "collision")
        L.append('  </link>')
    for j in JOINTS:
        L.append(f'  <joint name="{j.name}" type="{j.kind}">')
        L.append(f'    <parent link="{j.parent}"/>')
        L.append(f'    <child link="{j.child}"/>')
        L.append(f'    <origin xyz="{fmt(j.xyz)}" rpy="0 0 0"/>')
        L.append(f'    <axis xyz="{fmt(j.axis)}"/>')
        lim = f'lower="{fmt(-j.limit)}" upper="{fmt(j.limit)}" ' if j.limit is not None else ""
        L.append(f'    <limit {lim}effort="{fmt(j.effort)}" velocity="{fmt(j.velocity)}"/>')
        L.append(f'    <dynamics damping="{fmt(j.damping)}" friction="0"/>')
        L.append('  </joint>')
    for s, pos in SITES.items():
        L.append(f'  <link name="{s}_link"/>')
        L.append(f'  <joint name="{s}_joint" type="fixed">')
        L.append('    <parent link="base_link"/>')
        L.append(f'    <child link="{s}_link"/>')
        L.append(f'    <origin xyz="{fmt(pos)}" rpy="0 0 0"/>')
        L.append('  </joint>')
    L.append('</robot>')
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


# ----------------------------------------------------------------------------
# MJCF
# ----------------------------------------------------------------------------

def mjcf_geom(p: Prim) -> str:
    a = f'name="{p.name}" type="{p.kind}"'
    if p.kind == "cylinder":
        a += f' fromto="{fmt(p.fromto)}" size="{fmt(p.radius)}"'
    else:
        a += f' pos="{fmt(p.pos)}" size="{fmt(p.half)}"'
    if not p.collide:
        a += ' contype="0" conaffinity="0"'
    return f'<geom {a} mass="{fmt(p.mass)}" rgba="{fmt(p.rgba)}"/>'


def write_mjcf(path):
    L = ['<!-- GENERATED by models/rover/generate.py - do not edit by hand. -->',
         '<!-- Four-wheel-steer rover. Included by the worlds in models/worlds/',
         '     (<include file="../rover/rover.xml"/>). Rover geoms are in group 1 with contype 2 / conaffinity 1:',
         '     they touch the world (contype 1) but not each other, and the laser leaves group 1 out of its rays',
         '     (it does not see the robot). -->',
         '<mujoco model="hilsim_rover">',
         '  <compiler angle="radian" autolimits="true"/>',
         '  <option timestep="0.002" integrator="implicitfast"/>',
         '  <default>',
         '    <default class="rover">',
         '      <geom contype="2" conaffinity="1" group="1" condim="3" friction="1 0.005 0.0001"/>',
         '      <site group="1" size="0.02" rgba="0.1 0.8 0.1 1"/>',
         '      <motor ctrllimited="true"/>',
         '    </default>',
         '  </default>',
         '  <custom>',
         '    <!-- velocity limits (rad/s), same order as the actuators; MuJoCo does not enforce them -->',
         f'    <numeric name="rover_joint_velocity_limit" data="{fmt([j.velocity for j in JOINTS])}"/>',
         f'    <numeric name="rover_wheel_radius" data="{fmt(WHEEL_RADIUS)}"/>',
         '  </custom>',
         '  <worldbody>']
    children: dict[str, list[Joint]] = {}
    for j in JOINTS:
        children.setdefault(j.parent, []).append(j)

    def body(link: str, indent: str, joint: Joint | None) -> None:
        M, com, I = link_inertial(LINKS[link])
        pos = joint.xyz if joint is not None else (0, 0, START_Z)
        L.append(f'{indent}<body name="{link}" childclass="rover" pos="{fmt(pos)}">')
        if joint is None:
            L.append(f'{indent}  <freejoint name="base"/>')
        L.append(f'{indent}  <inertial pos="{fmt(com)}" mass="{fmt(M)}" '
                 f'fullinertia="{fmt([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])}"/>')
        if joint is not None:
            rng = f' range="{fmt(-joint.limit)} {fmt(joint.limit)}"' if joint.limit is not None else ' limited="false"'
            L.append(f'{indent}  <joint name="{joint.name}" type="hinge" axis="{fmt(joint.axis)}"{rng} '
                     f'damping="{fmt(joint.damping)}" armature="{fmt(ARMATURE)}"/>')
        for p in LINKS[link]:
            L.append(f'{indent}  {mjcf_geom(p)}')
        if joint is None:
            for s, spos in SITES.items():
                L.append(f'{indent}  <site name="{s}" pos="{fmt(spos)}"/>')
        for j in children.get(link, []):
            body(j.child, indent + "  ", j)
        L.append(f'{indent}</body>')

    body("base_link", "    ", None)
    L.append('  </worldbody>')
    L.append('  <actuator>')
    L.append('    <!-- torque motors named like their joints; hilsim turns them into position / velocity servos')
    L.append('         when the scenario gives a joint that interface (joints.<name>.interface) -->')
    for j in JOINTS:
        L.append(f'    <motor name="{j.name}" class="rover" joint="{j.name}" gear="1" '
                 f'ctrlrange="{fmt(-j.effort)} {fmt(j.effort)}"/>')
    L.append('  </actuator>')
    L.append('</mujoco>')
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


def main():
    write_urdf(os.path.join(HERE, "rover.urdf"))
    write_mjcf(os.path.join(HERE, "rover.xml"))
    total = 0.0
    for link, prims in LINKS.items():
        M, com, I = link_inertial(prims)
        total += M
        print(f"{link:18s} m={M:.3f} com={np.round(com, 4)} Idiag={np.round(np.diag(I), 5)}")
    print(f"total mass {total:.3f} kg -> wrote rover.urdf, rover.xml")


if __name__ == "__main__":
    main()
