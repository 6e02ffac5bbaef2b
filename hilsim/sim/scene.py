"""The world's static geometry and geodetic datum, read from the scenario's MuJoCo model, for the recorder.

:meth:`Scene.load` compiles the world model (``world.model``, the robot included) once, poses it
at its reference configuration and keeps every geom that cannot move: geoms of the world body
and of bodies welded to it, minus the robot's own bodies (those named like a link of the
scenario's URDF, and everything below them). Each becomes a :class:`StaticGeom` in world
coordinates (frame ``world``): boxes, planes, cylinders, spheres, ellipsoids, capsules and
meshes; height fields are not drawn (listed in :attr:`Scene.skipped`).

:meth:`Scene.log_static` writes them once, as static Rerun entities ``world/<geom name>``
(Boxes3D, Cylinders3D, Ellipsoids3D, Capsules3D, Mesh3D; a plane is a quad). An unbounded or very
large plane (the outdoor ground is 200 m across) is drawn only as far as the other geometry
reaches plus a margin (:data:`PLANE_MARGIN`), so the viewer's camera frames the world rather than the horizon.

Also here: the robot's placement in the world (a fixed base's root body pose; the size of a
mobile base's chassis, drawn where the odometry thinks it is) and the world's geodetic datum
(:class:`Datum`, the GPS sensor's convention: world X north, Y east), so the recorder can put
world positions on the map and GPS fixes into the world.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core.geometry import heading

# A plane is drawn this far beyond the rest of the static geometry: a quarter of that geometry's
# reach, between 0.5 m and PLANE_MARGIN (a table's floor stays small, the outdoor ground 5 m wide)
PLANE_MARGIN = 5.0  # [m]
PLANE_MARGIN_FRACTION = 0.25
PLANE_DEFAULT = 10.0  # [m] half size of an infinite plane in an otherwise empty world
GEOM_KINDS = {0: "plane", 2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder", 6: "box", 7: "mesh"}
DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's geom colour when none is given (a material's then wins)
TEXROLE_RGB = 1  # mjTEXROLE_RGB: the colour texture of a material


@dataclasses.dataclass(frozen=True)
class StaticGeom:
    """One static geom in world coordinates.

    ``size`` is MuJoCo's: box half sizes; plane half sizes in x, y (as drawn, see
    :data:`PLANE_MARGIN`); cylinder / capsule radius and half length; sphere radius; ellipsoid
    semi-axes. ``quat`` is (x, y, z, w). ``vertices``/``faces``: a mesh's, in world coordinates.
    """

    name: str
    kind: str
    pos: np.ndarray
    quat: np.ndarray
    size: np.ndarray
    rgba: tuple[float, float, float, float]
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None

    @property
    def half_extent(self) -> np.ndarray:
        """Half sizes of the world-axis-aligned box around the geom (for a plane: its drawn quad)."""
        if self.kind == "mesh":
            return np.max(np.abs(self.vertices - self.pos), axis=0)  # type: ignore[operator]
        r, s = self.size[0], self.size
        local = {"box": s, "ellipsoid": s, "sphere": np.array([r, r, r]), "plane": np.array([s[0], s[1], 0.0]),
                 "cylinder": np.array([r, r, s[1]]), "capsule": np.array([r, r, s[1] + r])}[self.kind]
        return np.abs(self.rotation) @ local

    @property
    def rotation(self) -> np.ndarray:
        """The geom's rotation matrix (its axes in world coordinates, as columns)."""
        x, y, z, w = self.quat
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ])


class Datum:
    """World ↔ geodetic coordinates by the GPS sensor's convention (``hilsim.sim.sensors_mobile``):
    the datum in UTM (the zone of its longitude), plus world X as northing and Y as easting."""

    def __init__(self, lat: float, lon: float, alt: float) -> None:
        from pyproj import Transformer

        from hilsim.sim.sensors_mobile import utm_zone

        epsg = utm_zone(lat, lon)
        self.lat, self.lon, self.alt = lat, lon, alt
        self._to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
        self._to_geo = Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
        self.easting0, self.northing0 = self._to_utm.transform(lon, lat)

    def to_geo(self, x: Any, y: Any) -> tuple[Any, Any]:
        """Latitude, longitude [deg] of world points (scalars or arrays)."""
        lon, lat = self._to_geo.transform(np.add(self.easting0, y), np.add(self.northing0, x))
        return lat, lon

    def to_world(self, lat: Any, lon: Any) -> tuple[Any, Any]:
        """World x (north), y (east) [m] of geodetic points (scalars or arrays)."""
        e, n = self._to_utm.transform(lon, lat)
        return np.subtract(n, self.northing0), np.subtract(e, self.easting0)


@dataclasses.dataclass
class Scene:
    """What the recorder draws of a world model besides the robot (see the module doc)."""

    geoms: list[StaticGeom]
    skipped: list[str]  # geoms not drawn (height fields), by name
    datum: Datum | None = None
    # A fixed-base robot: where its root link is in the world (position, quaternion x y z w).
    root_pose: tuple[np.ndarray, np.ndarray] | None = None
    # A mobile base: its body name and the box around its largest geom (centre, half sizes) in its frame.
    base: str | None = None
    base_box: tuple[np.ndarray, np.ndarray] | None = None
    # …and where it starts (x, y, z, yaw in the world: the model's reference pose), where its
    # odometry's frame is
    base_start: tuple[float, float, float, float] | None = None

    @classmethod
    def load(cls, model_path: str | Path, robot_links: Iterable[str] = (), root_link: str | None = None,
             datum: tuple[float, float, float] | None = None) -> Scene:
        """Read ``model_path`` (MJCF). ``robot_links``: names of the robot's links (its bodies are
        not static geometry); ``root_link``: the URDF's root, whose world pose is recorded for a
        fixed base; ``datum`` (lat, lon, alt) overrides the model's custom numeric ``geodetic_datum``."""
        import mujoco

        m = mujoco.MjModel.from_xml_path(str(model_path))
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        links = set(robot_links)
        robot = np.zeros(m.nbody, bool)
        for b in range(1, m.nbody):  # parents come before their children
            robot[b] = m.body(b).name in links or robot[m.body_parentid[b]]
        geoms: list[StaticGeom] = []
        skipped: list[str] = []
        for g in range(m.ngeom):
            b = m.geom_bodyid[g]
            if m.body_weldid[b] != 0 or robot[b]:
                continue
            name = m.geom(g).name or f"geom_{g}"
            kind = GEOM_KINDS.get(int(m.geom_type[g]))
            if kind is None:
                skipped.append(name)
                continue
            rot = d.geom_xmat[g].reshape(3, 3)
            q = np.zeros(4)
            mujoco.mju_mat2Quat(q, d.geom_xmat[g])
            verts = faces = None
            if kind == "mesh":
                mid = m.geom_dataid[g]
                va, vn = m.mesh_vertadr[mid], m.mesh_vertnum[mid]
                fa, fn = m.mesh_faceadr[mid], m.mesh_facenum[mid]
                verts = m.mesh_vert[va:va + vn] @ rot.T + d.geom_xpos[g]
                faces = m.mesh_face[fa:fa + fn].copy()
            geoms.append(StaticGeom(name, kind, d.geom_xpos[g].copy(), np.array([q[1], q[2], q[3], q[0]]),
                                    m.geom_size[g].copy(), _colour(m, g), verts, faces))
        geoms = _bound_planes(geoms)
        if datum is None:
            try:
                datum = tuple(float(v) for v in m.numeric("geodetic_datum").data)  # type: ignore[assignment]
            except KeyError:
                datum = None
        scene = cls(geoms, skipped, Datum(*datum) if datum is not None and len(datum) == 3 else None)
        free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
                and m.body_parentid[m.jnt_bodyid[j]] == 0]
        if free:
            b = int(m.jnt_bodyid[free[0]])
            scene.base = m.body(b).name
            scene.base_box = _body_box(m, b)
            x, y, z, qw, qx, qy, qz = (float(v) for v in m.qpos0[m.jnt_qposadr[free[0]]:][:7])
            scene.base_start = (x, y, z, heading(qw, qx, qy, qz))
        elif root_link is not None:
            try:
                b = m.body(root_link).id
            except KeyError:
                b = None
            if b is not None:
                q = d.xquat[b]
                scene.root_pose = (d.xpos[b].copy(), np.array([q[1], q[2], q[3], q[0]]))
        return scene

    @classmethod
    def for_scenario(cls, sc: Any, links: Iterable[str] = (), root_link: str | None = None) -> Scene:
        """The scene of a scenario's ``world.model``; the datum of an enabled ``gps`` sensor's
        ``datum`` setting wins over the model's, as for the sensor itself."""
        datum = None
        for s in sc.sensors.values():
            if s.type == "gps" and s.enabled and (s.model_extra or {}).get("datum") is not None:
                datum = tuple(float(v) for v in s.model_extra["datum"])
        return cls.load(sc.world.model, links, root_link, datum)  # type: ignore[arg-type]

    def log_static(self, rec: Any, frame: str = "world") -> None:
        """Log every geom once (static) as ``world/<name>`` in ``frame``."""
        from hilsim.core.recording import import_rerun

        rr = import_rerun()
        part = rr.escape_entity_path_part

        for g in self.geoms:
            colour = [round(c * 255) for c in g.rgba]
            if g.kind == "box":
                arch: Any = rr.Boxes3D(half_sizes=[g.size], centers=[g.pos], quaternions=[g.quat], colors=[colour],
                                       fill_mode="solid")
            elif g.kind == "cylinder":
                arch = rr.Cylinders3D(lengths=[2 * g.size[1]], radii=[g.size[0]], centers=[g.pos],
                                      quaternions=[g.quat], colors=[colour], fill_mode="solid")
            elif g.kind == "capsule":  # Rerun's capsule starts at its translation and runs along +z
                start = g.pos - g.rotation[:, 2] * g.size[1]
                arch = rr.Capsules3D(lengths=[2 * g.size[1]], radii=[g.size[0]], translations=[start],
                                     quaternions=[g.quat], colors=[colour])
            elif g.kind in ("sphere", "ellipsoid"):
                half = [g.size[0]] * 3 if g.kind == "sphere" else g.size
                arch = rr.Ellipsoids3D(half_sizes=[half], centers=[g.pos], quaternions=[g.quat], colors=[colour],
                                       fill_mode="solid")
            elif g.kind == "plane":
                sx, sy = g.size[0], g.size[1]
                corners = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0]]) @ g.rotation.T + g.pos
                arch = rr.Mesh3D(vertex_positions=corners, triangle_indices=[[0, 1, 2], [0, 2, 3]],
                                 vertex_normals=[g.rotation[:, 2]] * 4, albedo_factor=colour)
            else:  # mesh
                arch = rr.Mesh3D(vertex_positions=g.vertices, triangle_indices=g.faces, albedo_factor=colour)
            rec.log(f"world/{part(g.name)}", arch, rr.CoordinateFrame(frame), static=True)


def _colour(m: Any, g: int) -> tuple[float, float, float, float]:
    """A geom's colour as MuJoCo shows it: its rgba, else its material's (times the mean of the
    material's colour texture, e.g. a checker floor's two colours)."""
    rgba = tuple(float(c) for c in m.geom_rgba[g])
    mat = m.geom_matid[g]
    if mat < 0 or not np.allclose(rgba, DEFAULT_RGBA):
        return rgba  # type: ignore[return-value]
    c = m.mat_rgba[mat].astype(float)
    tex = m.mat_texid[mat]
    tex = tex[TEXROLE_RGB] if np.ndim(tex) else tex
    if tex >= 0:
        n, adr = m.tex_nchannel[tex], m.tex_adr[tex]
        data = m.tex_data[adr:adr + m.tex_width[tex] * m.tex_height[tex] * n].reshape(-1, n)
        c[:3] *= data[:, :3].mean(axis=0) / 255.0
    return (float(c[0]), float(c[1]), float(c[2]), float(c[3]))


def _bound_planes(geoms: list[StaticGeom]) -> list[StaticGeom]:
    """Planes cut down to the other geoms' reach plus PLANE_MARGIN (an infinite one: 0 in MuJoCo)."""
    others = [g for g in geoms if g.kind != "plane"]
    out = []
    for g in geoms:
        if g.kind != "plane":
            out.append(g)
            continue
        reach = np.zeros(2)
        for o in others:  # the other geoms' boxes, in the plane's frame
            local = g.rotation.T @ (o.pos - g.pos)
            half = np.abs(g.rotation.T) @ o.half_extent
            reach = np.maximum(reach, np.abs(local[:2]) + half[:2])
        margin = min(PLANE_MARGIN, max(0.5, PLANE_MARGIN_FRACTION * float(reach.max())))
        reach = reach + margin if others else np.full(2, PLANE_DEFAULT)
        size = g.size.copy()
        for i in range(2):
            size[i] = reach[i] if size[i] <= 0 else min(size[i], reach[i])
        out.append(dataclasses.replace(g, size=size))
    return out


def _body_box(m: Any, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half sizes, in the body's frame, of the box around the body's largest geom
    (a chassis: not its masts and sensor heads)."""
    import mujoco

    geoms = range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b])
    if not geoms:
        return np.zeros(3), np.full(3, 0.1)
    g = max(geoms, key=lambda i: float(np.prod(m.geom_aabb[i, 3:])))
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.geom_quat[g])
    centre, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half + centre
    pts = corners @ rot.reshape(3, 3).T + m.geom_pos[g]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return (lo + hi) / 2, (hi - lo) / 2
