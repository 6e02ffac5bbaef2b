"""Robots as arrays (``fleet.arrays``, hilsim.core.fleet): every robot's encoders and PID in one numpy step,
one fleet-wide sample per step between physics, sensors and controller, the per-robot keys still there."""

from __future__ import annotations

import itertools
import json
import os
import threading
from pathlib import Path

import numpy as np
import pytest
from test_scale import LEFT, OVER, _close_truth, _truth_of
from util import REPO, finish, up

from hilsim.core import msgs, transport
from hilsim.core.config import PidGains
from hilsim.core.keys import Keys
from hilsim.core.recording import contents
from hilsim.sim import control

ROBOTS = ["arm0", "arm1", "arm2"]


class _Member:
    """What FleetControllerService reads of a robot's controller: its PIDs, effort joints, gains version."""

    def __init__(self, pids: list[control.Pid], effort: list[bool]) -> None:
        self.pids, self.effort_joint, self.gains_version = pids, effort, 0


def _driver(members: list[_Member], dt: float) -> object:
    from hilsim.services.controller import FleetControllerService

    d = object.__new__(FleetControllerService)  # the PID arrays alone: no session, no scenario needed
    d.members, d.n_robots, d.n, d.dt = members, len(members), len(members[0].pids), dt
    d.effort = np.array([m.effort_joint for m in members], bool)
    d.integral = np.zeros((d.n_robots, d.n))
    d._gains()
    return d


def test_the_pid_as_arrays_is_the_scalar_pid_bit_for_bit() -> None:
    """Every branch of Pid.update (integral clamp, conditional integration at both limits, ki = 0, an
    infinite i_limit, a position joint's 0, live gain changes) over many random steps: the arrays give
    the very floats the per-joint PIDs give."""
    rng = np.random.default_rng(3)
    n_robots, n, dt = 4, 6, 1e-3
    gains = [PidGains(kp=100.0, ki=5.0, kd=5.0, i_limit=2.0), PidGains(kp=32.8, ki=0.0, kd=5.6, i_limit=1.5),
             PidGains(kp=85.3, ki=0.3159, kd=2.171, i_limit=float("inf"), feedforward=0.7),
             PidGains(kp=5.9, ki=0.0064, kd=0.41, i_limit=0.4, output_limit=1.0),
             PidGains(kp=5.2, ki=40.0, kd=0.75, i_limit=0.3), PidGains(kp=7.8, ki=0.0076, kd=0.86, i_limit=1.2)]
    scalar = [[control.Pid(gains[(j + k) % n], -3.0, 3.0) for j in range(n)] for k in range(n_robots)]
    effort = [[not (k == 2 and j == 4) for j in range(n)] for k in range(n_robots)]  # one position joint
    members = [_Member([control.Pid(gains[(j + k) % n], -3.0, 3.0) for j in range(n)], effort[k])
               for k in range(n_robots)]
    d = _driver(members, dt)
    saturated = clamped = 0
    for step in range(3000):
        if step == 1500:  # a live change: both sides as ControllerService.on_set_parameters does it
            assert scalar[1][1].integral != 0.0 and abs(scalar[3][1].integral) > 0.05 / 40.0  # a change bites
            for pid in (scalar[1][1], members[1].pids[1]):  # ki 0.3159 -> 0: its integral goes
                pid.set("ki", 0.0)
            for pid in (scalar[3][1], members[3].pids[1]):  # ki 40, i_limit 0.3 -> 0.05: clamped at once
                pid.set("i_limit", 0.05)
            members[1].gains_version += 1
            members[3].gains_version += 1
        # small errors, then a steady one (the integral winds up to its i_limit), then large ones that saturate
        phase = step % 600
        scale = 0.05 if phase < 400 else 2.0
        ref_pos, pos = rng.normal(0, scale, (n_robots, n)), rng.normal(0, scale, (n_robots, n))
        if 200 <= phase < 400:
            ref_pos = pos + 0.05 * (1 if step % 1200 < 600 else -1)
        ref_vel, vel = rng.normal(0, 1, (n_robots, n)), rng.normal(0, 1, (n_robots, n))
        want = [[scalar[k][j].update(ref_pos[k, j], ref_vel[k, j], pos[k, j], vel[k, j], dt) if effort[k][j] else 0.0
                 for j in range(n)] for k in range(n_robots)]
        if [m.gains_version for m in members] != d._versions:
            d._gains()
        got = d.pid(ref_pos, ref_vel, pos, vel)
        assert got.tolist() == want, step
        saturated += int(np.sum(np.abs(got) == 3.0))
        clamped += sum(p.ki > 0 and abs(p.integral) == p.i_limit / p.ki for pids in scalar for p in pids)
    assert saturated > 100  # the limits, and so the conditional integration, were exercised
    assert clamped > 100  # and the integral's clamp
    assert d.integral.tolist() == [[p.integral for p in pids] for pids in scalar]


def _run(tmp: Path, name: str, *extra: str, robots: list[str] = ROBOTS,
         fleet_commands: bool = True) -> dict[str, dict[int, list[float]]]:
    """One lockstep run of len(robots) arms, 1 s, seed 7: every robot's physics truth by stamp; and
    whether the fleet command (the arrays' path) carried the steps (``fleet_commands``) or not."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    ses, subs, truth = _truth_of(ep, robots)
    fleet = []
    subs.append(ses.declare_subscriber(Keys("hilsim", "arm").fleet("joint_commands"), lambda s: fleet.append(1)))
    # the last robot's own joint_commands, read by nobody (no recorder; physics takes the fleet's) until a
    # plain subscriber joins mid-run: from then on they are put (lever 1), from the same values
    late: list[int] = []
    joined = threading.Event()
    last = robots[-1]

    def join() -> None:
        while len(truth[last]) < 100 and not joined.wait(0.02):
            pass
        if not joined.is_set():
            subs.append(ses.declare_subscriber(Keys("hilsim", last).topic("joint_commands"), lambda s: late.append(
                msgs.ns_of(msgs.decode(msgs.JointState, s.payload.to_bytes()).header.stamp))))
            joined.set()

    joiner = threading.Thread(target=join)
    joiner.start()
    try:
        out = finish(up("arm", "--router", ep, "--set", f"robots={len(robots)}", "--set", f"task.targets=[{LEFT}]",
                        "--duration", "1.0", "--seed", "7", "--no-logger", "--out", str(tmp / name), *extra), 240)
    finally:
        joined.set()
        joiner.join()
        _close_truth(ses, subs)
        router.close()
    assert "result: STOPPED (duration)" in out, out
    assert len(fleet) >= 990 if fleet_commands else not fleet, (name, len(fleet))
    # how many depends on when this test's lagging view let it join; that they run on, step after step, to
    # the end does not
    assert len(late) >= 20 and late[0] >= 0.05e9 and late[-1] >= 0.99e9, (name, len(late), late[:3], late[-1:])
    assert all(b - a == 1_000_000 for a, b in itertools.pairwise(late)), (name, late)
    return {r: {t: q for t, _, q in truth[r]} for r in robots}


def _same(a: dict[str, dict[int, list[float]]], b: dict[str, dict[int, list[float]]], steps: int = 990) -> None:
    for r in a:
        common = sorted(set(a[r]) & set(b[r]))
        assert len(common) >= steps, (r, len(common))
        assert [a[r][t] for t in common] == [b[r][t] for t in common], r
        first, last = a[r][common[0]], a[r][common[-1]]
        assert max(abs(x - y) for x, y in zip(first, last, strict=True)) > 0.01, (r, first, last)  # it moved


# lag 1 (as shipped) is proven bit for bit across composition by test_e2e.test_lockstep_runs_are_bit_identical
@pytest.mark.parametrize("lag", [0])
def test_arrays_give_the_per_robot_paths_truth_bit_for_bit_distributed_and_composed(tmp_path: Path, lag: int) -> None:
    """Three arms, one seed, clock.controller_lag 1 (as shipped) and 0: with fleet.arrays the physics truth
    of every arm is the per-robot path's (arrays off), value for value, whether the services run apart
    or physics, sensors and controllers share one process."""
    lag_set = ("--set", f"clock.controller_lag={lag}")
    compose = ("--compose", "physics,sensors,controller")
    off = _run(tmp_path, "off", *lag_set, "--set", "fleet.arrays=false", fleet_commands=False)
    on = _run(tmp_path, "on", *lag_set, "--set", "fleet.arrays=true")
    _same(off, on)
    _same(on, _run(tmp_path, "on-composed", *lag_set, "--set", "fleet.arrays=true", *compose))


# batch 256 as shipped; samples without batches are recorded the same (test_batch)
@pytest.mark.parametrize("batch", [256])
def test_arrays_move_every_arm_to_its_target_and_keep_the_per_robot_keys(tmp_path: Path, batch: int) -> None:
    """Three arms as real processes, fleet.arrays on, each with a target of its own: judged by the physics
    truth; a plain subscriber that turns up mid-run on arm2's joint_states gets its samples (lever 1 turns
    the robot's own key on for it); the recorder has every robot's keys and the fleet's, every sample
    published (and, with ``logger.batch``, taken from the services' batches: every robot's key is still
    built for it)."""
    scen = tmp_path / "three-arms.yaml"
    scen.write_text(
        f"extends: [{REPO / 'config' / 'arm.yaml'}]\n"
        "robots: 3\n"
        "fleet: {arrays: true}\n"
        f"logger: {{batch: {batch}}}\n"
        "planner: {planning_time: 0.3}\n"
        f"task: {{targets: [{LEFT}]}}\n"
        f"robot_overrides: {{arm1: {{task.targets: [{OVER}]}}}}\n")
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    ses, subs, truth = _truth_of(ep, ROBOTS)
    late: list[int] = []

    def subscribe_late() -> None:  # once arm2 has run 0.3 s of sim time, as a ROS 2 node would join
        while len(truth["arm2"]) < 300 and not stop.wait(0.05):
            pass
        if not stop.is_set():
            subs.append(ses.declare_subscriber(Keys("hilsim", "arm2").topic("joint_states"),
                                               lambda s: late.append(msgs.ns_of(
                                                   msgs.decode(msgs.JointState, s.payload.to_bytes()).header.stamp))))

    stop = threading.Event()
    joiner = threading.Thread(target=subscribe_late)
    joiner.start()
    try:
        out = finish(up(str(scen), "--router", ep, "--out", str(tmp_path / "run")), 240)
    finally:
        stop.set()
        joiner.join()
        _close_truth(ses, subs)
        router.close()
    assert "result: OK" in out, out
    final = {}
    for r, target in (("arm0", LEFT), ("arm1", OVER), ("arm2", LEFT)):
        _stamp, names, q = max(truth[r])
        assert names == [f"joint_{i}" for i in range(1, 7)]
        assert np.abs(np.array(q) - target).max() < 0.01, (r, q, target)
        final[r] = np.array(q)
    assert np.abs(final["arm1"] - np.array(LEFT)).max() > 0.5  # arm1 went elsewhere
    # the late subscriber: arm2's encoders at 1 kHz from when it joined to the end, in order
    assert len(late) > 500 and late == sorted(late) and late[0] >= 0.3e9, (len(late), late[:3])
    counts = json.loads((tmp_path / "run" / "record_summary.json").read_text())
    fleet = Keys("hilsim", "arm")
    steps = counts[fleet.fleet("joint_states")]["recorded"]
    for topic in ("truth/joint_states", "joint_states", "joint_commands", "controller/reference"):
        assert counts.get(fleet.fleet(topic), {}).get("recorded", 0) == steps > 1000, topic
    for key, c in counts.items():
        assert c["received"] == c["recorded"] == c["bagged"] and c["lost"] == 0, (key, c)
    # the planners' ticks: every 10th step's fleet sample
    assert counts[fleet.fleet("joint_states_throttle")]["recorded"] == (steps - 1) // 10 + 1
    for r in ROBOTS:
        k = Keys("hilsim", r)
        recorded = {t: counts.get(k.topic(t), {}).get("recorded", 0)
                    for t in ("truth/joint_states", "joint_states", "joint_commands", "controller/reference")}
        if not batch:  # the recorder subscribes every key: the robot's own are built and put for it
            assert all(n == steps for n in recorded.values()), (r, recorded)
        else:  # batches: the fleet samples carry these values; a robot's own keys are built only for a
            # subscriber: its truth for this test's judge, arm2's joint_states from when the late one joined
            assert recorded["truth/joint_states"] == steps, (r, recorded)
            assert recorded["joint_commands"] == recorded["controller/reference"] == 0, (r, recorded)
            if r == "arm2":
                assert 500 < recorded["joint_states"] < steps, recorded
            else:
                assert recorded["joint_states"] == 0, (r, recorded)
    # either way every robot's joints are in the recording, robot by robot, every step
    rows = contents(tmp_path / "run").rows
    for r in ROBOTS:
        for source, q in (("truth", "position"), ("measured", "position"), ("command", "effort"),
                          ("reference", "position"), ("reference", "velocity")):
            assert rows.get(f"/robots/{r}/joints/joint_3/{q}/{source}") == steps, (r, source)


def test_each_robots_controller_run_alone_keeps_the_per_robot_path(tmp_path: Path) -> None:
    """fleet.arrays on, but every robot's controller runs as a process of its own (``hilsim run
    controller@arm0``, as on robots' own computers): no fleet controller, so physics takes each robot's
    joint_commands and waits for each controller; the sensors still run as arrays. The truth is the
    all-arrays run's, bit for bit."""
    import subprocess
    import sys

    robots = ROBOTS[:2]
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    ses, subs, truth = _truth_of(ep, robots)
    fleet: list[int] = []
    subs.append(ses.declare_subscriber(Keys("hilsim", "arm").fleet("joint_commands"), lambda s: fleet.append(1)))
    common = ("--set", "robots=2", "--set", f"task.targets=[{LEFT}]", "--set", "seed=7", "--set", "duration=0.5",
              "--set", f"zenoh.connect=[{ep}]")
    ctrls = [subprocess.Popen([sys.executable, "-m", "hilsim.cli", "run", f"controller@{r}", "--config", "arm",
                               *common], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True) for r in robots]
    try:
        out = finish(up("arm", "--router", ep, "--set", "robots=2", "--set", f"task.targets=[{LEFT}]",
                        "--duration", "0.5", "--seed", "7", "--no-logger", "--out", str(tmp_path / "alone"),
                        "--only", "physics,sensors@*,planner@*"), 240)
    finally:
        for p in ctrls:
            p.terminate()
        for p in ctrls:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        _close_truth(ses, subs)
        router.close()
    assert "result: STOPPED (duration)" in out, out
    assert not fleet, len(fleet)  # no fleet command: each controller's own carried the steps
    alone = {r: {t: q for t, _, q in truth[r]} for r in robots}
    _same(alone, _run(tmp_path, "arrays", robots=robots), 490)  # this run of 0.5 s, that of 1 s


def test_a_fleet_process_killed_mid_run_is_restarted_and_every_arm_arrives(tmp_path: Path) -> None:
    """fleet.arrays, two arms, restart on-failure: controller@* (whose fleet driver is the one lockstep
    participant acknowledging every arm's steps) and then sensors@* are SIGKILLed while the arms move;
    each comes back, sim time waits for it and goes on, and every arm reaches its target."""
    import re
    import signal

    import psutil
    from test_restart import Output, ended
    from util import wait_until

    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    ses, subs, truth = _truth_of(ep, ROBOTS[:2])
    p = up("arm", "--router", ep, "--no-logger", "--out", str(tmp_path / "run"), "--set", "robots=2",
           "--set", f"task.targets=[{LEFT}]", "--set", "planner.planning_time=0.3",
           "--set", "restart.services.default=on-failure", "--set", "restart.backoff=0.2")
    out = Output(p)
    try:
        ready = out.wait(r"^ready: (.*)$", 120)[1]
        pids = {n: int(pid) for n, pid in re.findall(r"(\w+)@\* \(pid (\d+)\)", ready)}
        at = 0.3e9
        for name in ("controller", "sensors"):
            assert wait_until(lambda t=at: bool(truth["arm1"]) and truth["arm1"][-1][0] >= t, 60), out.text()
            psutil.Process(pids[name]).send_signal(signal.SIGKILL)
            out.wait(rf"^  {name}@\* is back \(pid (\d+)\)", 60)
            at = truth["arm1"][-1][0] + 0.3e9
        text = ended(p, out, 180)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        _close_truth(ses, subs)
        router.close()
    assert p.returncode == 0 and "result: OK" in text, text
    for name in ("controller", "sensors"):
        assert re.search(rf"^  restarted {name}@\* \(exit code -9", text, re.M), text
    for r in ROBOTS[:2]:
        q = max(truth[r])[2]
        assert np.abs(np.array(q) - LEFT).max() < 0.01, (r, q)


def test_robots_the_arrays_cannot_take_together_run_robot_by_robot() -> None:
    """fleet.arrays is decided from the scenario alone, the same in every process: robots with control or
    encoder rates of their own (robot_overrides), or without one encoder each, run on their own keys."""
    from hilsim.core.scenario import array_misfit, fleet_arrays, load_scenario

    assert fleet_arrays(load_scenario("arm", {"robots": 2}))  # the default
    assert not fleet_arrays(load_scenario("arm", {"robots": 2, "fleet.arrays": False}))
    assert not fleet_arrays(load_scenario("arm"))  # one robot: nothing to batch
    slow = {"arm1": {"controller.rate_hz": 500, "sensors.encoders.rate_hz": 500}}
    sc = load_scenario("arm", {"robots": 2, "robot_overrides": slow})
    assert not fleet_arrays(sc) and "rates differ" in str(array_misfit(sc))
    sc = load_scenario("arm", {"robots": 2, "robot_overrides": {"arm0": {"sensors.encoders.enabled": False}}})
    assert not fleet_arrays(sc) and "arm0 has 0 enabled encoder" in str(array_misfit(sc))
