"""A lab's URDF read for import: links (inertial, visual and collision geometry), joints (limits,
dynamics, mimic) and the kinematic tree, with every fault said as one line naming the file, the
element and why (:class:`ImportFailure`).

Only the robot's own ``<link>`` and ``<joint>`` elements count (direct children of ``<robot>``):
``<transmission>``, ``<gazebo>`` and ``<ros2_control>`` blocks hold ``<joint>`` elements of their own.
Mesh URIs are resolved as ROS resolves them (:func:`resolve_uri`): ``package://PKG/rest`` through the
package path (``--package-path``, ``ROS_PACKAGE_PATH``, ``AMENT_PREFIX_PATH``'s ``share/``), ``file://``
and plain paths relative to the URDF's folder.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from hilsim.core.config import ConfigError

MOVING = ("revolute", "continuous", "prismatic")
KNOWN_JOINTS = (*MOVING, "fixed", "floating", "planar")


class ImportFailure(ConfigError):
    """The URDF cannot be imported: one line naming the file, the element and why."""


@dataclass(frozen=True)
class Origin:
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Geometry:
    """One ``<visual>`` or ``<collision>``: kind box | cylinder | sphere | mesh."""

    kind: str
    origin: Origin
    size: tuple[float, ...] = ()  # box: full sizes; cylinder: radius, length; sphere: radius
    uri: str = ""  # mesh: as written in the URDF
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    rgba: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class Inertial:
    origin: Origin
    mass: float
    inertia: tuple[float, float, float, float, float, float]  # ixx iyy izz ixy ixz iyz


@dataclass
class Link:
    name: str
    inertial: Inertial | None = None
    visuals: list[Geometry] = field(default_factory=list)
    collisions: list[Geometry] = field(default_factory=list)


@dataclass(frozen=True)
class Mimic:
    joint: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str
    parent: str
    child: str
    origin: Origin
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    lower: float = -math.inf
    upper: float = math.inf
    effort: float = math.inf
    velocity: float = math.inf
    damping: float = 0.0
    friction: float = 0.0
    mimic: Mimic | None = None

    @property
    def moving(self) -> bool:
        return self.kind in MOVING

    @property
    def limited(self) -> bool:
        """Continuous joints turn freely; so does a revolute joint the URDF gives no finite range."""
        return self.kind != "continuous" and math.isfinite(self.lower) and math.isfinite(self.upper) \
            and self.upper > self.lower


@dataclass
class Urdf:
    path: Path
    name: str
    links: dict[str, Link]
    joints: list[Joint]

    @property
    def root(self) -> str:
        children = {j.child for j in self.joints}
        return next(n for n in self.links if n not in children)

    def joint_to(self, link: str) -> Joint | None:
        return next((j for j in self.joints if j.child == link), None)

    def chain(self, link: str) -> list[Joint]:
        """The joints from the root to ``link``, root first."""
        out = []
        j = self.joint_to(link)
        while j is not None:
            out.append(j)
            j = self.joint_to(j.parent)
        return out[::-1]

    @property
    def actuated(self) -> list[Joint]:
        """The joints that get a motor: moving and not mimicking another, in the URDF's order."""
        return [j for j in self.joints if j.moving and j.mimic is None]


def _floats(text: str | None, n: int, default: tuple[float, ...], where: str) -> tuple[float, ...]:
    if text is None:
        return default
    try:
        vals = tuple(float(v) for v in text.split())
    except ValueError:
        raise ImportFailure(f"{where}: expected {n} numbers, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ImportFailure(f"{where}: expected {n} finite numbers, got {text!r}")
    return vals


def _num(el: ET.Element, attr: str, default: float, where: str) -> float:
    text = el.get(attr)
    if text is None:
        return default
    try:
        return float(text)
    except ValueError:
        raise ImportFailure(f"{where} {attr}: expected a number, got {text!r}") from None


def _origin(el: ET.Element | None, where: str) -> Origin:
    if el is None:
        return Origin()
    return Origin(_floats(el.get("xyz"), 3, (0.0, 0.0, 0.0), f"{where} <origin xyz>"),  # type: ignore[arg-type]
                  _floats(el.get("rpy"), 3, (0.0, 0.0, 0.0), f"{where} <origin rpy>"))  # type: ignore[arg-type]


def _geometry(el: ET.Element, where: str, materials: dict[str, tuple[float, float, float, float]]) -> Geometry | None:
    g = el.find("geometry")
    if g is None or len(g) == 0:
        raise ImportFailure(f"{where}: no <geometry> inside")
    shape = g[0]
    origin = _origin(el.find("origin"), where)
    rgba = None
    mat = el.find("material")
    if mat is not None:
        col = mat.find("color")
        if col is not None:
            rgba = _floats(col.get("rgba"), 4, (0.7, 0.7, 0.7, 1.0), f"{where} <material><color rgba>")
        elif mat.get("name") in materials:
            rgba = materials[mat.get("name", "")]
    w = f"{where} <{shape.tag}>"
    if shape.tag == "box":
        return Geometry("box", origin, _floats(shape.get("size"), 3, (0.0, 0.0, 0.0), f"{w} size"), rgba=rgba)
    if shape.tag == "cylinder":
        return Geometry("cylinder", origin, (_num(shape, "radius", 0.0, w), _num(shape, "length", 0.0, w)), rgba=rgba)
    if shape.tag == "sphere":
        return Geometry("sphere", origin, (_num(shape, "radius", 0.0, w),), rgba=rgba)
    if shape.tag == "mesh":
        uri = shape.get("filename", "")
        if not uri:
            raise ImportFailure(f"{w}: no filename")
        scale = _floats(shape.get("scale"), 3, (1.0, 1.0, 1.0), f"{w} scale")
        return Geometry("mesh", origin, uri=uri, scale=scale, rgba=rgba)  # type: ignore[arg-type]
    raise ImportFailure(f"{w}: unknown geometry (expected box, cylinder, sphere or mesh)")


def read(path: Path) -> Urdf:
    """The URDF at ``path``, checked: a tree of links, known joint kinds, finite numbers."""
    path = Path(path)
    if not path.is_file():
        raise ImportFailure(f"{path}: no such file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ImportFailure(f"{path}: not XML: {e}") from None
    if root.tag != "robot":
        raise ImportFailure(f"{path}: <{root.tag}>: expected a URDF (<robot> at the top)")
    materials: dict[str, tuple[float, float, float, float]] = {}
    for m in root.findall("material"):
        c = m.find("color")
        if c is not None and m.get("name"):
            materials[m.get("name", "")] = _floats(c.get("rgba"), 4, (0.7, 0.7, 0.7, 1.0),  # type: ignore[assignment]
                                                   f"{path}: <material name={m.get('name')!r}>")
    links: dict[str, Link] = {}
    for el in root.findall("link"):
        name = el.get("name", "")
        where = f"{path}: <link name={name!r}>"
        if not name:
            raise ImportFailure(f"{path}: <link> without a name")
        if name in links:
            raise ImportFailure(f"{where}: a second link of that name")
        link = Link(name)
        ine = el.find("inertial")
        if ine is not None:
            mass_el, i_el = ine.find("mass"), ine.find("inertia")
            mass = _num(mass_el, "value", 0.0, f"{where} <mass>") if mass_el is not None else 0.0
            tensor = tuple(_num(i_el, a, 0.0, f"{where} <inertia>") if i_el is not None else 0.0
                           for a in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz"))
            link.inertial = Inertial(_origin(ine.find("origin"), f"{where} <inertial>"), mass, tensor)  # type: ignore[arg-type]
        for k, v in enumerate(el.findall("visual")):
            g = _geometry(v, f"{where} <visual> {k}", materials)
            if g is not None:
                link.visuals.append(g)
        for k, c in enumerate(el.findall("collision")):
            g = _geometry(c, f"{where} <collision> {k}", materials)
            if g is not None:
                link.collisions.append(g)
        links[name] = link
    if not links:
        raise ImportFailure(f"{path}: no <link>")
    joints: list[Joint] = []
    children: dict[str, str] = {}
    for el in root.findall("joint"):
        name = el.get("name", "")
        kind = el.get("type", "")
        where = f"{path}: <joint name={name!r}>"
        if kind not in KNOWN_JOINTS:
            raise ImportFailure(f"{where} type={kind!r}: expected one of {', '.join(KNOWN_JOINTS)}")
        if kind in ("floating", "planar"):
            raise ImportFailure(f"{where} type={kind!r}: a mobile base or free body; the import takes fixed-base arms "
                                "(docs/robots.md)")
        p, c = el.find("parent"), el.find("child")
        if p is None or c is None:
            raise ImportFailure(f"{where}: needs <parent link> and <child link>")
        parent, child = p.get("link", ""), c.get("link", "")
        for role, ln in (("parent", parent), ("child", child)):
            if ln not in links:
                raise ImportFailure(f"{where} <{role} link={ln!r}>: no such link")
        if child in children:
            raise ImportFailure(f"{where} <child link={child!r}>: the link already has a parent joint "
                                f"({children[child]!r}): a closed chain (parallel linkage), which the import "
                                "cannot take")
        children[child] = name
        ax_el = el.find("axis")
        axis = _floats(ax_el.get("xyz") if ax_el is not None else None, 3, (1.0, 0.0, 0.0), f"{where} <axis xyz>")
        norm = math.sqrt(sum(a * a for a in axis))
        if kind in MOVING and norm == 0:
            raise ImportFailure(f"{where} <axis xyz>: a zero axis")
        axis = tuple(a / norm for a in axis) if norm else (1.0, 0.0, 0.0)
        lim = el.find("limit")
        lower = upper = math.nan
        effort = velocity = math.inf
        if lim is not None:
            lower = _num(lim, "lower", math.nan, f"{where} <limit>")
            upper = _num(lim, "upper", math.nan, f"{where} <limit>")
            effort = _num(lim, "effort", math.inf, f"{where} <limit>")
            velocity = _num(lim, "velocity", math.inf, f"{where} <limit>")
        elif kind in ("revolute", "prismatic"):
            raise ImportFailure(f"{where}: a {kind} joint needs <limit> (lower, upper, effort, velocity)")
        if kind == "continuous" or math.isnan(lower) or math.isnan(upper) or lower >= upper:
            if kind == "prismatic":
                raise ImportFailure(f"{where} <limit>: a prismatic joint needs lower < upper")
            lower, upper = -math.inf, math.inf
        dyn = el.find("dynamics")
        damping = _num(dyn, "damping", 0.0, f"{where} <dynamics>") if dyn is not None else 0.0
        friction = _num(dyn, "friction", 0.0, f"{where} <dynamics>") if dyn is not None else 0.0
        mim = el.find("mimic")
        mimic = None
        if mim is not None:
            mimic = Mimic(mim.get("joint", ""), _num(mim, "multiplier", 1.0, f"{where} <mimic>"),
                          _num(mim, "offset", 0.0, f"{where} <mimic>"))
        joints.append(Joint(name, kind, parent, child, _origin(el.find("origin"), where), axis,  # type: ignore[arg-type]
                            lower, upper, effort, velocity, max(damping, 0.0), max(friction, 0.0), mimic))
    names = {j.name for j in joints}
    for j in joints:
        if j.mimic is not None and (j.mimic.joint not in names or j.mimic.joint == j.name):
            raise ImportFailure(f"{path}: <joint name={j.name!r}> <mimic joint={j.mimic.joint!r}>: no such other joint")
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise ImportFailure(f"{path}: <link>s {', '.join(roots[:4])}: expected one tree with one root link, "
                            f"found {len(roots)} roots")
    u = Urdf(path, root.get("name", path.stem), links, joints)
    if not u.actuated:
        raise ImportFailure(f"{path}: <joint>: no movable joint (revolute, continuous or prismatic) to drive")
    return u


def package_roots(extra: list[Path] | None = None) -> list[Path]:
    """Where ``package://`` looks, in ROS's order: the given folders, ``ROS_PACKAGE_PATH``, and each
    ``AMENT_PREFIX_PATH`` prefix's ``share/``."""
    out = [Path(p) for p in extra or []]
    out += [Path(p) for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
    out += [Path(p) / "share" for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return out


def _find_package(name: str, roots: list[Path]) -> Path | None:
    for r in roots:
        if (r / name).is_dir():
            return r / name
        if r.name == name and r.is_dir():  # the package's own folder given
            return r
        # ROS_PACKAGE_PATH entries are searched below, as rospack does (a package.xml names it)
        for pkg_xml in sorted(r.glob("*/package.xml")) if r.is_dir() else []:
            try:
                if ET.parse(pkg_xml).getroot().findtext("name") == name:
                    return pkg_xml.parent
            except ET.ParseError:
                continue
    return None


def resolve_uri(uri: str, urdf_dir: Path, roots: list[Path]) -> Path | None:
    """The file a mesh URI names, or None when it cannot be found."""
    if uri.startswith("package://"):
        pkg, _, rest = uri[len("package://"):].partition("/")
        base = _find_package(pkg, roots)
        return base / rest if base is not None and (base / rest).is_file() else None
    if uri.startswith("file://"):
        p = Path(uri[len("file://"):])
    else:
        p = Path(uri)
    p = p if p.is_absolute() else urdf_dir / p
    return p if p.is_file() else None
