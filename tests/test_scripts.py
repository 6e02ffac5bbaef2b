"""The setup scripts and the packaging: ``scripts/arm.sh`` and ``scripts/test.sh`` install hilsim
into ``.venv`` once and again only when ``pyproject.toml`` changes (no pip call otherwise: it
reaches for the index, half a minute of retries offline); every directory of the installed
packages is a package of ``pyproject.toml`` (else setuptools prints a 45-line warning at each
install, as it did for ``hilsim/ui/static``)."""

from __future__ import annotations

import shutil
import subprocess
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_the_venv_is_installed_once_and_again_when_pyproject_changes(tmp_path: Path) -> None:
    (tmp_path / "scripts").mkdir()
    shutil.copy(REPO / "scripts" / "venv.sh", tmp_path / "scripts" / "venv.sh")
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    py = tmp_path / ".venv" / "bin" / "python"
    py.parent.mkdir(parents=True)
    calls = tmp_path / "pip-calls"
    py.write_text(f'#!/bin/sh\necho "$*" >> {calls}\n')  # a stand-in: records each pip call
    py.chmod(0o755)

    def ensure(spec: str) -> list[str]:
        r = subprocess.run(["bash", "-c", f"set -euo pipefail; source scripts/venv.sh; ensure_venv '{spec}'"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=30)
        assert r.returncode == 0, r.stderr
        return calls.read_text().splitlines() if calls.exists() else []

    assert ensure(".") == ["-m pip install -q -e ."]
    assert len(ensure(".")) == 1  # the same pyproject.toml: no pip at all
    assert ensure(".[test]")[-1] == "-m pip install -q -e .[test]"  # more asked for
    assert len(ensure(".")) == 2 and len(ensure(".[test]")) == 2  # the test extras cover `.`
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\ndependencies = ['y']\n")
    assert len(ensure(".")) == 3 and len(ensure(".")) == 3
    for script in ("arm.sh", "test.sh"):
        text = (REPO / "scripts" / script).read_text()
        assert "ensure_venv" in text and "pip install -q -e" not in text, script  # hilsim: only through it


def test_every_directory_of_the_packages_is_a_listed_package() -> None:
    conf = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages, dirs = set(conf["packages"]), conf.get("package-dir", {})
    roots = {"hilsim": REPO / "hilsim", **{p: REPO / d for p, d in dirs.items()}}
    missing = []
    for pkg, root in roots.items():
        for d in [root, *(p for p in root.rglob("*") if p.is_dir())]:
            if d.name == "__pycache__" or not any(f.is_file() for f in d.iterdir()):
                continue
            name = ".".join([pkg, *d.relative_to(root).parts])
            if name not in packages:
                missing.append(name)
    assert not missing, f"add to [tool.setuptools] packages in pyproject.toml: {missing}"
    assert conf["package-data"]["hilsim.ui.static"], conf["package-data"]
