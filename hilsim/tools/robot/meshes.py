"""The meshes of an imported robot, made readable by MuJoCo and Rerun, in ``DIR/meshes/``.

STL and OBJ are copied as they are (MuJoCo and Rerun read both). Any other format (Collada ``.dae``
above all, also ``.ply``, ``.glb``, ``.off``) is converted to binary STL with trimesh (Collada through
pycollada), its scene flattened with every node's transform and the file's unit applied. A visual mesh
that cannot be read falls back to the link's collision geometry (one line says so); a collision mesh
that cannot be read, or any mesh that cannot be found, stops the import with one line naming the file,
the element and why.
"""

from __future__ import annotations

import hashlib
import logging
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hilsim.tools.robot.urdf import ImportFailure, resolve_uri

COPIED = (".stl", ".obj")
MESH_DIR = "meshes"


@dataclass(frozen=True)
class Mesh:
    name: str  # unique within the robot, a valid MuJoCo asset name
    file: Path  # in DIR/meshes
    source: Path


class Meshes:
    """The robot's meshes, each resolved, converted once and named once."""

    def __init__(self, urdf_path: Path, out: Path, roots: list[Path], say: Callable[[str], None]) -> None:
        self.urdf_path, self.out, self.roots, self.say = urdf_path, out, roots, say
        self.by_source: dict[Path, Mesh] = {}
        self.names: set[str] = set()

    def get(self, uri: str, where: str, visual: bool) -> Mesh | None:
        """The usable mesh for ``uri`` (None: a visual mesh that cannot be read; the caller draws the
        collision geometry instead)."""
        src = resolve_uri(uri, self.urdf_path.parent, self.roots)
        if src is None:
            hint = " (give its package's parent folder with --package-path)" if uri.startswith("package://") else ""
            raise ImportFailure(f"{where} <mesh filename={uri!r}>: file not found{hint}")
        src = src.resolve()
        if src in self.by_source:
            return self.by_source[src]
        name = self._name(src)
        (self.out / MESH_DIR).mkdir(parents=True, exist_ok=True)
        if src.suffix.lower() in COPIED:
            dest = self.out / MESH_DIR / f"{name}{src.suffix.lower()}"
            shutil.copyfile(src, dest)
        else:
            dest = self.out / MESH_DIR / f"{name}.stl"
            why = _convert(src, dest)
            if why is not None:
                if visual:
                    self.say(f"  {where}: {src.name} cannot be converted ({why}): drawn with the collision geometry")
                    return None
                raise ImportFailure(f"{where} <mesh filename={uri!r}>: cannot be read or converted: {why}")
        mesh = Mesh(name, dest, src)
        self.by_source[src] = mesh
        return mesh

    def _name(self, src: Path) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", src.stem) or "mesh"
        # the folder tells visual/link1 from collision/link1
        folder = re.sub(r"[^A-Za-z0-9_]", "_", src.parent.name)
        name = f"{folder}_{base}" if folder else base
        if name in self.names:
            name = f"{name}_{hashlib.sha1(str(src).encode()).hexdigest()[:6]}"
        self.names.add(name)
        return name


def _convert(src: Path, dest: Path) -> str | None:
    """Convert ``src`` to binary STL at ``dest``; None on success, else why not (one line)."""
    logging.getLogger("trimesh").setLevel(logging.ERROR)  # its warnings are said here, once, if fatal
    try:
        import trimesh
    except ImportError:  # pragma: no cover - a dependency of hilsim
        return "trimesh is not installed"
    try:
        loaded = trimesh.load(str(src), force="mesh")
    except Exception as e:
        return " ".join(f"{type(e).__name__}: {e}".split())[:200]
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        return "no triangles in it"
    loaded.export(str(dest), file_type="stl")
    return None
