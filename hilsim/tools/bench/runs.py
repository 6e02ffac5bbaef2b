"""How ``hilsim bench`` runs the arm: its benchmark scenario, and a run of it with ``hilsim up``'s launcher.

The shared part of :mod:`hilsim.tools.bench.pipeline`, :mod:`hilsim.tools.bench.live` and
:mod:`hilsim.tools.bench.scale`: :func:`arm_scenario` (the arm holding position, no task, ``clock.controller_lag``
0 unless asked), :func:`run_arm` (a run with the launcher, its outcome and each process's CPU seconds),
:func:`launch` (the same to the scenario's duration: physics' health at the end) and :func:`cpu_s`. Zenoh keys:
none of its own (the run's services').
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import psutil

from hilsim.core.config import Scenario
from hilsim.core.scenario import load_scenario


def arm_scenario(sim_seconds: float, **more: Any) -> Scenario:
    # lag 0 unless a pipeline says otherwise: the figures stay comparable with every earlier sitting
    o: dict[str, Any] = {"task.targets": [], "duration": sim_seconds, "clock.controller_lag": 0}
    o.update(more)
    return load_scenario("arm", o)


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of a process and its threads so far; 0 if it is gone."""
    try:
        t = psutil.Process(pid).cpu_times()
        return float(t.user + t.system)
    except psutil.Error:
        return 0.0


def run_arm(sc: Scenario, run_dir: Path, cpu: dict[str, float] | None = None, *, task: bool = False,
         run_router: bool = False, per_service: bool = True, after_ready: Any = None) -> Any:
    """Run ``sc`` with ``hilsim up``'s launcher; its outcome (hilsim.launch.follow.Outcome). ``cpu``, if
    given, is filled with the CPU seconds each process spent from "ready" to the end of the run (the
    router and launcher: this process). ``task``: the run ends with its task, not at a duration.

    The router: a plain one, whose clients are then peers that also reach each other directly
    (every earlier sitting's figures); ``run_router``: the run's own, with its user and password,
    as ``hilsim up`` opens it, every service a client of it, so every sample passes through it; each
    process with an identity of its own (``per_service``), or all with one that may do everything (as
    before identities, docs/security.md)."""
    from hilsim.launch.launcher import Launcher, open_default_router

    ep, router = (None, None) if run_router else open_default_router()
    la = Launcher(sc, run_dir, router=ep, quiet=True, per_service=per_service)
    try:
        la.start()
        if not la.wait_ready():
            raise RuntimeError(f"services did not start; see {run_dir}")
        if after_ready is not None:
            after_ready(la)
        pids = {c.name: c.proc.pid for c in la.children.values()}
        pids["router+launcher"] = os.getpid()
        c0 = {n: cpu_s(p) for n, p in pids.items()}
        la.follow(wall_timeout=600)
        if cpu is not None:  # before stop: a process that has exited has no CPU times to read
            cpu.update({n: cpu_s(p) - c0[n] for n, p in pids.items()})
    finally:
        la.stop()
        if router is not None:
            router.close()
    if la.outcome.died:
        raise RuntimeError(f"service died during the benchmark: {la.outcome.died}; see {run_dir}")
    if task and la.outcome.task is None:
        raise RuntimeError(f"the run's task did not end; see {run_dir}")
    if not task and not la.outcome.physics_done:
        raise RuntimeError(f"the run did not reach its duration; see {run_dir}")
    return la.outcome


def launch(sc: Scenario, run_dir: Path, cpu: dict[str, float] | None = None,
            run_router: bool = False, per_service: bool = True) -> dict[str, str]:
    """:func:`run_arm` to the scenario's duration; physics' health at the end."""
    return dict(run_arm(sc, run_dir, cpu, run_router=run_router, per_service=per_service).health.get("physics", {}))
