"""Starting one service's process: ``hilsim run NAME`` with its log, its identity and its restart count.

A child gets SIGTERM if the launcher dies (PR_SET_PDEATHSIG), leaves the terminal's signals to the
launcher (a process group of its own) and starts in an ordinary scheduling class whatever the
launcher's (:func:`pdeathsig`). Its stdout and stderr go to ``<run>/<name>.log`` (a restart appends);
the recorder's stdout, its per-key summary, is pumped to ``<run>/logger.out`` by a thread. The
:class:`Child` is what the launcher keeps of each. Reads and writes no key.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hilsim.core import transport
from hilsim.core.restart import RESTART_ENV
from hilsim.core.threads import sigterm_when_parent_dies


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    ready: bool = False  # every service of the process has announced itself
    alive: set[str] = field(default_factory=set)  # those that have (a composed process has several)
    restarts: int = 0
    restart_at: float | None = None  # monotonic time of the pending restart
    died_at: float = 0.0  # monotonic time its last process was found dead


def pdeathsig() -> None:
    """In the child: get SIGTERM when the launcher dies, and leave the terminal's signals to it; an
    ordinary scheduling class whatever the launcher's (a realtime run's router: each service asks
    for its own)."""
    os.setpgrp()
    sigterm_when_parent_dies()
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass


STOP_WITH_PARENT_ENV = "HILSIM_STOP_WITH_PARENT"


def stop_with_parent() -> None:
    """In ``hilsim up``, where ``HILSIM_STOP_WITH_PARENT=1`` asks for it (the test suite sets it): SIGTERM
    when the process that started this one dies, so that a run started by a killed pytest worker stops
    with its services instead of staying up. Opt-in: ``nohup hilsim up … &`` must outlive its shell.
    The kernel signals when the starting *thread* ends: start it from a thread that lives as long."""
    if os.environ.get(STOP_WITH_PARENT_ENV) != "1":
        return
    parent = os.getppid()
    if sigterm_when_parent_dies() and os.getppid() != parent:  # it died before the signal was asked for
        os.kill(os.getpid(), signal.SIGTERM)


def spawn(name: str, attempt: int, run_dir: Path, cfg_path: Path, auth: Path | None) -> subprocess.Popen[bytes]:
    """Start ``hilsim run NAME`` with the scenario ``cfg_path`` and the identity ``auth``; a restart
    (``attempt`` > 0) appends to the same log."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    if attempt:
        env[RESTART_ENV] = str(attempt)
    if auth is not None:  # its own identity on the run's router, whatever the caller's environment says
        env[transport.AUTH_ENV] = str(auth)
    log_path = run_dir / f"{name}.log"
    with open(log_path, "ab" if attempt else "wb") as logf:
        if attempt:
            logf.write(f"--- hilsim up: restart {attempt} of {name} ---\n".encode())
            logf.flush()
        proc = subprocess.Popen(
            [sys.executable, "-m", "hilsim.cli", "run", name, "--config", str(cfg_path)],
            stdout=logf if name != "logger" else subprocess.PIPE,
            stderr=logf,
            stdin=subprocess.DEVNULL,
            env=env,
            preexec_fn=pdeathsig,
        )
    if name == "logger":
        # the logger's stdout is its per-key summary, shown to the user at the end
        assert proc.stdout is not None
        threading.Thread(target=pump, args=(proc.stdout, log_path, attempt), daemon=True).start()
    return proc


def pump(stream: Any, log_path: Path, attempt: int = 0) -> None:
    with open(log_path.with_suffix(".out"), "ab" if attempt else "wb") as f:
        for line in stream:
            f.write(line)
            f.flush()


def tail(path: Path, n: int = 1) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    errs = [ln for ln in lines if "ERROR" in ln or "Error" in ln or "error" in ln]
    return " | ".join((errs or lines)[-n:])[-300:]
