"""docker/compose.yaml for real: the image built (offline: docker/build-offline.sh), the arm scenario
brought up in containers with podman-compose as the README says, judged by the physics truth the
recorder wrote to the host, and brought down with nothing left behind.

Podman reads the repository's config/podman/containers.conf (CONTAINERS_CONF, unless the environment
names another): runc, and limits this kernel lets root set. scripts/test.sh installs podman, runc,
mmdebstrap and podman-compose and builds the base image when it is missing; the image and the
wheels (~/.cache/hilsim-wheels) stay between runs, so a second run only rebuilds the layers a code
change touched. A machine that cannot run containers skips the test with one line naming what is
missing, except under ``CI=true``, where that is a failure."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from util import REPO

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.bag_read import key_counts, open_bag

COMPOSE = REPO / "docker" / "compose.yaml"
BASE = "localhost/hilsim-base:bookworm"  # docker/build-offline.sh's default
TRUTH_SLACK = 0.002  # rad: the truth may differ from the encoders the planner judged by (resolution, noise)

pytestmark = pytest.mark.e2e


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("CONTAINERS_CONF", str(REPO / "config" / "podman" / "containers.conf"))
    return env


def _podman_compose() -> str | None:
    here = Path(sys.executable).parent / "podman-compose"  # scripts/test.sh installs it into .venv
    return str(here) if here.exists() else shutil.which("podman-compose")


def _missing(env: dict[str, str]) -> str | None:
    """What stops this machine from running the compose file in containers (one line), or None.
    Builds the base image if it is missing (docker/build-offline.sh --base-only)."""
    if shutil.which("podman") is None:
        return "podman is not installed (scripts/test.sh installs it with apt-get as root)"
    if _podman_compose() is None:
        return "podman-compose is not installed (scripts/test.sh installs it into .venv with pip)"
    have_base = subprocess.run(["podman", "image", "exists", BASE], env=env).returncode == 0
    if not have_base:
        if shutil.which("mmdebstrap") is None:
            return f"the base image {BASE} is missing and mmdebstrap, which builds it, is not installed"
        p = subprocess.run(["bash", "docker/build-offline.sh", "--base-only"], cwd=REPO, env=env,
                           capture_output=True, text=True, timeout=600)
        if p.returncode != 0:
            return f"the base image {BASE} could not be built: {_last_line(p.stderr + p.stdout)}"
    p = subprocess.run(["podman", "run", "--rm", "--network", "none", BASE, "true"], env=env,
                       capture_output=True, text=True, timeout=120)
    if p.returncode != 0:
        return f"podman cannot start a container here ({env['CONTAINERS_CONF']}): {_last_line(p.stderr)}"
    return None


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1] if lines else "(no output)"


def _free_port() -> int:
    """A TCP port free on every address of the host (the router's published port)."""
    with socket.socket() as s:
        s.bind(("0.0.0.0", 0))
        return int(s.getsockname()[1])


def _leftovers(project: str, env: dict[str, str]) -> dict[str, list[str]]:
    """Containers, networks and volumes of the compose project still on the machine."""
    label = f"label=io.podman.compose.project={project}"
    out = {}
    for what, cmd in {"containers": ["ps", "-a", "--format", "{{.Names}}"],
                      "networks": ["network", "ls", "--format", "{{.Name}}"],
                      "volumes": ["volume", "ls", "--format", "{{.Name}}"]}.items():
        p = subprocess.run(["podman", *cmd, "--filter", label], env=env, capture_output=True, text=True)
        out[what] = p.stdout.split() if p.returncode == 0 else [f"? {p.stderr.strip()}"]
    # podman-compose names its network <project>_default (older ones left no label on it)
    p = subprocess.run(["podman", "network", "exists", f"{project}_default"], env=env)
    if p.returncode == 0 and f"{project}_default" not in out["networks"]:
        out["networks"].append(f"{project}_default")
    return {k: v for k, v in out.items() if v}


@pytest.mark.timeout(1200)  # cold: the base image, the wheels and the image are built first
def test_the_arm_runs_in_containers_with_podman_compose(tmp_path: Path) -> None:
    env = _env()
    why = _missing(env)
    if why is not None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true: the compose run must run, but {why}")
        pytest.skip(why)
    t0 = time.monotonic()
    p = subprocess.run(["bash", "docker/build-offline.sh"], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=1200)
    assert p.returncode == 0, f"docker/build-offline.sh failed:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    t_build = time.monotonic() - t0

    project = f"hilsim-test-{os.getpid()}"  # never another run's containers (a user's `hilsim` project)
    runs = tmp_path / "runs"
    runs.mkdir()
    env.update(HILSIM_ROUTER_PORT=str(_free_port()), HILSIM_RUNS=str(runs))
    pc = [_podman_compose() or "podman-compose", "-p", project, "-f", str(COMPOSE)]
    log = tmp_path / "compose.log"
    t1 = time.monotonic()
    try:
        with open(log, "w") as f:
            # the README's command: the logger container ends the run with hilsim up's verdict
            up = subprocess.run([*pc, "up", "--exit-code-from", "logger"], cwd=REPO, env=env, stdout=f,
                                stderr=subprocess.STDOUT, timeout=600)
        t_up = time.monotonic() - t1
    finally:
        down = subprocess.run([*pc, "down", "-v"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    text = log.read_text(errors="replace")
    assert down.returncode == 0, down.stdout + down.stderr
    left = _leftovers(project, env)
    assert not left, f"left behind after `podman-compose down`: {left}"
    assert up.returncode == 0, f"exit code {up.returncode}:\n{text[-6000:]}"

    # the logger container's summary is hilsim up's: every target, the recording's counts
    logger_lines = [ln.split("|", 1)[1].strip() for ln in text.splitlines() if "[logger]" in ln and "|" in ln]
    said = "\n".join(logger_lines)
    sc = load_scenario(REPO / "config" / "arm.yaml")
    n = len(sc.task.targets)
    assert f"targets reached: {n}/{n}" in said and "result: OK" in said, said[-3000:]
    # what each container runs: one service each, the router apart
    for svc in ("physics", "sensors", "controller", "planner"):
        assert f"hilsim up arm: 5 services ({svc} here, the rest from other hosts)" in text, svc

    # the recording, on the host
    dirs = [d for d in runs.iterdir() if d.is_dir()]
    assert len(dirs) == 1, dirs
    run = dirs[0]
    assert (run / "recording.rrd").stat().st_size > 10_000
    counts = json.loads((run / "record_summary.json").read_text())
    rec, recv = sum(v["recorded"] for v in counts.values()), sum(v["received"] for v in counts.values())
    assert f"recorded {rec} of {recv} received messages on {len(counts)} keys" in said, said[-3000:]
    assert rec == recv and not any(v.get("lost") for v in counts.values()), counts
    held = key_counts(run / "bag")
    assert {k: v["received"] for k, v in counts.items() if v["received"]} == dict(held)

    # judged by the physics truth in the bag: each target reached, in order, within the tolerance
    truth_key = Keys.of(sc).truth("joint_states")
    truth = [msgs.decode(msgs.JointState, m.data) for m in open_bag(run / "bag").messages() if m.key == truth_key]
    assert len(truth) > 1000, len(truth)
    pos = np.array([t.position for t in truth])
    i = 0
    for k, target in enumerate(sc.task.targets):
        err = np.abs(pos[i:] - np.asarray(target)).max(axis=1)
        near = np.flatnonzero(err <= sc.task.tolerance + TRUTH_SLACK)
        assert near.size, f"target {k + 1} {target} never reached in the truth (closest {err.min():.4f} rad)"
        i += int(near[0])
    scenario = yaml.safe_load((run / "scenario.yaml").read_text())
    assert scenario["name"] == "arm" and scenario["zenoh"]["connect"] == ["tcp/router:7447"], scenario["zenoh"]
    print(f"\ncompose run: build {t_build:.1f} s, up {t_up:.1f} s, down {time.monotonic() - t1 - t_up:.1f} s")
