"""An occupancy grid of a MuJoCo world's static geometry, and its inflation by the robot's footprint.

Which cells are occupied: every geom fixed to the world body (not the robot's, nor any other
moving body's), except planes and height fields (the ground), that has any part inside the height
band ``z_band`` above the ground — by default 0.1–0.7 m: above the floor, up to the top of the
rover's GPS mast, so the laser's plane (z ≈ 0.42 m) lies inside it and anything the chassis would
hit is in. The band is sampled every ``z_step`` metres and each cell at its centre: a point test
against the geom's shape in its own frame (box, sphere, capsule, cylinder, ellipsoid; a mesh or
any other shape by its bounding box). A centre test can miss a sliver of an obstacle narrower
than half a cell, so :meth:`Grid.inflate` adds half a cell diagonal to the radius it is given.

A 2D grid cannot tell a ramp from a wall: the outdoor world's slope and plateau are obstacles here.

Conventions are nav_msgs/OccupancyGrid's: ``occ[row, col]`` with rows along +y and columns along
+x from ``origin`` (the world position of cell (0, 0)'s corner), 0 free, 100 occupied.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core import msgs

FREE, OCCUPIED = 0, 100


@dataclass
class Grid:
    origin: tuple[float, float]  # world x, y of the corner of cell (0, 0)
    resolution: float  # metres per cell
    occ: np.ndarray  # bool, shape (height, width): the obstacles themselves
    inflated: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))  # occ grown by the footprint
    radius: float = 0.0  # the inflation radius [m] (as asked, before the half-cell margin)

    @property
    def height(self) -> int:
        return int(self.occ.shape[0])

    @property
    def width(self) -> int:
        return int(self.occ.shape[1])

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """x_min, x_max, y_min, y_max of the grid's area."""
        x0, y0 = self.origin
        return x0, x0 + self.width * self.resolution, y0, y0 + self.height * self.resolution

    def cell(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of world points (may lie outside the grid)."""
        c = np.floor((np.asarray(x, float) - self.origin[0]) / self.resolution).astype(np.int64)
        r = np.floor((np.asarray(y, float) - self.origin[1]) / self.resolution).astype(np.int64)
        return r, c

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x of each column's centre and y of each row's centre."""
        xs = self.origin[0] + (np.arange(self.width) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(self.height) + 0.5) * self.resolution
        return xs, ys

    def free(self, x: np.ndarray | float, y: np.ndarray | float, *, inflated: bool = True) -> np.ndarray:
        """True where a point lies in a free cell of the grid (outside the grid: not free)."""
        g = self.inflated if inflated else self.occ
        r, c = self.cell(x, y)
        inside = (r >= 0) & (r < self.height) & (c >= 0) & (c < self.width)
        out = np.zeros(np.shape(r), bool)
        out[inside] = ~g[r[inside], c[inside]]
        return out

    def inflate(self, radius: float) -> Grid:
        """Grow the obstacles by ``radius`` metres (plus half a cell diagonal, see the module
        doc): a disc of cells around every occupied one. Returns self."""
        self.radius = float(radius)
        reach = radius + self.resolution * math.sqrt(0.5)
        n = math.ceil(reach / self.resolution)
        out = self.occ.copy()
        h, w = self.occ.shape
        for dr in range(-n, n + 1):
            for dc in range(-n, n + 1):
                # cells whose centres are within reach of an occupied cell's centre
                if (dr * dr + dc * dc) * self.resolution**2 > reach * reach or (dr == 0 and dc == 0):
                    continue
                src = self.occ[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
                out[max(0, dr):h - max(0, -dr), max(0, dc):w - max(0, -dc)] |= src
        self.inflated = out
        return self

    def to_msg(self, stamp_ns: int, *, inflated: bool = False) -> msgs.OccupancyGrid:
        g = self.inflated if inflated else self.occ
        data = np.where(g, OCCUPIED, FREE).astype(np.int8)
        return msgs.OccupancyGrid(
            header=msgs.header(stamp_ns, "world"),
            info=msgs.MapMetaData(
                map_load_time=msgs.stamp(stamp_ns), resolution=self.resolution, width=self.width,
                height=self.height,
                origin=msgs.Pose(position=msgs.Point(x=self.origin[0], y=self.origin[1])),
            ),
            data=data.ravel().tolist(),
        )


# ------------------------------------------------------------------ rasterising a MuJoCo world
def _inside(gtype: int, size: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points ``p`` (N×3, in the geom's frame) inside a geom of MuJoCo type ``gtype``."""
    import mujoco

    T = mujoco.mjtGeom
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if gtype == T.mjGEOM_SPHERE:
        return x * x + y * y + z * z <= size[0] ** 2
    if gtype == T.mjGEOM_CAPSULE:
        zc = np.clip(z, -size[1], size[1])
        return x * x + y * y + (z - zc) ** 2 <= size[0] ** 2
    if gtype == T.mjGEOM_CYLINDER:
        return (x * x + y * y <= size[0] ** 2) & (np.abs(z) <= size[1])
    if gtype == T.mjGEOM_ELLIPSOID:
        return (x / size[0]) ** 2 + (y / size[1]) ** 2 + (z / size[2]) ** 2 <= 1.0
    # box, and by its bounding box anything else (mesh, sdf)
    return (np.abs(x) <= size[0]) & (np.abs(y) <= size[1]) & (np.abs(z) <= size[2])


_SHAPES = (2, 3, 4, 5, 6)  # mjtGeom: sphere, capsule, ellipsoid, cylinder, box


def static_geoms(model: Any) -> list[int]:
    """Geoms fixed to the world body that are not ground (plane, height field)."""
    import mujoco

    T = mujoco.mjtGeom
    out = []
    for g in range(model.ngeom):
        body = int(model.geom_bodyid[g])
        if int(model.body_rootid[body]) != 0 or model.body_mocapid[body] >= 0:
            continue  # the robot (a free-joint root) or anything else that moves
        if int(model.geom_type[g]) in (T.mjGEOM_PLANE, T.mjGEOM_HFIELD):
            continue
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only: nothing collides with it
        out.append(g)
    return out


def load_model(model: Any) -> Any:
    import mujoco

    if isinstance(model, str | Path):
        return mujoco.MjModel.from_xml_path(str(model))
    return model


def from_model(
    model: Any,
    *,
    resolution: float = 0.05,
    z_band: tuple[float, float] = (0.1, 0.7),
    z_step: float = 0.05,
    bounds: tuple[float, float, float, float] | None = None,
    margin: float = 1.0,
) -> Grid:
    """Rasterise a MuJoCo world (a model or an MJCF path) into a :class:`Grid` (not inflated).

    ``bounds`` (x_min, x_max, y_min, y_max): the area; by default the static geoms' extent plus
    ``margin`` on every side.
    """
    import mujoco

    m = load_model(model)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    geoms = static_geoms(m)
    # each geom's world-frame axis-aligned box: |R| @ half-extent of its local bounding box
    boxes = []
    for g in geoms:
        rot = d.geom_xmat[g].reshape(3, 3)
        centre = d.geom_xpos[g] + rot @ m.geom_aabb[g, :3]
        half = np.abs(rot) @ m.geom_aabb[g, 3:]
        boxes.append((centre - half, centre + half))
    if bounds is None:
        if not boxes:
            raise ValueError("the world has no static geometry to bound the grid: give bounds")
        lo = np.min([b[0] for b in boxes], axis=0) - margin
        hi = np.max([b[1] for b in boxes], axis=0) + margin
        bounds = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    x0, x1, y0, y1 = bounds
    if not (x1 > x0 and y1 > y0) or resolution <= 0:
        raise ValueError(f"empty grid: bounds {bounds}, resolution {resolution}")
    w, h = math.ceil((x1 - x0) / resolution), math.ceil((y1 - y0) / resolution)
    grid = Grid((x0, y0), float(resolution), np.zeros((h, w), bool))
    xs, ys = grid.centres()
    zs = np.arange(z_band[0], z_band[1] + 1e-9, z_step)
    if zs[-1] < z_band[1] - 1e-9:
        zs = np.append(zs, z_band[1])
    for g, (lo, hi) in zip(geoms, boxes, strict=True):
        if hi[2] < z_band[0] or lo[2] > z_band[1]:
            continue  # entirely below or above the band
        ci = np.nonzero((xs >= lo[0]) & (xs <= hi[0]))[0]
        ri = np.nonzero((ys >= lo[1]) & (ys <= hi[1]))[0]
        zi = zs[(zs >= lo[2]) & (zs <= hi[2])]
        if not len(ci) or not len(ri) or not len(zi):
            continue
        X, Y, Z = np.meshgrid(xs[ci], ys[ri], zi, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        rot = d.geom_xmat[g].reshape(3, 3)
        local = (pts - d.geom_xpos[g]) @ rot  # rows: rot.T @ (p - pos)
        gtype, size = int(m.geom_type[g]), m.geom_size[g]
        if gtype not in _SHAPES:  # a mesh (or anything else): its bounding box, as a box
            gtype, size, local = mujoco.mjtGeom.mjGEOM_BOX, m.geom_aabb[g, 3:], local - m.geom_aabb[g, :3]
        hit = _inside(gtype, size, local).reshape(len(ci), len(ri), len(zi)).any(axis=2)
        grid.occ[np.ix_(ri, ci)] |= hit.T
    return grid
