"""Running step experiments (:mod:`hilsim.tools.tuning.rig`): the scenario's loop, and one run of its real services.

:func:`loop_scenario` is the part of a scenario whose step responses are measured (lockstep; with
hardware in the loop, realtime with its servers and stand-ins); :func:`run_experiments` runs the
experiments in one run of those services as separate processes, with a router of its own and the
rig as one more participant, and returns what they measured.
"""

from __future__ import annotations

import logging
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hilsim.core import transport
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.scenario import load_scenario
from hilsim.tools.tuning.rig import (
    CONTROLLERS,
    HARDWARE_STAND_INS,
    LOOP_SENSORS,
    LOOP_SERVICES,
    Experiment,
    LateStep,
    Response,
    RigError,
    StepRig,
)


def loop_scenario(robot: str, overrides: dict[str, Any] | None = None, overlays: Sequence[str | Path] = (),
                  record: bool = False) -> Scenario:
    """The scenario's physics, sensors and controller in lockstep, nothing else (no planner or
    navigator, no recorder unless ``record``, no task; no sensor the loops do not read, e.g. the
    rover's laser): the loop whose step responses are measured. A scenario with hardware in the loop
    (a joint served by an external server) stays realtime and keeps its servers and the services that
    stand in for hardware (the drive emulator)."""
    o: dict[str, Any] = {"task.targets": []}
    o.update(overrides or {})
    sc = load_scenario(robot, o, overlays)
    hil = bool(sc.external_servers())
    if not hil:
        sc = load_scenario(robot, {"clock.mode": "lockstep", **o}, overlays)
    elif sc.clock.mode != "realtime":
        raise ConfigError(f"{sc.source}: clock.mode: joints served by {', '.join(sc.external_servers())} (hardware) "
                          f"need clock.mode: realtime")
    if sc.controller.type not in CONTROLLERS:
        raise ConfigError(f"{sc.source}: controller.type {sc.controller.type!r}: step experiments need a "
                          f"controller with per-joint PIDs ({' or '.join(CONTROLLERS)})")
    for c in sc.sensors.values():
        c.enabled = c.enabled and c.type in LOOP_SENSORS
    keep = [*LOOP_SERVICES, *(HARDWARE_STAND_INS if hil else ()), *(("logger",) if record else ())]
    missing = [s for s in LOOP_SERVICES if s not in sc.services]
    if record and "logger" not in sc.services:
        sc.services = [*sc.services, "logger"]
    sc.services = [s for s in sc.services if s in keep]
    if missing:
        raise ConfigError(f"{sc.source}: services: a step experiment needs {', '.join(missing)}")
    return sc


def run_experiments(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None = None,
                    progress: Callable[[int, int], None] | None = None, wall_timeout: float = 900.0) -> list[Response]:
    """Run the experiments in one lockstep run of the real services and return what they measured
    (once more if a step reached the controller late: on a starved machine a link can lag)."""
    try:
        return _run_once(sc.model_copy(deep=True), experiments, run_dir, progress, wall_timeout)
    except LateStep as e:
        aside = ""
        if run_dir is not None and run_dir.exists():  # kept, apart: the run made again is run_dir's alone
            late = next(run_dir.with_name(f"{run_dir.name}-late{i}") for i in range(1, 100)
                        if not run_dir.with_name(f"{run_dir.name}-late{i}").exists())
            run_dir.rename(late)
            aside = f" (that run: {late})"
        logging.getLogger("hilsim.step-rig").warning("%s; running the experiments again%s", e, aside)
        return _run_once(sc.model_copy(deep=True), experiments, run_dir, progress, wall_timeout)


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def _run_once(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None,
              progress: Callable[[int, int], None] | None, wall_timeout: float) -> list[Response]:
    # Ctrl-C and SIGTERM stop the run (and its services) wherever it is; set explicitly, as hilsim up
    # does, since a process started in the background inherits SIGINT ignored
    old = {}
    if threading.current_thread() is threading.main_thread():
        old = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run_services(sc, experiments, run_dir, progress, wall_timeout)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _run_services(sc: Scenario, experiments: Sequence[Experiment], run_dir: Path | None,
                  progress: Callable[[int, int], None] | None, wall_timeout: float) -> list[Response]:
    from hilsim.launch.launcher import Launcher

    if not experiments:
        return []
    rig = StepRig(sc, experiments, progress)  # first: a bad experiment is a ConfigError before anything opens
    sc.duration = rig.end * sc.clock.dt
    if rig.rover:  # the rover's steps: its controller's own script (see the module)
        sc.controller.params["script"] = [list(x) for x in rig.script]
    tmp = None
    if run_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="hilsim-rig-")
        run_dir = Path(tmp.name)
    # a router of our own on a free port: never the default one another simulation may be using
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    sc.zenoh.connect = [ep]
    session = transport.open_session(sc.zenoh)
    # the rig's lockstep token exists before any service starts, so physics counts it in at step 0
    worker = threading.Thread(target=rig.serve, args=(session,), daemon=True, name="step-rig")
    worker.start()
    la = Launcher(sc, run_dir, router=ep, quiet=True)
    try:
        deadline = time.monotonic() + 10.0
        while rig.state == "starting" and time.monotonic() < deadline:
            time.sleep(0.01)
        if rig.state != "running":
            raise RigError(f"the step rig did not start: {rig.last_error or rig.state}")
        la.start()
        if not la.wait_ready():
            raise RigError(f"the services did not start; see their logs in {run_dir}")
        t0 = time.monotonic()
        while not rig.done.wait(0.2):
            if la.check_children():
                raise RigError(f"a service died: {la.outcome.died}; see {run_dir}")
            if la.outcome.stalled:
                raise RigError(f"the run stalled: {la.outcome.stalled}; see {run_dir}")
            if time.monotonic() - t0 > wall_timeout:
                raise RigError(f"the experiments did not finish within {wall_timeout:.0f} s wall; see {run_dir}")
        if rig.error:
            raise RigError(rig.error)
    finally:
        la.stop()
        rig.request_stop()
        worker.join(timeout=10.0)
        session.close()
        router.close()
        if tmp is not None:
            tmp.cleanup()
    with rig.lock:
        return rig.responses()
