"""The robot model as the recorder draws it: the scenario's URDF loaded by Rerun's ``UrdfTree``.

- :class:`RobotModel`: the tree (logged once, static, under ``robot/``), its moving joints
  (their transforms follow ``truth/joint_states``) and :class:`ToolKinematics`;
- :class:`ToolKinematics`: forward kinematics from the URDF root to the tool link, vectorised
  over many joint configurations (the tool path of a planned trajectory).

Importing this module imports rerun, after turning its analytics off.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core.geometry import rpy_to_matrix
from hilsim.core.recording import disable_analytics

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402
from rerun.urdf import UrdfTree  # noqa: E402

ENTITY_PREFIX = "robot"  # where the URDF's links go in the recording


def axis_angle(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) about a unit axis by angles q (N,)."""
    x, y, z = axis
    c, s = np.cos(q), np.sin(q)
    t = 1 - c
    return np.stack(
        [
            np.stack([t * x * x + c, t * x * y - s * z, t * x * z + s * y], -1),
            np.stack([t * x * y + s * z, t * y * y + c, t * y * z - s * x], -1),
            np.stack([t * x * z - s * y, t * y * z + s * x, t * z * z + c], -1),
        ],
        -2,
    )


class ToolKinematics:
    """Forward kinematics from the URDF root to the tool link (``tool_link``, else the deepest link)."""

    def __init__(self, tree: UrdfTree) -> None:
        joints = {j.child_link: j for j in tree.joints()}
        self.root = tree.root_link().name

        def depth(link: str) -> int:
            n = 0
            while link in joints:
                link, n = joints[link].parent_link, n + 1
            return n

        tool = "tool_link" if "tool_link" in joints else max(joints, key=depth, default=self.root)
        chain = []
        link = tool
        while link in joints:
            chain.append(joints[link])
            link = joints[link].parent_link
        self.tool = tool
        self.chain = list(reversed(chain))

    def positions(self, joint_names: list[str], q: np.ndarray) -> np.ndarray:
        """Tool positions (N, 3) in the root frame for joint values q (N, len(joint_names))."""
        n = q.shape[0]
        col = {name: i for i, name in enumerate(joint_names)}
        rot = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        pos = np.zeros((n, 3))
        for j in self.chain:
            o_rot = rpy_to_matrix(*j.origin_rpy)
            pos = pos + rot @ np.asarray(j.origin_xyz)
            rot = rot @ o_rot
            if j.joint_type == "fixed" or j.name not in col:
                continue
            axis = np.asarray(j.axis, dtype=float)
            axis = axis / (np.linalg.norm(axis) or 1.0)
            v = q[:, col[j.name]]
            if j.joint_type == "prismatic":
                pos = pos + (rot @ axis) * v[:, None]
            else:
                rot = rot @ axis_angle(axis, v)
        return pos


class RobotModel:
    """A URDF loaded for recording: the tree, its moving joints by name, the tool's kinematics."""

    def __init__(self, tree: UrdfTree) -> None:
        self.tree = tree
        self.kin = ToolKinematics(tree)
        # joints whose transforms are recorded; emptied if the model itself could not be logged
        self.joints: dict[str, Any] = {j.name: j for j in tree.joints() if j.joint_type != "fixed"}

    @classmethod
    def load(cls, urdf: str | Path) -> RobotModel:
        """Load ``urdf`` (raises whatever rerun's loader raises for a file it cannot read)."""
        return cls(UrdfTree.from_file_path(urdf, entity_path_prefix=ENTITY_PREFIX))

    @property
    def links(self) -> list[str]:
        """Every link's name (the root first)."""
        return [self.tree.root_link().name, *(j.child_link for j in self.tree.joints())]

    @property
    def root(self) -> str:
        """The URDF's root link: the frame tool paths are drawn in."""
        return self.kin.root

    def log_static(self, rec: rr.RecordingStream) -> None:
        """Log the links' geometry and fixed transforms (``robot/…``, ``tf_static``) once."""
        self.tree.log_urdf_to_recording(rec)

    def transform_columns(self, joint: str, values: list[float]) -> Any:
        """Transform3D columns of one moving joint at the given joint values."""
        return self.joints[joint].compute_transform_columns(values, clamp=False)
