"""The URDF written beside the imported MJCF (``DIR/NAME.urdf``): the lab's own URDF, element for element,
with each mesh URI pointing at the file in ``DIR/meshes/`` that the import made readable (a converted
``.dae`` is an ``.stl`` there). It is what physics publishes on ``robot_description`` and ``tf``, and what
the recorder draws: so Rerun, rviz2 and Foxglove find every mesh without the lab's package path. A visual
whose mesh could not be converted is drawn with the link's collision geometry instead.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

from hilsim.tools.robot.meshes import MESH_DIR, Meshes


def write(urdf_path: Path, meshes: Meshes, out: Path) -> None:
    tree = ET.parse(urdf_path)
    root = tree.getroot()
    for link in root.findall("link"):
        where = f"{urdf_path}: <link name={link.get('name')!r}>"
        collisions = link.findall("collision")
        for tag in ("collision", "visual"):
            for k, el in enumerate(list(link.findall(tag))):
                mesh_el = el.find("geometry/mesh")
                if mesh_el is None:
                    continue
                mesh = meshes.get(mesh_el.get("filename", ""), f"{where} <{tag}> {k}", visual=tag == "visual")
                if mesh is not None:
                    mesh_el.set("filename", f"{MESH_DIR}/{mesh.file.name}")
                    continue
                # an unreadable visual: the collision geometry in its place
                link.remove(el)
                for c in collisions:
                    v = copy.deepcopy(c)
                    v.tag = "visual"
                    link.append(v)
    ET.indent(tree)
    tree.write(out, encoding="unicode", xml_declaration=True)
