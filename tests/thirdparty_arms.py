"""Test worlds from real third-party URDFs (the ``example-robot-data`` package), built with MuJoCo's
spec API as a lab would by hand until ``hilsim robot import`` does it: collision STL meshes, a motor per
joint, a ``tool`` site at the last link, a table under the base, adjacent links excluded, a ``home`` key.

Only for the planning tests (robots not written here). The package is found under ``ERD_ROOT`` or the
unzipped wheel in /tmp/erd; tests skip when it is not there.
"""

from __future__ import annotations

import itertools
import os
import re
import sysconfig
from pathlib import Path

import numpy as np

# the package as the test extras install it (pyproject.toml), or unpacked elsewhere (ERD_ROOT)
ERD_CANDIDATES = [os.environ.get("ERD_ROOT", ""),
                  str(Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix/share/example-robot-data/robots")]


def erd_root() -> Path | None:
    for c in ERD_CANDIDATES:
        if c and Path(c, "ur_description").is_dir():
            return Path(c)
    return None


def ur5_world(out_dir: Path, continuous: tuple[str, ...] = ("wrist_3_joint",), name_geoms: bool = True) -> Path:
    """The UR5 of example-robot-data on a table, as an MJCF in ``out_dir`` (meshes referenced where they
    are). ``continuous`` joints lose their limits (as URDF ``continuous`` joints): the rest keep ±2π."""
    import mujoco

    root = erd_root()
    assert root is not None
    desc = root / "ur_description"
    text = (desc / "urdf" / "ur5_robot.urdf").read_text()
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)  # DAE visuals: MuJoCo cannot read them
    text = re.sub(r'filename="package://[^"]*/collision/([^"/]+)"', r'filename="\1"', text)
    meshdir = desc / "meshes" / "ur5" / "collision"
    text = text.replace(
        "</robot>",
        f'<mujoco><compiler meshdir="{meshdir}" balanceinertia="true" discardvisual="true" '
        'fusestatic="false"/></mujoco></robot>',
    )
    spec = mujoco.MjSpec.from_string(text)
    spec.modelname = "ur5"
    joints = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint"]
    for j in spec.joints:
        if j.name in continuous:
            j.limited = mujoco.mjtLimited.mjLIMITED_FALSE
    for b in spec.bodies if name_geoms else ():  # geoms named after their links (the URDF reader leaves them unnamed)
        for k, g in enumerate(b.geoms):
            g.name = b.name if k == 0 else f"{b.name}_{k}"
    for j in joints:
        spec.add_actuator(name=j, target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT, ctrlrange=[-150, 150],
                          ctrllimited=True)
    wrist3 = spec.body("wrist_3_link")
    wrist3.add_site(name="tool", pos=[0, 0.0823, 0])
    # base_link is welded to the world: MuJoCo does not filter it against the shoulder (3 mm apart)
    spec.add_exclude(bodyname1="base_link", bodyname2="shoulder_link")
    names = [b.name for b in spec.bodies]
    for a, b in itertools.pairwise(names[1:]):
        spec.add_exclude(bodyname1=a, bodyname2=b)
    # the wrist's links: their meshes' convex hulls (what MuJoCo collides) touch at most poses (as MoveIt's
    # Setup Assistant finds pairs "often in collision" and disables them)
    wrist = ["forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]
    for i, a in enumerate(wrist):
        for b in wrist[i + 2:]:
            spec.add_exclude(bodyname1=a, bodyname2=b)
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.8, 0.8, 0.02],
                            pos=[0.2, 0, -0.021])
    spec.add_numeric(name="arm_joint_velocity_limit", data=[3.15, 3.15, 3.15, 3.2, 3.2, 3.2])
    home = np.array([0.0, -1.2, 1.2, -1.57, -1.57, 0.0])
    model = spec.compile()
    qpos = model.qpos0.copy()
    for j, v in zip(joints, home, strict=True):
        qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]] = v
    spec.add_key(name="home", qpos=qpos.tolist())
    spec.compile()
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "ur5.xml"
    path.write_text(spec.to_xml())
    return path
