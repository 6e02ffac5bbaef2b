"""The restart policy (``restart.services``): a service killed with SIGKILL during a run is
started again by ``hilsim up``, lockstep physics pauses sim time while it is gone and resumes
where it stopped, and the task still ends as it should, judged by the physics truth. Without the
policy a dead service ends the run (``tests/test_e2e.py``). What a restarted process takes over
(live gains, the task's progress) is checked in-process here too."""

from __future__ import annotations

import itertools
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
from util import LEAN, Observer, up, wait_until

from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys
from hilsim.core.restart import RESTART_ENV, keep
from hilsim.core.scenario import load_scenario, parse_overrides

LEFT = [0.866, -0.789, -0.399, 0.0, -0.382, 0.0]


class Output:
    """The launcher's output, read in a thread so the test can wait for a line while it runs."""

    def __init__(self, p: Any) -> None:
        self.lines: list[str] = []
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._read, args=(p,), daemon=True)
        self.thread.start()

    def _read(self, p: Any) -> None:
        for line in p.stdout:
            with self.lock:
                self.lines.append(line)

    def text(self) -> str:
        with self.lock:
            return "".join(self.lines)

    def wait(self, pattern: str, timeout: float) -> re.Match[str]:
        found: list[re.Match[str]] = []

        def seen() -> bool:
            m = re.search(pattern, self.text(), re.M)
            if m:
                found.append(m)
            return m is not None

        assert wait_until(seen, timeout), f"no {pattern!r} within {timeout} s:\n{self.text()}"
        return found[-1]


def ended(p: subprocess.Popen[str], out: Output, timeout: float) -> str:
    """Wait for ``hilsim up`` to end and return all it printed; past ``timeout`` kill it and fail
    with what it printed (on a slow machine, where it got to)."""
    try:
        p.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        out.thread.join(10)
        raise AssertionError(f"hilsim up still running after {timeout:.0f} s:\n{out.text()}") from None
    out.thread.join(10)
    return out.text()


def sim_now(obs: Observer) -> int:
    with obs.lock:
        return obs.truth[-1][0] if obs.truth else -1


def still(obs: Observer, quiet: float = 0.3, timeout: float = 30.0) -> int:
    """The truth's sim time once it has not moved for ``quiet`` wall seconds (physics paused)."""
    end = time.monotonic() + timeout
    last = sim_now(obs)
    while time.monotonic() < end:
        time.sleep(quiet)
        now = sim_now(obs)
        if now == last:
            return now
        last = now
    raise AssertionError(f"the truth never stood still: sim time {last}")


@pytest.mark.e2e
def test_each_service_killed_in_turn_is_restarted_and_the_task_completes(tmp_path: Path) -> None:
    """Lockstep arm, one target: the controller, the sensors and the planner are SIGKILLed one
    after the other while the arm moves; each comes back, sim time stops while it is gone, and
    the target is reached in the truth. (Physics cannot be restarted: it is the world.)"""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    clock: list[int] = []
    clock_sub = obs.session.declare_subscriber(
        Keys().clock, lambda s: clock.append(msgs.ns_of(msgs.decode(msgs.Clock, s.payload.to_bytes()).clock)))
    p = up("arm", "--router", ep, "--no-logger", "--out", str(tmp_path / "run"),
           "--set", f"task.targets=[{LEFT}]", "--set", "restart.services.default=on-failure",
           "--set", "restart.backoff=0.2")
    out = Output(p)
    pids: set[int] = set()
    killed: dict[str, int] = {}
    held: dict[str, int] = {}
    try:
        ready = out.wait(r"^ready: (.*)$", 120)[1]
        now = {n: int(pid) for n, pid in re.findall(r"(\w+) \(pid (\d+)\)", ready)}
        pids |= set(now.values())
        sim_at = 0.3e9
        # the planner first: its restart plans the target again, which would hide whether a
        # restarted controller is sent the trajectory being executed
        for name in ("planner", "sensors", "controller"):
            # while the arm moves (planning the target takes no sim time in lockstep)
            assert wait_until(lambda t=sim_at: sim_now(obs) >= t, 60), out.text()
            psutil.Process(now[name]).send_signal(signal.SIGKILL)
            killed_at = sim_now(obs)
            # where the truth stops while it is gone (this test's view lags on a loaded machine)
            held[name] = still(obs)
            back = out.wait(rf"^  {name} is back \(pid (\d+)\)", 60)
            now[name] = int(back[1])
            pids.add(now[name])
            killed[name] = killed_at
            # 0.3 s of sim past where it stood (this test's view of the kill can lag that much on a
            # loaded machine; the next kill must come after physics ran again)
            sim_at = max(killed_at, held[name]) + 0.3e9
        ended(p, out, 180)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        clock_sub.undeclare()
        obs.close()
        router.close()
    text = out.text()
    assert p.returncode == 0, text
    assert "targets reached: 1/1" in text and "result: OK" in text, text
    # the clock never went back, through every pause and restart
    assert len(clock) > 1000 and all(b >= a for a, b in itertools.pairwise(clock)), clock[:10]
    for name in ("controller", "sensors", "planner"):
        assert re.search(rf"^  restarted {name} \(exit code -9 at sim time [\d.]+ s; back after", text, re.M), text
        assert re.search(rf"^  physics: sim time paused at t=[\d.]+ s until {name} is back", text, re.M), text
    # sim time stopped when each died (after the moment this test saw before the kill), where
    # physics says, judged by the truth: it did not move while the service was gone
    for name, t_kill in killed.items():
        stop = re.search(rf"^  physics: sim time paused at t=([\d.]+) s until {name} is back\n"
                         rf"(?:.*\n)*?  physics: sim time runs again from t=([\d.]+) s", text, re.M)
        assert stop and float(stop[1]) * 1e9 >= t_kill, (name, t_kill, text)
        assert abs(held[name] - float(stop[1]) * 1e9) <= 0.0015e9, (name, held[name], text)
        assert 0 <= float(stop[2]) - float(stop[1]) <= 0.1, (name, text)
    # it resumed where it stopped: the truth's steps go on without a jump (a step published again
    # for a restarted service comes twice) and never back
    stamps = np.array([t for t, _ in obs.truth])
    assert np.all(np.diff(stamps) >= 0) and np.diff(stamps).max() <= 1_000_000, np.diff(stamps).max()
    # the target, judged by the physics truth once the task ended
    sc = load_scenario("arm")
    stamp, ok = obs.results["task-1"]
    assert ok and np.abs(obs.truth_at(stamp) - np.asarray(LEFT)).max() <= sc.task.tolerance + 0.002
    # no process is left: the first ones, and the restarted ones
    assert wait_until(lambda: not any(psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
                                      for pid in pids), 10), pids


@pytest.mark.serial  # wall-clock timing: failed two tests at a time
@pytest.mark.e2e
def test_in_realtime_restarted_sensors_and_controller_just_rejoin(tmp_path: Path) -> None:
    """Realtime (the lean arm): the wall clock does not wait. The sensors, then the controller,
    are SIGKILLed while the arm moves; while either is gone physics gives the simulated joints no
    torque instead of the last command (a drive's watchdog: held, it throws the arm about), each
    restarted one rejoins (the controller with the trajectory being executed), and the target is
    reached in the truth. (Without torque the arm coasts: near the table it may touch it.)"""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    p = up(LEAN, "--router", ep, "--clock", "realtime", "--no-logger", "--out", str(tmp_path / "run"),
           "--set", f"task.targets=[{LEFT}]", "--set", "restart.services.default=on-failure")
    out = Output(p)
    killed: dict[str, int] = {}
    try:
        ready = out.wait(r"^ready: (.*)$", 120)[1]
        now = {n: int(pid) for n, pid in re.findall(r"(\w+) \(pid (\d+)\)", ready)}
        # while the arm moves towards the target
        assert wait_until(lambda: bool(obs.truth) and obs.truth[-1][1][0] > 0.1, 60), out.text()
        for name in ("sensors", "controller"):
            psutil.Process(now[name]).send_signal(signal.SIGKILL)
            killed[name] = sim_now(obs)
            out.wait(rf"^  {name} is back \(pid (\d+)\)", 60)
        ended(p, out, 180)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        obs.close()
        router.close()
    text = out.text()
    assert p.returncode == 0 and "targets reached: 1/1" in text, text
    # sim time went on meanwhile (realtime), and each restart is reported with the time it happened
    for name, t_kill in killed.items():
        m = re.search(rf"^  restarted {name} \(exit code -9 at sim time ([\d.]+) s; back after", text, re.M)
        assert m and abs(float(m[1]) * 1e9 - t_kill) < 0.3e9, (text, killed)
    assert "paused" not in text, text
    stamp, ok = obs.results["task-1"]
    sc = load_scenario(LEAN)
    assert ok and np.abs(obs.truth_at(stamp) - np.asarray(LEFT)).max() <= sc.task.tolerance + 0.002


def test_restart_policy_is_checked_in_one_line() -> None:
    def err(*sets: str) -> str:
        with pytest.raises(ConfigError) as e:
            load_scenario("arm", parse_overrides(sets))
        assert "\n" not in str(e.value)
        return str(e.value)

    assert "restart.services: Value error, unknown service 'controler'" in err("restart.services.controler=on-failure")
    assert "physics cannot be restarted" in err("restart.services.physics=on-failure")
    assert "restart.services.default: Input should be 'no' or 'on-failure'" in err("restart.services.default=always")
    assert "restart.max_attempts" in err("restart.max_attempts=0")
    sc = load_scenario("arm", parse_overrides(["restart.services.default=on-failure", "restart.services.planner=no"]))
    # YAML's bare `no` is False: read as the policy "no"; physics is never restarted
    assert [sc.restart.policy(s) for s in ("controller", "planner", "physics")] == ["on-failure", "no", "no"]
    assert load_scenario("arm").restart.policy("controller") == "no"  # the default: no restart
    # a composed process (hilsim.launch.compose) is restarted only if each of its services may be
    assert sc.restart.policy("sensors+controller") == "on-failure"
    assert sc.restart.policy("physics+sensors") == "no" and sc.restart.policy("controller+planner") == "no"


def test_restarts_are_bounded_and_a_clean_exit_is_not_restarted(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The launcher's bookkeeping alone, with processes that exit at once instead of services:
    on-failure restarts a failing one max_attempts times, then the run ends on it; exit code 0
    (a service that finished) and a service without the policy are never restarted."""
    from hilsim.launch.launcher import Child, Launcher

    sc = load_scenario("arm", parse_overrides(["restart.services.controller=on-failure", "restart.max_attempts=2",
                                               "restart.backoff=0.01"]))
    la = Launcher(sc, tmp_path)
    spawned: list[tuple[str, int]] = []

    def spawn(name: str, attempt: int) -> subprocess.Popen[bytes]:
        spawned.append((name, attempt))
        return subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])

    monkeypatch.setattr(la, "_spawn", spawn)
    la.children["controller"] = Child("controller", spawn("controller", 0), tmp_path / "controller.log")
    deadline = time.monotonic() + 30
    while not la.check_children():
        assert time.monotonic() < deadline, spawned
        time.sleep(0.01)
    assert spawned == [("controller", 0), ("controller", 1), ("controller", 2)]
    assert la.outcome.died == [("controller", 3)] and len(la.outcome.restarts) == 2
    assert "died 3 times; restart.max_attempts (2) used up" in capsys.readouterr().out
    # a clean exit, and a service without the policy: the run ends on them, nothing restarted
    for name, code in (("controller", 0), ("sensors", 3)):
        la = Launcher(sc, tmp_path)
        monkeypatch.setattr(la, "_spawn", spawn)
        spawned.clear()
        la.children[name] = Child(name, subprocess.Popen([sys.executable, "-c", f"raise SystemExit({code})"]),
                                  tmp_path / f"{name}.log")
        assert wait_until(la.check_children, 30) and spawned == [] and la.outcome.died == [(name, code)]


def test_a_restarted_controller_takes_over_the_live_gains(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hilsim.services.controller import ControllerService

    sc = load_scenario("arm", {"logger.run_dir": str(tmp_path)})
    first = ControllerService(sc)
    res = first.on_set_parameters(msgs.SetParameters(parameters=[msgs.Parameter(name="joint_2.kp", value=123.0)]))
    assert res.successful
    # a fresh run does not inherit them (the scenario's gains, whatever config/arm.yaml holds)…
    fresh = ControllerService(sc)
    assert fresh.pids[1].kp != 123.0
    # …a restarted process does, on top of the scenario's gains
    monkeypatch.setenv(RESTART_ENV, "1")
    again = ControllerService(sc)
    assert again.pids[1].kp == 123.0 and again.pids[1].kd == fresh.pids[1].kd
    assert again.pids[0].kp == fresh.pids[0].kp


def test_a_restarted_planner_resumes_the_task_where_it_was(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hilsim.services.planner import PlannerService

    right = [-0.866, -0.789, -0.399, 0.0, -0.382, 0.0]
    sc = load_scenario("arm", {"logger.run_dir": str(tmp_path), "task.targets": [LEFT, right, LEFT]})
    keep(sc, "planner", {"task": {"index": 1, "reached": 1}})
    monkeypatch.setenv(RESTART_ENV, "1")
    planner = PlannerService(sc)
    submitted: list[str] = []
    planner.task_runner.submit = lambda tg: submitted.append(tg.goal_id)
    planner.task_runner.on_tick()
    assert submitted == ["task-2"] and planner.task_runner.reached == 1
