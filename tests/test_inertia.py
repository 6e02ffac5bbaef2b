"""``hilsim inertia``: closed forms, parallel-axis theorem and rotation, against MuJoCo's own inertia."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from hilsim.core.config import ConfigError
from hilsim.tools.tuning import inertia as ti

REPO = Path(__file__).resolve().parent.parent


def parts(*items: dict) -> list:
    return ti.InertiaFile.model_validate({"links": {"l": list(items)}}).links["l"]


def test_closed_forms() -> None:
    m, r, h = 2.0, 0.05, 0.3
    i = ti.combine(parts({"shape": "cylinder", "mass": m, "radius": r, "length": h})).tensor
    assert np.allclose(np.diag(i), [m * (3 * r * r + h * h) / 12] * 2 + [m * r * r / 2])
    i = ti.combine(parts({"shape": "box", "mass": m, "size": [0.1, 0.2, 0.3]})).tensor
    assert np.allclose(np.diag(i), [m * (0.04 + 0.09) / 12, m * (0.01 + 0.09) / 12, m * (0.01 + 0.04) / 12])
    i = ti.combine(parts({"shape": "hollow_cylinder", "mass": m, "inner_radius": 0.03, "radius": r,
                          "length": h})).tensor
    assert i[2, 2] == pytest.approx(m * (0.03**2 + r * r) / 2)
    i = ti.combine(parts({"shape": "sphere", "mass": m, "radius": r})).tensor
    assert np.allclose(i, np.eye(3) * 0.4 * m * r * r)
    # thin square column: four plates of side a at a/2 from the axis
    a = 0.12
    i = ti.combine(parts({"shape": "thin_square_column", "mass": m, "side": a, "height": h})).tensor
    assert i[2, 2] == pytest.approx(m * a * a / 3) and i[0, 0] == pytest.approx(m * (2 * a * a + h * h) / 12)


def test_parallel_axis_and_rotation() -> None:
    # two point masses 1 kg at ±0.1 m on x: COM at 0, Iyy = Izz = 2·1·0.01, Ixx = 0
    ia = ti.combine(parts({"shape": "point", "mass": 1, "pos": [0.1, 0, 0]}, {"shape": "point", "mass": 1,
                                                                                "pos": [-0.1, 0, 0]}))
    assert np.allclose(ia.com, 0) and np.allclose(np.diag(ia.tensor), [0, 0.02, 0.02])
    # an offset point: I about the COM of (box + point) = I_box + m d² terms (the paper's eq. 3)
    box = {"shape": "box", "mass": 3.0, "size": [0.1, 0.1, 0.1]}
    two = ti.combine(parts(box, {"shape": "point", "mass": 1.0, "pos": [0.2, 0, 0]}))
    assert two.com[0] == pytest.approx(0.05)
    assert two.tensor[1, 1] == pytest.approx(3.0 * 0.02 / 12 + 3.0 * 0.05**2 + 1.0 * 0.15**2)
    # a box turned 90° about z swaps its x and y moments; turned 45°, a product of inertia appears
    turned = ti.combine(parts({**box, "size": [0.1, 0.3, 0.2], "rpy": [0, 0, math.pi / 2]})).tensor
    flat = ti.combine(parts({**box, "size": [0.3, 0.1, 0.2]})).tensor
    assert np.allclose(turned, flat)
    skew = ti.combine(parts({**box, "size": [0.1, 0.3, 0.2], "rpy": [0, 0, math.pi / 4]})).tensor
    assert abs(skew[0, 1]) > 1e-3 and np.allclose(np.linalg.eigvalsh(skew), np.sort(np.diag(flat)))


MIXED = [
    {"shape": "box", "mass": 0.4, "size": [0.04, 0.06, 0.1], "pos": [0.02, -0.01, 0.05], "rpy": [0.3, -0.2, 0.9]},
    {"shape": "cylinder", "mass": 0.7, "radius": 0.03, "length": 0.15, "pos": [0.0, 0.05, 0.1],
     "rpy": [math.pi / 2, 0.1, 0]},
    {"shape": "hollow_cylinder", "mass": 0.3, "inner_radius": 0.02, "radius": 0.035, "length": 0.05,
     "pos": [-0.03, 0, 0.02], "rpy": [0, 0.4, 0]},
    {"shape": "thin_square_column", "mass": 0.5, "side": 0.13, "height": 0.09, "wall": 0.004,
     "pos": [0, 0, 0.045], "rpy": [0, 0, 0.3]},
    {"shape": "sphere", "mass": 0.2, "radius": 0.02, "pos": [0.1, 0.1, 0.0]},
    {"shape": "point", "mass": 0.05, "pos": [-0.1, 0.02, 0.2]},
]


def test_against_mujoco() -> None:
    """Every shape, offset and turned, against MuJoCo compiling the same geoms (inertiafromgeom)."""
    p = parts(*MIXED)
    ours, theirs = ti.combine(p), ti.mujoco_inertial(p)
    assert ours.mass == pytest.approx(theirs.mass, rel=1e-12)
    assert np.allclose(ours.com, theirs.com, atol=1e-9)
    # the hollow cylinder is a 1024-sided polygon in MuJoCo: ~1e-5 of its share
    assert np.abs(ours.tensor - theirs.tensor).max() < 1e-5 * np.abs(ours.tensor).max()
    for one in MIXED:  # and each alone, so no error hides behind a bigger part
        a, b = ti.combine(parts(one)), ti.mujoco_inertial(parts(one))
        assert a.mass == pytest.approx(b.mass) and np.allclose(a.com, b.com, atol=1e-9)
        if one["shape"] == "point":  # MuJoCo's stand-in: a sphere of 10 µm
            assert np.abs(b.tensor).max() < 1e-11
            continue
        tol = 2e-5 if one["shape"] == "hollow_cylinder" else 1e-9
        assert np.abs(a.tensor - b.tensor).max() <= tol * np.abs(a.tensor).max(), one["shape"]


def test_arm_generator_link() -> None:
    """The arm's elbow_link (a cylinder and a box) as models/arm/generate.py computed it for arm.xml."""
    elbow = ti.combine(parts(
        {"shape": "cylinder", "mass": 0.25, "radius": 0.033, "length": 0.07},
        {"shape": "box", "mass": 0.1, "size": [0.04, 0.048, 0.056], "pos": [0.037, 0.004, 0]},
    ))
    m = mujoco.MjModel.from_xml_path(str(REPO / "models/arm/arm.xml"))
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "elbow_link")
    assert elbow.mass == pytest.approx(m.body_mass[b])
    assert np.allclose(elbow.com, m.body_ipos[b], atol=1e-8)
    assert np.allclose(np.linalg.eigvalsh(elbow.tensor), np.sort(m.body_inertia[b]), rtol=1e-6)


def test_cli_writes_urdf_inertial(tmp_path: Path) -> None:
    urdf = tmp_path / "arm.urdf"
    shutil.copy(REPO / "models/arm/arm.urdf", urdf)
    before = urdf.read_text()
    example = str(REPO / "hilsim/tools/examples/niryo_base.yaml")
    p = subprocess.run([sys.executable, "-m", "hilsim.cli", "inertia", example, "--urdf", str(urdf), "--json"],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)["base_link"]
    assert got["mujoco_relative_difference"] < 1e-3  # thin walls: MuJoCo's walls are 1e-4 of the side
    after = urdf.read_text()
    assert after != before and after.count("<inertial>") == before.count("<inertial>")
    # the URDF still loads, and MuJoCo reads our mass and centre of mass for base_link
    m = mujoco.MjModel.from_xml_path(str(urdf))
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "base_link")
    assert m.body_mass[b] == pytest.approx(got["mass"])
    assert np.allclose(m.body_ipos[b], got["com"], atol=1e-8)
    # everything outside base_link's <inertial> is unchanged
    cut = lambda s: s[:s.index("<inertial>")] + s[s.index("</inertial>"):]  # noqa: E731
    assert cut(after) == cut(before)


def test_bad_file_is_one_line(tmp_path: Path) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text("links:\n  l:\n    - {shape: hollow_cylinder, mass: 1, inner_radius: 0.05, radius: 0.04, length: 1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: links.l.0.hollow_cylinder: .*inner_radius"):
        ti.load(f)
    f.write_text("links:\n  l:\n    - {shape: cone, mass: 1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: links.l.0: .*tag 'cone'"):
        ti.load(f)
