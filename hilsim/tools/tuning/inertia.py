"""``hilsim inertia FILE``: a link's mass, centre of mass and inertia tensor from primitive bodies.

As the arm paper estimates its links' moments of inertia: each link is simplified into a few
primitives of uniform density, each primitive's inertia about its own centre is a closed form,
turned into the link frame by its orientation (``I = R I₀ Rᵀ``), and moved to the link's centre of
mass by the parallel-axis theorem in tensor form (``I += m (|d|² E − d dᵀ)``); the link's tensor is
the sum (the paper's equations 1–3).

The FILE (YAML) names links and their parts; poses are in the link frame (metres, radians, ``rpy``
as in URDF: fixed axes X, then Y, then Z). A cylinder's axis, a column's axis, is its frame's z::

    links:
      base_link:                      # the paper's base: a thin-walled square shell + a stepper motor
        - {shape: thin_square_column, mass: 0.55, side: 0.13, height: 0.09, pos: [0, 0, 0.045]}
        - {shape: box, mass: 0.35, size: [0.042, 0.042, 0.048], pos: [0, 0, 0.024]}

Shapes and their parameters (closed forms about the centre, own frame):

================== ========================= =========================================================
shape              parameters                inertia
================== ========================= =========================================================
box                size [x, y, z] (full)     m(y²+z²)/12, m(x²+z²)/12, m(x²+y²)/12
cylinder           radius, length            m(3r²+l²)/12 (x, y), m r²/2 (z)
hollow_cylinder    inner_radius, radius,     m(3(r₁²+r₂²)+l²)/12 (x, y), m(r₁²+r₂²)/2 (z)
                   length
thin_square_column side, height [, wall]     thin walls (4 plates, open ends): m(2a²+h²)/12 (x, y),
                                             m a²/3 (z); with ``wall`` the exact hollow square prism
sphere             radius                    2/5 m r²
point              (mass only)               0
================== ========================= =========================================================

:func:`mujoco_inertial` builds the same parts as MuJoCo geoms (a hollow cylinder as a
1024-sided annular mesh, a thin column as four wall boxes) and reads MuJoCo's own figures for the
cross-check printed by the command. ``--urdf FILE --link NAME`` replaces that link's
``<inertial>`` element in a URDF (nothing else in the file changes).
"""

from __future__ import annotations

import argparse
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, model_validator

from hilsim.core.config import ConfigError, format_error

Vec3 = tuple[float, float, float]
THIN = 1e-4  # wall of a "thin" column in MuJoCo's cross-check, as a fraction of its side
MESH_SIDES = 1024  # sides of the polygon standing in for a hollow cylinder in MuJoCo


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mass: PositiveFloat
    pos: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)


class Box(_Part):
    shape: Literal["box"]
    size: tuple[PositiveFloat, PositiveFloat, PositiveFloat]


class Cylinder(_Part):
    shape: Literal["cylinder"]
    radius: PositiveFloat
    length: PositiveFloat


class HollowCylinder(_Part):
    shape: Literal["hollow_cylinder"]
    inner_radius: PositiveFloat
    radius: PositiveFloat
    length: PositiveFloat

    @model_validator(mode="after")
    def _radii(self) -> HollowCylinder:
        if self.inner_radius >= self.radius:
            raise ValueError(f"inner_radius {self.inner_radius} must be smaller than radius {self.radius}")
        return self


class ThinSquareColumn(_Part):
    shape: Literal["thin_square_column"]
    side: PositiveFloat
    height: PositiveFloat
    wall: PositiveFloat | None = None  # None: thin walls (the limit of zero thickness)

    @model_validator(mode="after")
    def _wall(self) -> ThinSquareColumn:
        if self.wall is not None and 2 * self.wall >= self.side:
            raise ValueError(f"wall {self.wall} must be less than half the side {self.side}")
        return self


class Sphere(_Part):
    shape: Literal["sphere"]
    radius: PositiveFloat


class Point(_Part):
    shape: Literal["point"]


Part = Annotated[Box | Cylinder | HollowCylinder | ThinSquareColumn | Sphere | Point, Field(discriminator="shape")]


class InertiaFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    links: dict[str, list[Part]] = Field(min_length=1)

    @model_validator(mode="after")
    def _nonempty(self) -> InertiaFile:
        for name, parts in self.links.items():
            if not parts:
                raise ValueError(f"link {name} has no parts")
        return self


@dataclass(frozen=True)
class Inertial:
    """A link's inertial: mass, centre of mass and the inertia tensor about it (link-frame axes)."""

    mass: float
    com: np.ndarray  # (3,)
    tensor: np.ndarray  # (3, 3), symmetric

    def urdf(self, indent: str = "    ") -> str:
        i = self.tensor
        c = " ".join(_g(x) for x in self.com)
        return (f"{indent}<inertial>\n"
                f'{indent}  <origin xyz="{c}" rpy="0 0 0"/>\n'
                f'{indent}  <mass value="{_g(self.mass)}"/>\n'
                f'{indent}  <inertia ixx="{_g(i[0, 0])}" ixy="{_g(i[0, 1])}" ixz="{_g(i[0, 2])}" '
                f'iyy="{_g(i[1, 1])}" iyz="{_g(i[1, 2])}" izz="{_g(i[2, 2])}"/>\n'
                f"{indent}</inertial>")

    def as_dict(self) -> dict[str, object]:
        i = self.tensor
        return {"mass": self.mass, "com": self.com.tolist(),
                "inertia": {"ixx": i[0, 0], "ixy": i[0, 1], "ixz": i[0, 2], "iyy": i[1, 1], "iyz": i[1, 2],
                            "izz": i[2, 2]},
                "principal_moments": np.linalg.eigvalsh(i).tolist()}


def _g(x: float) -> str:
    x = float(x)
    return "0" if abs(x) < 1e-15 else f"{x:.9g}"


# ---------------------------------------------------------------- closed forms
def rpy_matrix(rpy: Vec3) -> np.ndarray:
    """URDF's rpy: rotations about the fixed X, then Y, then Z axes (R = Rz·Ry·Rx)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _box(m: float, x: float, y: float, z: float) -> np.ndarray:
    return np.diag([m * (y * y + z * z), m * (x * x + z * z), m * (x * x + y * y)]) / 12.0


def local_inertia(p: Part) -> np.ndarray:
    """The closed form about the part's own centre, in its own frame."""
    m = p.mass
    if isinstance(p, Box):
        return _box(m, *p.size)
    if isinstance(p, Cylinder):
        r, h = p.radius, p.length
        return np.diag([m * (3 * r * r + h * h) / 12, m * (3 * r * r + h * h) / 12, m * r * r / 2])
    if isinstance(p, HollowCylinder):
        s, h = p.inner_radius**2 + p.radius**2, p.length
        return np.diag([m * (3 * s + h * h) / 12, m * (3 * s + h * h) / 12, m * s / 2])
    if isinstance(p, ThinSquareColumn):
        a, h = p.side, p.height
        if p.wall is None:
            return np.diag([m * (2 * a * a + h * h) / 12, m * (2 * a * a + h * h) / 12, m * a * a / 3])
        b = a - 2 * p.wall  # outer prism minus the inner one, same density
        v_out, v_in = a * a, b * b
        rho = m / (v_out - v_in)
        return _box(rho * v_out, a, a, h) - _box(rho * v_in, b, b, h)
    if isinstance(p, Sphere):
        return np.eye(3) * 0.4 * m * p.radius**2
    return np.zeros((3, 3))  # a point mass


def combine(parts: list[Part]) -> Inertial:
    """Mass, centre of mass and inertia tensor about it of a link made of ``parts``."""
    mass = sum(p.mass for p in parts)
    com = sum(p.mass * np.asarray(p.pos, float) for p in parts) / mass
    tensor = np.zeros((3, 3))
    for p in parts:
        r = rpy_matrix(p.rpy)
        d = np.asarray(p.pos, float) - com
        tensor += r @ local_inertia(p) @ r.T  # the part's axes into the link's
        tensor += p.mass * (float(d @ d) * np.eye(3) - np.outer(d, d))  # parallel-axis theorem
    return Inertial(float(mass), np.asarray(com, float), (tensor + tensor.T) / 2)


# ---------------------------------------------------------------- MuJoCo's own figures
def _annulus_mesh(r_in: float, r_out: float, length: float, n: int = MESH_SIDES) -> tuple[list[float], list[int]]:
    """A closed, outward-oriented mesh of an n-sided annular prism along z."""
    a = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    verts = []
    for r in (r_out, r_in):
        for z in (-length / 2, length / 2):
            verts += [(r * math.cos(t), r * math.sin(t), z) for t in a]
    oi_lo, oi_hi, ii_lo, ii_hi = 0, n, 2 * n, 3 * n  # outer/inner ring, bottom/top
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [(oi_lo + i, oi_lo + j, oi_hi + j), (oi_lo + i, oi_hi + j, oi_hi + i)]  # outer wall, out
        faces += [(ii_lo + i, ii_hi + j, ii_lo + j), (ii_lo + i, ii_hi + i, ii_hi + j)]  # inner wall, in
        faces += [(oi_hi + i, oi_hi + j, ii_hi + j), (oi_hi + i, ii_hi + j, ii_hi + i)]  # top, +z
        faces += [(oi_lo + i, ii_lo + j, oi_lo + j), (oi_lo + i, ii_lo + i, ii_lo + j)]  # bottom, -z
    return [c for v in verts for c in v], [k for f in faces for k in f]


def _geoms(i: int, p: Part) -> tuple[list[str], list[str]]:
    """MJCF geoms (and mesh assets) of one part; each gets its share of the part's mass."""
    pose = f'pos="{" ".join(map(repr, p.pos))}" euler="{" ".join(map(repr, p.rpy))}"'
    m = p.mass
    if isinstance(p, Box):
        half = " ".join(repr(s / 2) for s in p.size)
        return [f'<geom type="box" size="{half}" mass="{m!r}" {pose}/>'], []
    if isinstance(p, Cylinder):
        return [f'<geom type="cylinder" size="{p.radius!r} {p.length / 2!r}" mass="{m!r}" {pose}/>'], []
    if isinstance(p, Sphere):
        return [f'<geom type="sphere" size="{p.radius!r}" mass="{m!r}" {pose}/>'], []
    if isinstance(p, Point):
        # a body of its own with an explicit inertial (MuJoCo takes no massive geom of zero size)
        return [f'<body pos="{" ".join(map(repr, p.pos))}"><inertial pos="0 0 0" mass="{m!r}" '
                f'diaginertia="1e-15 1e-15 1e-15"/></body>'], []
    if isinstance(p, HollowCylinder):
        v, f = _annulus_mesh(p.inner_radius, p.radius, p.length)
        asset = (f'<mesh name="part{i}" inertia="exact" vertex="{" ".join(map(repr, v))}" '
                 f'face="{" ".join(map(str, f))}"/>')
        return [f'<geom type="mesh" mesh="part{i}" mass="{m!r}" {pose}/>'], [asset]
    assert isinstance(p, ThinSquareColumn)
    a, h = p.side, p.height
    w = p.wall if p.wall is not None else THIN * a
    # four wall boxes in a child body posed like the part; their masses by volume (uniform density)
    walls = [((a / 2 - w / 2, 0.0), (w, a, h)), ((-(a / 2 - w / 2), 0.0), (w, a, h)),
             ((0.0, a / 2 - w / 2), (a - 2 * w, w, h)), ((0.0, -(a / 2 - w / 2)), (a - 2 * w, w, h))]
    vol = sum(s[0] * s[1] * s[2] for _, s in walls)
    inner = [f'<geom type="box" size="{s[0] / 2!r} {s[1] / 2!r} {s[2] / 2!r}" pos="{x!r} {y!r} 0" '
             f'mass="{m * s[0] * s[1] * s[2] / vol!r}"/>' for (x, y), s in walls]
    return [f'<body {pose}>{"".join(inner)}</body>'], []


def mujoco_inertial(parts: list[Part]) -> Inertial:
    """MuJoCo's mass, centre of mass and inertia tensor (about it, link axes) of the same parts,
    compiled from geoms (``inertiafromgeom``; a point mass is a child body with an explicit inertial);
    the parts' child bodies are summed into the link here."""
    import mujoco

    geoms, assets = [], []
    for i, p in enumerate(parts):
        g, a = _geoms(i, p)
        geoms += g
        assets += a
    xml = (f'<mujoco><compiler angle="radian" eulerseq="XYZ" inertiafromgeom="auto"/>'
           f'<asset>{"".join(assets)}</asset>'
           f'<worldbody><body name="link">{"".join(geoms)}</body></worldbody></mujoco>')
    spec = mujoco.MjSpec.from_string(xml)
    m = spec.compile()
    # sum every body below the link (the column's wall body) into the link frame
    data = mujoco.MjData(m)
    mujoco.mj_forward(m, data)
    link = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "link")
    bodies = [b for b in range(m.nbody) if b == link or m.body_rootid[b] == link]
    mass = float(sum(m.body_mass[b] for b in bodies))
    com = sum(m.body_mass[b] * data.xipos[b] for b in bodies) / mass
    tensor = np.zeros((3, 3))
    for b in bodies:
        r = data.ximat[b].reshape(3, 3)
        d = data.xipos[b] - com
        tensor += r @ np.diag(m.body_inertia[b]) @ r.T + m.body_mass[b] * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return Inertial(mass, np.asarray(com, float), (tensor + tensor.T) / 2)


def compare(a: Inertial, b: Inertial) -> float:
    """Largest relative difference of mass, centre of mass and tensor (scaled by their norms)."""
    scale = max(float(np.abs(a.tensor).max()), 1e-300)
    com_scale = max(float(np.abs(a.com).max()), 1e-3)
    return max(abs(a.mass - b.mass) / a.mass, float(np.abs(a.com - b.com).max()) / com_scale,
               float(np.abs(a.tensor - b.tensor).max()) / scale)


# ---------------------------------------------------------------- files
def load(path: str | Path) -> InertiaFile:
    p = Path(path)
    try:
        raw = yaml.safe_load(p.read_text())
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not YAML: {str(e).splitlines()[0]}") from None
    try:
        return InertiaFile.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(format_error(p, e)) from None


def write_urdf(urdf: str | Path, link: str, inertial: Inertial) -> None:
    """Replace (or add) the ``<inertial>`` element of ``link`` in a URDF; the rest stays byte for byte."""
    path = Path(urdf)
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    head = re.search(rf'<link\s+name="{re.escape(link)}"\s*(/?)>', text)
    if head is None:
        names = re.findall(r'<link\s+name="([^"]+)"', text)
        raise ConfigError(f"{path}: no link {link!r} (links: {', '.join(names)})")
    indent = re.match(r"[ \t]*", text[text.rfind("\n", 0, head.start()) + 1:]).group(0) + "  "  # type: ignore[union-attr]
    block = inertial.urdf(indent)
    if head.group(1):  # <link name="x"/>: open it up
        new = f'<link name="{link}">\n{block}\n{indent[:-2]}</link>'
        text = text[:head.start()] + new + text[head.end():]
    else:
        end = text.index("</link>", head.end())
        body = text[head.end():end]
        old = re.search(r"[ \t]*<inertial>.*?</inertial>", body, re.S)
        if old is not None:
            body = body[:old.start()] + block + body[old.end():]
        else:
            body = "\n" + block + body
        text = text[:head.end()] + body + text[end:]
    path.write_text(text)


def cmd_inertia(args: argparse.Namespace) -> int:
    f = load(args.file)
    links = [args.link] if args.link else list(f.links)
    for name in links:
        if name not in f.links:
            raise ConfigError(f"{args.file}: no link {name!r} (links: {', '.join(f.links)})")
    if args.urdf and len(links) != 1:
        raise ConfigError(f"--urdf: the file has {len(links)} links; say which with --link")
    out = {}
    for name in links:
        ours = combine(f.links[name])
        theirs = mujoco_inertial(f.links[name])
        diff = compare(ours, theirs)
        out[name] = {**ours.as_dict(), "mujoco_relative_difference": diff}
        if not args.json:
            print(f"{name}: {len(f.links[name])} parts, mass {ours.mass:.6g} kg, "
                  f"centre of mass {np.array2string(ours.com, precision=6)} m")
            print("  inertia about the centre of mass [kg m^2]:")
            for row in ours.tensor:
                print("   " + " ".join(f"{x:14.6e}" for x in row))
            print(f"  principal moments: {', '.join(f'{x:.6e}' for x in np.linalg.eigvalsh(ours.tensor))}")
            print(f"  MuJoCo's own figures for the same geoms: relative difference {diff:.1e}")
            print(ours.urdf("  "))
        if args.urdf:
            write_urdf(args.urdf, name, ours)
            if not args.json:
                print(f"written: <inertial> of {name} in {args.urdf}")
    if args.json:
        print(json.dumps(out))
    return 0
