"""``hilsim compose SCENARIO [--hil FILE]…``: a docker compose file made from the scenarios, and the
entry point of its containers (``python -m hilsim.launch.deploy``).

The compose file is generated, so it cannot drift from the scenarios: one container per process
``hilsim up`` would start (``Scenario.launch_units``), plus the Zenoh router (``hilsim router``, in a
container of its own). Every container is one host of the several-machines set-up
(docs/deployment.md): it runs ``hilsim up SCENARIO --only ITS-SERVICE --router tcp/router:7447``, so
its service runs exactly as the launcher runs it (``hilsim run SERVICE --config FILE``, supervised,
restarted by the scenario's policy), waits for the others' liveliness tokens, follows the run and
stops its service when the task ends, as ``hilsim up`` does. Every container reads the scenario
named by ``HILSIM_SCENARIO`` (default: SCENARIO). The recorder's container writes the run directory
(``runs/<stamp>/``: recording.rrd, bag/, record_summary.json, the logger's log) to ``runs/`` on the
host and ends with ``hilsim up``'s verdict on the whole run, task and recording: its exit code is the
run's, and ``docker compose … up --exit-code-from logger`` returns it.

Compose ends a run when the first container exits (``--exit-code-from`` implies
``--abort-on-container-exit``, podman-compose the same), so that must be the recorder's, and only
after physics stopped (the recorder drains what is still in flight; a recorder stopped while
lockstep physics still steps would miss samples). So every other container ``--hold``s: once its
launcher ended well (the task is over, its service stopped) it stays, idle, until compose stops it;
one that ended badly (its service died, the others never came, the router was unreachable) exits
with that code at once, which stops the run: the recorder's launcher is interrupted, a non-zero exit.

Each ``--hil FILE`` is a HIL scenario (a whole scenario file, e.g. ``config/hil/arm-can.yaml``) that
runs every process of SCENARIO plus its bridges; those bridges become containers under a profile:

- ``hil``: the motor model (and any other joint server);
- ``hil-can``: the CAN bridge and the drive emulator, with host networking, so that ``can0`` (a
  host interface) and python-can's UDP multicast bus are reachable; they reach the router through
  its published port on the host;
- ``hil-mavlink``: the MAVLink bridge (and the GPS emulator), with the serial device or the UDP port
  of ``bridge-mavlink.connection`` passed through.

``HILSIM_SCENARIO=config/hil/arm-motor-model.yaml docker compose -f docker/compose.yaml --profile hil
up --exit-code-from logger`` then runs that HIL set-up. Physics (in realtime) and the drive bridges
(with ``realtime_priority``) may use SCHED_FIFO: their containers get ``cap_add: [SYS_NICE]``, which
is all SCHED_FIFO needs (docs/deployment.md says when the host still refuses it).
``tests/test_compose_file.py`` checks that the shipped files are this module's output and runs each
container's command outside any engine; ``tests/test_compose_run.py`` runs the arm's in containers.
"""

from __future__ import annotations

import argparse
import re
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import yaml

from hilsim.core.config import REPO_ROOT, ConfigError, Scenario
from hilsim.core.scenario import load_scenario, scenario_path

ROUTER_PORT = 7447
ROUTER = f"tcp/router:{ROUTER_PORT}"  # the router container, by its name on the compose network
# the router's port on the host (tools, the panel, ROS 2 nodes there; the host-network bridges):
# HILSIM_ROUTER_PORT when 7447 is taken (e.g. by a `hilsim up` on the same host)
HOST_PORT = f"${{HILSIM_ROUTER_PORT:-{ROUTER_PORT}}}"
IN_CONTAINER_RUNS = "/hilsim/runs"  # run directories inside a container; the recorder's is mounted from ../runs
ENTRYPOINT = ["python", "-m", "hilsim.launch.deploy"]  # this module's main, in the image's venv
HOLD = "--hold"
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


def result_unit(units: list[str]) -> str:
    """The launch unit whose container ends the run with its verdict: the recorder's (its launcher
    alone judges the recording), else physics'."""
    for svc in ("logger", "physics"):
        for u in units:
            if svc in u.split("+"):
                return u
    return units[0]


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
    result = result_unit(base.launch_units())
    anchor = {
        "image": "hilsim:latest",
        "build": {"context": "..", "dockerfile": "docker/Dockerfile"},
        # PID 1 reaps and passes compose's stop signal on (a process as PID 1 gets only the signals it handles)
        "init": True,
        "entrypoint": ENTRYPOINT,
        "environment": {"HILSIM_ZENOH_CONNECT": ROUTER,
                        # containers reach each other only through the router
                        "HILSIM_ZENOH_MODE": "client"},
        "depends_on": ["router"],
        "restart": "no",
        "stop_signal": "SIGINT",
        "stop_grace_period": "30s",
    }
    services: dict[str, Any] = {
        "router": {"<<": anchor, "entrypoint": ["hilsim"], "depends_on": [],
                   "command": ["router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}"],
                   # on the host's loopback only: the router has no authentication (docs/security.md)
                   "ports": [f"127.0.0.1:{HOST_PORT}:{ROUTER_PORT}"]}}
    for u, profile in sorted(units.items(), key=lambda kv: (kv[1] or "", list(units).index(kv[0]))):
        name = container_name(u)  # a composed process a+b: one container
        svc: dict[str, Any] = {"<<": anchor}
        if profile:
            svc["profiles"] = [profile]
        router = ROUTER
        if REALTIME_CAPABLE & set(u.split("+")):
            # physics in realtime, and the drive bridges with realtime_priority, ask for SCHED_FIFO
            # (they run without when refused, and say so)
            svc["cap_add"] = ["SYS_NICE"]
        if "physics" in u.split("+"):
            # started last: the others are up by the time it waits for them
            others = [container_name(n) for n, p in units.items() if n != u and p is None]
            svc["depends_on"] = ["router", *others]
        if "logger" in u.split("+"):
            # HILSIM_RUNS: another directory of the host (an absolute path)
            svc["volumes"] = [f"${{HILSIM_RUNS:-../runs}}:{IN_CONTAINER_RUNS}"]
        if profile in HOST_NETWORK:
            svc["network_mode"] = "host"
            svc["depends_on"] = []  # with host networking it meets the router on its published port
            router = f"tcp/127.0.0.1:{HOST_PORT}"
            svc["environment"] = {**anchor["environment"], "HILSIM_ZENOH_CONNECT": router}
        svc.update(extra.get(u, {}))
        hold = [] if u == result else [HOLD]
        svc["command"] = [*hold, "up", config, "--only", u.replace("+", ","), "--router", router]
        services[name] = svc
    return {"name": "hilsim", "x-podman": {"in_pod": False}, "x-service": anchor, "services": services}


def _result(data: dict[str, Any]) -> str:
    """The container that ends the run: the one that does not ``--hold``."""
    return next(n for n, s in data["services"].items() if n != "router" and HOLD not in s["command"])


def render(data: dict[str, Any], argv: list[str]) -> str:
    """YAML text with the anchor written once (``x-service: &service``, ``<<: *service``)."""
    anchor = data["x-service"]
    result = _result(data)
    hil = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--hil"]
    profiles = [s["profiles"][0] for s in data["services"].values() if s.get("profiles")]

    class Dumper(yaml.SafeDumper):
        def ignore_aliases(self, d: Any) -> bool:
            return True

    def dump(obj: Any) -> str:
        return yaml.dump(obj, Dumper=Dumper, sort_keys=False, default_flow_style=None, width=120)

    head = [
        "# Generated by `hilsim " + " ".join(argv) + "`: do not edit, regenerate",
        "# (tests/test_compose_file.py fails when this file and the scenarios disagree).",
        "# One container per process `hilsim up` starts, each one host of the several-machines set-up",
        "# (`hilsim up SCENARIO --only ITS-SERVICE --router tcp/router:7447`), on the scenario HILSIM_SCENARIO",
        f"# names. The {result} container ends the run with `hilsim up`'s verdict; run it (podman-compose alike):",
        f"#   docker compose -f THIS-FILE up --exit-code-from {result}; docker compose -f THIS-FILE down",
    ]
    if hil and profiles:
        head += ["# HIL bridges are profiles, e.g.",
                 f"#   HILSIM_SCENARIO={hil[0]} docker compose -f THIS-FILE --profile {profiles[0]} up "
                 f"--exit-code-from {result}"]
    head += ["# Recording: ../runs on the host (or HILSIM_RUNS); the router on host port 7447 (or HILSIM_ROUTER_PORT).",
             "# Why the others --hold, realtime privileges, Docker and Podman: docs/deployment.md."]
    body = f"name: {data['name']}\n\n"
    body += "# podman-compose: each container on the compose network, as with docker (not all in one pod)\n"
    body += "x-podman: " + dump(data["x-podman"])
    body += "\nx-service: &service\n"
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


# ---------------------------------------------------------------------------------- in the container
class _LogTail:
    """The service logs the launcher writes to its run directory (``<unit>.log``), copied to this
    process's output as they grow: what ``docker compose logs SERVICE`` shows."""

    def __init__(self, run_dir: Path | None) -> None:
        self.run_dir = run_dir
        self.pos: dict[Path, int] = {}
        self.rest: dict[Path, bytes] = {}

    def step(self, final: bool = False) -> None:
        if self.run_dir is None or not self.run_dir.is_dir():
            return
        for f in sorted(self.run_dir.glob("*.log")):
            try:
                with open(f, "rb") as fh:
                    fh.seek(self.pos.get(f, 0))
                    data = fh.read()
            except OSError:
                continue
            if not data:
                continue
            self.pos[f] = self.pos.get(f, 0) + len(data)
            *lines, rest = (self.rest.pop(f, b"") + data).split(b"\n")
            if final and rest:
                lines.append(rest)
            elif rest:
                self.rest[f] = rest
            if lines:
                sys.stdout.buffer.write(b"".join(ln + b"\n" for ln in lines))
                sys.stdout.flush()


def container_main(argv: list[str]) -> int:
    """``python -m hilsim.launch.deploy [--hold] HILSIM-ARGS…``: a compose service's entry point.

    Runs ``hilsim HILSIM-ARGS`` (``up SCENARIO --only SERVICE --router …``; its run directory
    ``/hilsim/runs/<stamp>`` unless ``--out`` says), shows its service's log as it grows, passes
    SIGINT and SIGTERM on (compose stops a container with SIGINT) and exits with its exit code. With
    ``--hold``, a launcher that ended well leaves this process waiting, idle, for compose's stop
    signal, so that the recorder's container is the first to end (the module's docstring says why).
    """
    hold = argv[:1] == [HOLD]
    args = list(argv[1:] if hold else argv)
    run_dir: Path | None = None
    if args[:1] == ["up"]:
        if "--out" not in args:
            stamp = datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]  # as hilsim up names its run directories
            args += ["--out", f"{IN_CONTAINER_RUNS}/{stamp}"]
        run_dir = Path(args[args.index("--out") + 1])
    got: list[int] = []  # signals received; the handler only appends (no lock taken in a handler)
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda signum, _frame: got.append(signum))
    # its own session: a terminal's Ctrl-C reaches it once, through us
    child = subprocess.Popen([sys.executable, "-m", "hilsim.cli", *args], start_new_session=True)
    tail = _LogTail(run_dir)
    sent = 0
    while child.poll() is None:
        while sent < len(got):
            child.send_signal(got[sent])
            sent += 1
        tail.step()
        time.sleep(0.1)
    tail.step(final=True)
    rc = child.returncode if child.returncode >= 0 else 128 - child.returncode
    if not hold or rc != 0 or got:
        return rc
    print(f"hilsim: this container's share of the run is over (exit code {rc}); waiting for compose to stop it "
          f"(`up --exit-code-from` returns the recorder's verdict)", flush=True)
    while not got:
        time.sleep(0.2)
    return 0


if __name__ == "__main__":
    sys.exit(container_main(sys.argv[1:]))
