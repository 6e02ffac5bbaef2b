"""What the model generators (models/arm/generate.py, models/rover/generate.py) share.

Primitive shapes with masses, the inertia maths (uniform density per primitive, exact solid
formulas, rotated into the link frame and shifted with the parallel-axis theorem), the number
formats of the generated files, and the URDF / MJCF pieces that do not depend on the robot.

Not run on its own: each generator puts this folder on ``sys.path`` and imports it, so
``python models/<robot>/generate.py`` works from anywhere. Only numpy is required.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

# ----------------------------------------------------------------------------
# Primitives.  Capsules/cylinders are given by segment end points (fromto, link
# frame) and radius; boxes by centre and half sizes (axis aligned with the link
# frame); spheres by centre and radius.
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
    collide: bool = True      # False: visual only (no contact)


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
    com = sum(p.mass * c for p, (c, _, _) in zip(prims, frames, strict=True)) / M
    I = np.zeros((3, 3))
    for p, (c, R, L) in zip(prims, frames, strict=True):
        d = c - com
        I += R @ prim_local_inertia(p, L) @ R.T                       # rotate into link frame
        I += p.mass * (np.dot(d, d) * np.eye(3) - np.outer(d, d))     # parallel-axis theorem
    I = (I + I.T) / 2
    return M, com, I


# ----------------------------------------------------------------------------
# Frames and number formats
# ----------------------------------------------------------------------------

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
    """Angles such as pi/2 are written with full precision; round-off (|x| <= 1e-15) as 0."""
    return " ".join(repr(float(round(x, 15))) if abs(x) > 1e-15 else "0" for x in v)


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


def urdf_link(link: str, prims: list[Prim]) -> list[str]:
    """A link: its inertial from the primitives, every primitive as visual, the colliding ones as collision."""
    M, com, I = link_inertial(prims)
    L = [f'  <link name="{link}">',
         '    <inertial>',
         f'      <origin xyz="{fmt(com)}" rpy="0 0 0"/>',
         f'      <mass value="{fmt(M)}"/>',
         f'      <inertia ixx="{fmt(I[0, 0])}" ixy="{fmt(I[0, 1])}" ixz="{fmt(I[0, 2])}" '
         f'iyy="{fmt(I[1, 1])}" iyz="{fmt(I[1, 2])}" izz="{fmt(I[2, 2])}"/>',
         '    </inertial>']
    for p in prims:
        L += urdf_shape(p, "    ", "visual")
    for p in prims:
        if p.collide:
            L += urdf_shape(p, "    ", "collision")
    L.append('  </link>')
    return L


def urdf_joint(name: str, kind: str, parent: str, child: str, xyz, axis, effort: float, velocity: float,
               damping: float, rpy: str = "0 0 0", lower: float | None = None, upper: float | None = None) -> list[str]:
    """A moving joint; ``lower``/``upper`` only where it has limits (not a continuous joint)."""
    lim = f'lower="{fmt(lower)}" upper="{fmt(upper)}" ' if lower is not None else ""
    return [f'  <joint name="{name}" type="{kind}">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{child}"/>',
            f'    <origin xyz="{fmt(xyz)}" rpy="{rpy}"/>',
            f'    <axis xyz="{fmt(axis)}"/>',
            f'    <limit {lim}effort="{fmt(effort)}" velocity="{fmt(velocity)}"/>',
            f'    <dynamics damping="{fmt(damping)}" friction="0"/>',
            '  </joint>']


def urdf_fixed_frame(name: str, parent: str, xyz) -> list[str]:
    """A massless frame (``<name>_link``) fixed to ``parent`` by ``<name>_joint``."""
    return [f'  <link name="{name}_link"/>',
            f'  <joint name="{name}_joint" type="fixed">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{name}_link"/>',
            f'    <origin xyz="{fmt(xyz)}" rpy="0 0 0"/>',
            '  </joint>']


# ----------------------------------------------------------------------------
# MJCF
# ----------------------------------------------------------------------------

def mjcf_geom(p: Prim) -> str:
    a = f'name="{p.name}" type="{p.kind}"'
    if p.kind in ("capsule", "cylinder"):
        a += f' fromto="{fmt(p.fromto)}" size="{fmt(p.radius)}"'
    elif p.kind == "box":
        a += f' pos="{fmt(p.pos)}" size="{fmt(p.half)}"'
    else:
        a += f' pos="{fmt(p.pos)}" size="{fmt(p.radius)}"'
    if not p.collide:
        a += ' contype="0" conaffinity="0"'
    # `mass` is informative only: the explicit <inertial> wins (inertiafromgeom="auto");
    # models/arm/verify.py recompiles with inertiafromgeom="true" to cross-check the generator.
    return f'<geom {a} mass="{fmt(p.mass)}" rgba="{fmt(p.rgba)}"/>'


def mjcf_inertial(prims: list[Prim], indent: str) -> str:
    M, com, I = link_inertial(prims)
    return (f'{indent}<inertial pos="{fmt(com)}" mass="{fmt(M)}" '
            f'fullinertia="{fmt([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])}"/>')


# ----------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------

def write_lines(path, lines: list[str]) -> None:
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def generate(here: str, robot: str, write_urdf, write_mjcf, links: dict[str, list[Prim]], width: int,
             decimals: int) -> None:
    """A generator's main: ``<robot>.urdf`` and ``<robot>.xml`` into ``here`` (the generator's folder),
    then each link's mass, COM and principal inertias, and the total mass, on stdout."""
    write_urdf(os.path.join(here, f"{robot}.urdf"))
    write_mjcf(os.path.join(here, f"{robot}.xml"))
    wrote = f"{robot}.urdf, {robot}.xml"
    total = 0.0
    for link, prims in links.items():
        M, com, I = link_inertial(prims)
        total += M
        print(f"{link:{width}s} m={M:.3f} com={np.round(com, 4)} Idiag={np.round(np.diag(I), decimals)}")
    print(f"total mass {total:.3f} kg -> wrote {wrote}")
