"""Shared fixtures: a Zenoh router on a free loopback port, scenarios wired to it, and
leak checks (no session or child process may outlive its test)."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
import zenoh
from util import alive

from hilsim.core import transport
from hilsim.core.config import ZenohConfig
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
# every `hilsim up` a test starts stops when the test's process dies (a killed worker leaves no run up)
os.environ.setdefault("HILSIM_STOP_WITH_PARENT", "1")


@pytest.fixture
def router() -> Iterator[str]:
    """Endpoint of a fresh Zenoh router on loopback."""
    endpoint = f"tcp/127.0.0.1:{transport.free_port()}"
    r = transport.open_router(endpoint)
    yield endpoint
    r.close()


@pytest.fixture
def scenario(router: str, tmp_path: Path) -> Callable[..., Any]:
    """``scenario(name='arm', **overrides)``: a loaded scenario connected to the test router,
    recording under tmp_path. Overrides are dotted fields, e.g. ``{'clock.mode': 'realtime'}``."""

    def make(name: str = "arm", overrides: dict[str, Any] | None = None) -> Any:
        o = {"zenoh.connect": [router], "logger.out_dir": str(tmp_path / "runs")}
        o.update(overrides or {})
        return load_scenario(name, o)

    return make


@pytest.fixture
def session(router: str) -> Iterator[zenoh.Session]:
    """A peer session of the test itself, connected to the router."""
    s = transport.open_session(ZenohConfig(connect=[router]))
    yield s
    s.close()


class ServiceThread:
    """Runs a Service in a thread of the test process (unit-level tests; e2e tests use processes)."""

    def __init__(self, svc: Any) -> None:
        self.svc = svc
        self.rc: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True, name=f"svc:{svc.name}")

    def _run(self) -> None:
        self.rc = self.svc.run()

    def __enter__(self) -> Any:
        self.thread.start()
        for _ in range(200):
            if self.svc.state != "starting":
                break
            threading.Event().wait(0.02)
        return self.svc

    def __exit__(self, *_: Any) -> None:
        self.svc.request_stop()
        self.thread.join(10)
        assert not self.thread.is_alive(), f"{self.svc.name} did not stop"


@pytest.fixture
def run_service() -> Callable[[Any], ServiceThread]:
    return ServiceThread


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """Fail a test that leaves a child process or a service thread running after it ends."""
    before = {t.ident for t in threading.enumerate()}
    me = psutil.Process()
    # what ran before the test is not the test's: scripts/test.sh's ROS 2 install beside the suite (pytest
    # took over its shell, so it is pytest's child) and whatever it starts
    older = {k.pid for k in me.children(recursive=True)}
    yield
    deadline = time.monotonic() + 5.0
    while True:
        kids = [k for k in me.children(recursive=True) if alive(k)
                and not _started_by(k, older)]
        if not kids or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    said = [(k.pid, _cmd(k)) for k in kids]  # before the kill: a zombie has no command line to read
    for k in kids:
        with contextlib.suppress(psutil.Error):
            k.kill()
    assert not kids, f"test left processes running: {said}"
    leaked = [t for t in threading.enumerate() if t.ident not in before and t.name.startswith("svc:")]
    assert not leaked, f"test left service threads running: {[t.name for t in leaked]}"
    # a real-time scheduling class (physics' realtime loop, as root) must stay in its own process:
    # a pytest thread left SCHED_FIFO would starve the services of every later test
    # (Zenoh's own shared-memory watchdog threads ask for a real-time class by design: not ours)
    rt = [f"{tid} ({_comm(tid)})" for tid in os.listdir("/proc/self/task")
          if _policy(int(tid)) != os.SCHED_OTHER and not _comm(tid).startswith("Watchdog")]
    assert not rt, f"test left threads of the test process in a real-time scheduling class: {rt}"


def _started_by(proc: psutil.Process, pids: set[int]) -> bool:
    """``proc`` is one of ``pids`` or their descendant."""
    try:
        return proc.pid in pids or any(p.pid in pids for p in proc.parents())
    except psutil.Error:
        return False


def _cmd(proc: psutil.Process) -> str:
    try:
        return " ".join(proc.cmdline()[-4:])
    except psutil.Error:  # it ended meanwhile
        return "?"


def _comm(tid: str) -> str:
    try:
        return open(f"/proc/self/task/{tid}/comm").read().strip()
    except OSError:
        return "?"


def _policy(tid: int) -> int:
    try:
        return os.sched_getscheduler(tid)
    except OSError:  # the thread ended meanwhile
        return os.SCHED_OTHER


def pytest_unconfigure(config: pytest.Config) -> None:
    """After the summary: hide the OMPL binding's "nanobind: leaked …" report at interpreter
    exit, so the test run ends on pytest's own closing line."""
    import os
    import sys

    sys.stderr.flush()
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
