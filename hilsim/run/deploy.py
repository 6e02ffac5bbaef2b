"""``hilsim compose SCENARIO [--hil FILE]…``: a docker compose file made from the scenarios.

The compose file is generated, so it cannot drift from the scenarios: one container per process
``hilsim up`` would start (``Scenario.launch_units``), each running exactly what the launcher runs
(``hilsim run SERVICE --config FILE``), plus the Zenoh router. Every container reads the scenario
named by ``HILSIM_SCENARIO`` (default: SCENARIO). Each ``--hil FILE`` is a HIL scenario (a whole
scenario file, e.g. ``config/hil/arm-can.yaml``) that runs every process of SCENARIO plus its
bridges; those bridges become containers under a profile:

- ``hil``: the motor model (and any other joint server);
- ``hil-can``: the CAN bridge and the drive emulator, with host networking, so that ``can0`` (a
  host interface) and python-can's UDP multicast bus are reachable; they reach the router through
  its published port on the host;
- ``hil-mavlink``: the MAVLink bridge (and the GPS emulator), with the serial device or the UDP port
  of ``bridge-mavlink.connection`` passed through.

``HILSIM_SCENARIO=config/hil/arm-can.yaml docker compose -f docker/compose.yaml --profile hil-can up``
then runs that HIL set-up. The recording goes to ``runs/`` on the host (a mounted volume); physics
(in realtime) and the drive bridges (with ``realtime_priority``) may use SCHED_FIFO (``cap_add:
SYS_NICE`` and an ``rtprio`` limit; docs/deployment.md, docs/hil.md).
``tests/test_compose_file.py`` checks that ``docker/compose.yaml`` is this module's output and runs
each container's command outside docker.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import yaml

from hilsim.core.config import REPO_ROOT, ConfigError, Scenario
from hilsim.core.scenario import load_scenario, scenario_path

ROUTER_PORT = 7447
IN_CONTAINER_RUNS = "/hilsim/runs"  # the logger's out_dir inside its container, mounted from ../runs
# the profile of each bridge-like service; any other service a HIL scenario adds is under "hil"
PROFILES = {"bridge-can": "hil-can", "drive-emulator": "hil-can", "bridge-mavlink": "hil-mavlink",
            "gps-emulator": "hil-mavlink"}
HOST_NETWORK = {"hil-can"}  # can0 is an interface of the host, not of a container network


# services that may ask for a real-time scheduling class: their containers are allowed to
REALTIME_CAPABLE = {"physics", "bridge-can", "drive-emulator"}


def _rel(path: Path) -> str:
    """A scenario path as the image sees it (its WORKDIR holds the repository's config/)."""
    p = path.resolve()
    try:
        return str(p.relative_to(REPO_ROOT))
    except ValueError:
        raise ConfigError(f"{path}: not inside the repository ({REPO_ROOT}), so not in the image") from None


def container_name(unit: str) -> str:
    """A launch unit as a compose service name (``[a-zA-Z0-9._-]`` only): a composed process
    ``a+b`` is ``a_b``, every robot's ``controller@*`` is ``controller-fleet``, one robot's
    ``controller@arm3`` is ``controller-arm3``."""
    return unit.replace("+", "_").replace("@*", "-fleet").replace("@", "-")


def _mavlink_passthrough(sc: Scenario) -> dict[str, Any]:
    """Ports or devices for ``bridge-mavlink.connection`` (pymavlink syntax: udpin:HOST:PORT,
    udp:…, tcp:…, or a serial device such as /dev/ttyUSB0[,BAUD])."""
    conn = str(sc.section("bridge-mavlink").get("connection", ""))
    if m := re.match(r"^(udpin|udp|udpout|tcpin|tcp):[^:]*:(\d+)$", conn):
        proto = "udp" if m.group(1).startswith("udp") else "tcp"
        return {"ports": [f"{m.group(2)}:{m.group(2)}/{proto}"]}
    if m := re.search(r"(/dev/[\w./-]+)", conn):
        return {"devices": [f"{m.group(1)}:{m.group(1)}"]}
    return {}


def compose(scenario: str | Path, hil: list[str | Path] | tuple[str | Path, ...] = ()) -> dict[str, Any]:
    """The compose file (as data) for ``scenario`` and the HIL scenarios ``hil``."""
    base_path = scenario_path(scenario)
    base = load_scenario(base_path)
    default = _rel(base_path)
    config = f"${{HILSIM_SCENARIO:-{default}}}"
    units: dict[str, str | None] = {u: None for u in base.launch_units()}  # unit -> profile
    extra: dict[str, Any] = {}
    for f in hil:
        path = scenario_path(f)
        sc = load_scenario(path)
        lost = [u for u in base.launch_units() if u not in sc.launch_units()]
        if lost:
            raise ConfigError(f"--hil {f}: runs no {', '.join(lost)}, which {default} runs (a compose file serves "
                              f"one scenario and its HIL variants: generate another for it)")
        for u in sc.launch_units():
            if u not in units:
                units[u] = PROFILES.get(u.split("+")[0], "hil")
                if u == "bridge-mavlink":
                    extra[u] = _mavlink_passthrough(sc)
    anchor = {
        "image": "hilsim:latest",
        "build": {"context": "..", "dockerfile": "docker/Dockerfile"},
        "environment": {"HILSIM_ZENOH_CONNECT": f"tcp/router:{ROUTER_PORT}",
                        # containers reach each other only through the router
                        "HILSIM_ZENOH_MODE": "client"},
        "depends_on": ["router"],
        "restart": "no",
        "stop_signal": "SIGINT",
        "stop_grace_period": "30s",
    }
    services: dict[str, Any] = {
        "router": {"<<": anchor, "depends_on": [],
                   "command": ["router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}"],
                   "ports": [f"{ROUTER_PORT}:{ROUTER_PORT}"]}}
    for u, profile in sorted(units.items(), key=lambda kv: (kv[1] or "", list(units).index(kv[0]))):
        name = container_name(u)  # a composed process a+b: one container
        svc: dict[str, Any] = {"<<": anchor}
        if profile:
            svc["profiles"] = [profile]
        cmd = ["run", u, "--config", config]
        if "logger" in u.split("+"):
            cmd += ["--set", f"logger.out_dir={IN_CONTAINER_RUNS}"]
            svc["volumes"] = [f"../runs:{IN_CONTAINER_RUNS}"]
        if REALTIME_CAPABLE & set(u.split("+")):
            # physics in realtime, and the drive bridges with realtime_priority, ask for SCHED_FIFO
            # (they run without when refused, and say so)
            svc["cap_add"] = ["SYS_NICE"]
            svc["ulimits"] = {"rtprio": 99}
        if "physics" in u.split("+"):
            others = [container_name(n) for n, p in units.items() if n != u and p is None]
            svc["depends_on"] = ["router", *others]
        if profile in HOST_NETWORK:
            svc["network_mode"] = "host"
            svc["depends_on"] = []  # with host networking it meets the router on its published port
            svc["environment"] = {**anchor["environment"], "HILSIM_ZENOH_CONNECT": f"tcp/127.0.0.1:{ROUTER_PORT}"}
        svc.update(extra.get(u, {}))
        svc["command"] = cmd
        services[name] = svc
    return {"name": "hilsim", "x-service": anchor, "services": services}


def render(data: dict[str, Any], argv: list[str]) -> str:
    """YAML text with the anchor written once (``x-service: &service``, ``<<: *service``)."""
    anchor = data["x-service"]

    class Dumper(yaml.SafeDumper):
        def ignore_aliases(self, d: Any) -> bool:
            return True

    def dump(obj: Any) -> str:
        return yaml.dump(obj, Dumper=Dumper, sort_keys=False, default_flow_style=None, width=120)

    head = [
        "# Generated by `hilsim " + " ".join(argv) + "`: do not edit, regenerate",
        "# (tests/test_compose_file.py fails when this file and the scenarios disagree).",
        "# One container per process `hilsim up` starts, each running `hilsim run SERVICE --config FILE` on the",
        "# scenario HILSIM_SCENARIO names, meeting at the router. HIL bridges are profiles, e.g.",
        "#   HILSIM_SCENARIO=config/hil/arm-can.yaml docker compose -f docker/compose.yaml --profile hil-can up",
        "# Recording: ../runs on the host. Realtime privileges and the multi-host set-up: docs/deployment.md.",
    ]
    body = f"name: {data['name']}\n\nx-service: &service\n"
    body += "".join(f"  {ln}\n" for ln in dump(anchor).splitlines())
    body += "\nservices:\n"
    for name, svc in data["services"].items():
        rest = {k: v for k, v in svc.items() if k != "<<"}
        body += f"  {name}:\n    <<: *service\n" + "".join(f"    {ln}\n" for ln in dump(rest).splitlines()) + "\n"
    return "\n".join(head) + "\n" + body.rstrip("\n") + "\n"


def cmd_compose(args: argparse.Namespace) -> int:
    argv = ["compose", args.scenario, *[a for f in args.hil for a in ("--hil", f)]]
    text = render(compose(args.scenario, args.hil), argv)
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
