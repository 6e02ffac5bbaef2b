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

    assert ensure(".") == ["-m pip install -e ."]
    assert len(ensure(".")) == 1  # the same pyproject.toml: no pip at all
    assert ensure(".[test]")[-1] == "-m pip install -e .[test]"  # more asked for
    assert len(ensure(".")) == 2 and len(ensure(".[test]")) == 2  # the test extras cover `.`
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\ndependencies = ['y']\n")
    assert len(ensure(".")) == 3 and len(ensure(".")) == 3
    for script in ("arm.sh", "test.sh"):
        text = (REPO / "scripts" / script).read_text()
        assert "ensure_venv" in text and "pip install -q -e" not in text, script  # hilsim: only through it


def _venv_with_pip(tmp_path: Path, pip: str) -> Path:
    """A copy of scripts/venv.sh beside a .venv whose python is a stand-in running ``pip`` (shell)."""
    (tmp_path / "scripts").mkdir(parents=True)
    shutil.copy(REPO / "scripts" / "venv.sh", tmp_path / "scripts" / "venv.sh")
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    py = tmp_path / ".venv" / "bin" / "python"
    py.parent.mkdir(parents=True)
    py.write_text("#!/bin/sh\n" + pip)
    py.chmod(0o755)
    return tmp_path


def test_the_first_install_says_how_long_and_shows_its_progress(tmp_path: Path) -> None:
    """The set-up's long step (a few minutes the first time) gives an estimate up front, then a line per
    package pip collects with the seconds so far, announces the silent install step and says when it is
    done; pip's noise stays in its log. A failing pip shows its error and leaves the venv to be retried."""
    d = _venv_with_pip(tmp_path / "ok", "echo \"WARNING: Location 'file:///x/' is ignored: it is neither a file nor a "
                       "directory.\"\nfor p in numpy scipy mujoco; do echo \"Collecting $p\"; echo '  Using cached "
                       "x.whl'; done\necho 'Installing collected packages: absl-py, glfw, numpy, scipy, mujoco'\n"
                       "sleep 1\n"
                       "echo 'Successfully installed absl-py glfw numpy scipy mujoco'\n")
    r = subprocess.run(["bash", "-c", "set -euo pipefail; source scripts/venv.sh; ensure_venv ."], cwd=d,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert "the first time about 4 minutes" in lines[0], lines
    assert [ln.split("] ", 1)[1] for ln in lines[1:4]] == ["  1: Collecting numpy", "  2: Collecting scipy",
                                                          "  3: Collecting mujoco"], lines
    # what pip installs (its list, dependencies too), not the requirements it collected: the message once said 75
    assert "installing 5 packages into .venv" in lines[4] and lines[5].endswith("] done"), lines
    assert lines[6].startswith("hilsim installed into .venv in "), lines
    assert "WARNING" not in r.stderr and "Using cached" not in r.stderr  # in .venv/pip-install.log
    assert (d / ".venv" / ".hilsim-installed").exists()

    bad = _venv_with_pip(tmp_path / "bad", "echo 'Collecting y'\necho 'ERROR: No matching distribution found for y'\n"
                         "exit 1\n")
    r = subprocess.run(["bash", "-c", "set -euo pipefail; source scripts/venv.sh; ensure_venv ."], cwd=bad,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and "failed (exit code 1)" in r.stderr, r.stderr
    assert "ERROR: No matching distribution found for y" in r.stderr
    assert not (bad / ".venv" / ".hilsim-installed").exists()  # tried again next time


def test_every_directory_of_the_packages_is_a_listed_package() -> None:
    conf = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages, dirs = set(conf["packages"]), conf.get("package-dir", {})
    roots = {"hilsim": REPO / "hilsim", **{p: REPO / d for p, d in dirs.items()}}
    data = conf.get("package-data", {})

    def is_data(d: Path, root: Path, pkg: str) -> bool:
        """A folder of no module whose every file a listed ancestor package's package-data globs take (the ROS 2
        interface files of hilsim/core/ros2/interfaces/, laid out as ROS packages ship them)."""
        if any(f.suffix == ".py" for f in d.iterdir()):
            return False
        parts = d.relative_to(root).parts
        for i in range(len(parts) - 1, -1, -1):
            owner = ".".join([pkg, *parts[:i]])
            globs = data.get(owner, [])
            if owner in packages and globs:
                base = root.joinpath(*parts[:i])
                return all(any(f.relative_to(base).match(g) for g in globs) for f in d.iterdir() if f.is_file())
        return False

    missing = []
    for pkg, root in roots.items():
        for d in [root, *(p for p in root.rglob("*") if p.is_dir())]:
            if d.name == "__pycache__" or not any(f.is_file() for f in d.iterdir()):
                continue
            name = ".".join([pkg, *d.relative_to(root).parts])
            if name not in packages and not is_data(d, root, pkg):
                missing.append(name)
    assert not missing, f"add to [tool.setuptools] packages in pyproject.toml: {missing}"
    assert conf["package-data"]["hilsim.ui.static"], conf["package-data"]
