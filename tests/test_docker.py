"""Static checks of the docker files: every compose service runs a command hilsim accepts, with a
config file that exists and validates, on the shared image (tests/test_compose_run.py runs the arm's
in containers; these also cover the profiles and files a run does not use)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hilsim.cli import build_parser
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
DOCKER = REPO / "docker"


def _compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


SCENARIO_VAR = "${HILSIM_SCENARIO:-config/arm.yaml}"


@pytest.mark.parametrize(("scenario", "profiles"), [("config/arm.yaml", set()),
                                                    ("config/hil/arm-motor-model.yaml", {"hil"})])
def test_compose_runs_every_service_with_valid_commands(scenario: str, profiles: set[str]) -> None:
    """With the default scenario, and with HILSIM_SCENARIO naming a HIL one and its profile on:
    every process the scenario needs is a compose service, and every command parses."""
    comp = _compose()
    services = {n: s for n, s in comp["services"].items() if set(s.get("profiles", [])) <= profiles}
    needed = load_scenario(REPO / scenario).processes()
    assert set(needed) | {"router"} == set(services), (needed, sorted(services))
    parser = build_parser()
    holding = []
    for name, svc in services.items():
        cmd = [scenario if a == SCENARIO_VAR else a for a in svc["command"]]
        if name == "router":
            assert svc["entrypoint"] == ["hilsim"]
            args = parser.parse_args(cmd)  # raises SystemExit on a command hilsim would reject
            assert args.cmd == "router" and args.listen.endswith(":7447")
            continue
        # python -m hilsim.launch.deploy [--hold] HILSIM-ARGS: `hilsim HILSIM-ARGS`, held or not
        assert svc["entrypoint"] == ["python", "-m", "hilsim.launch.deploy"]
        if cmd[0] == "--hold":
            holding.append(name)
            cmd = cmd[1:]
        args = parser.parse_args(cmd)
        assert args.cmd == "up" and args.only == name and args.router == "tcp/router:7447"
        # the config path is relative to the image's WORKDIR, which holds the repository's config/
        sc = load_scenario(REPO / args.scenario)
        assert name in sc.processes()
        env = svc["environment"]
        assert env["HILSIM_ZENOH_CONNECT"] == "tcp/router:7447"
        assert "router" in svc.get("depends_on", []) or name == "router"
        assert svc["build"]["dockerfile"] == "docker/Dockerfile"
        assert (DOCKER / svc["build"]["context"]).resolve() == REPO
        assert svc["init"] is True  # something as PID 1 that passes compose's stop signal on
    # only the recorder's container ends by itself: `up --exit-code-from logger` returns its verdict
    assert set(services) - set(holding) == {"router", "logger"}, holding


def test_dockerfile_copies_what_the_services_need() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    for part in ("hilsim", "services", "bridges", "models", "config", "pyproject.toml"):
        assert f"COPY {part}" in text, part
        assert (REPO / part).exists()
    assert "WORKDIR /hilsim" in text and 'ENTRYPOINT ["hilsim"]' in text
    # a real user's build: FROM python:3.11-slim and PyPI, unless docker/build-offline.sh says otherwise
    assert "ARG BASE_IMAGE=python:3.11-slim" in text and "FROM ${BASE_IMAGE}" in text
    # no service renders: MuJoCo must not look for OpenGL libraries the image lacks
    assert "MUJOCO_GL=disable" in text


def test_docker_files_mention_only_files_that_exist() -> None:
    import re

    for f in ("compose.yaml", "Dockerfile"):
        text = (DOCKER / f).read_text().replace(SCENARIO_VAR, "config/arm.yaml")
        for name in re.findall(r"[\w./-]+\.(?:ya?ml|py|toml|md)\b", text):
            exists = (DOCKER / name).exists() or (REPO / name).exists()
            assert exists, f"docker/{f} mentions {name}, which does not exist"
