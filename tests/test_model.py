"""The arm model: the committed files are what generate.py derives, and its own checks pass."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

ARM = Path(__file__).resolve().parent.parent / "models" / "arm"


def test_committed_model_matches_its_generator(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location("arm_generate", ARM / "generate.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = gen  # its dataclasses look their module up
    try:
        spec.loader.exec_module(gen)
    finally:
        del sys.modules[spec.name]
    gen.write_urdf(str(tmp_path / "arm.urdf"))
    gen.write_mjcf(str(tmp_path / "arm.xml"))
    for name in ("arm.urdf", "arm.xml"):
        generated = (tmp_path / name).read_text()
        assert generated == (ARM / name).read_text(), f"{name} was edited by hand or not regenerated"


def test_model_checks_pass() -> None:
    """Joint limits and geometry from the Niryo One facts, URDF == MJCF kinematics, inertias,
    collision-free targets with the straight line between two of them blocked by the obstacle."""
    r = subprocess.run([sys.executable, str(ARM / "verify.py")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "ALL PASS" in r.stdout, r.stdout[-3000:] + r.stderr[-2000:]
