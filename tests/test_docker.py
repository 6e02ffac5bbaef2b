"""Static checks of the docker files (no Docker engine runs here): every compose service runs a
command hilsim accepts, with a config file that exists and validates, on the shared image."""

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
    for name, svc in services.items():
        cmd = [scenario if a == SCENARIO_VAR else a for a in svc["command"]]
        args = parser.parse_args(cmd)  # raises SystemExit on a command hilsim would reject
        if name == "router":
            assert args.cmd == "router" and args.listen.endswith(":7447")
            continue
        assert args.cmd == "run" and args.service == name
        # the config path is relative to the image's WORKDIR, which holds the repository's config/
        sc = load_scenario(REPO / args.config)
        assert name in sc.processes()
        env = svc["environment"]
        assert env["HILSIM_ZENOH_CONNECT"] == "tcp/router:7447"
        assert "router" in svc.get("depends_on", []) or name == "router"
        assert svc["build"]["dockerfile"] == "docker/Dockerfile"
        assert (DOCKER / svc["build"]["context"]).resolve() == REPO


def test_dockerfile_copies_what_the_services_need() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    for part in ("hilsim", "services", "bridges", "models", "config", "pyproject.toml"):
        assert f"COPY {part}" in text, part
        assert (REPO / part).exists()
    assert "WORKDIR /hilsim" in text and 'ENTRYPOINT ["hilsim"]' in text


def test_docker_files_mention_only_files_that_exist() -> None:
    import re

    for f in ("compose.yaml", "Dockerfile"):
        text = (DOCKER / f).read_text().replace(SCENARIO_VAR, "config/arm.yaml")
        for name in re.findall(r"[\w./-]+\.(?:ya?ml|py|toml|md)\b", text):
            exists = (DOCKER / name).exists() or (REPO / name).exists()
            assert exists, f"docker/{f} mentions {name}, which does not exist"
