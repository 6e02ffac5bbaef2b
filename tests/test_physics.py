"""Physics service alone: lockstep waits for every participant; bad commands are rejected."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import zenoh

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.services.physics import PhysicsService
from hilsim.sim.world import World


def test_world_holds_still_with_gravity_compensation(scenario: Any) -> None:
    w = World(scenario("arm"))
    for _ in range(500):
        w.step()
    assert abs(w.positions()).max() < 1e-9
    assert w.joint_names == [f"joint_{i}" for i in range(1, 7)]
    assert list(w.effort_limit) == [12, 15, 12, 5, 4, 3]


def test_motor_inputs_are_clipped_and_never_push_past_the_velocity_limit(scenario: Any) -> None:
    """apply_commands (the lean path of an all-effort arm) gives what the limits say, joint by joint:
    effort clipped to the actuator's range; no torque that pushes a joint faster past its velocity
    limit (2 rad/s from the URDF), while a torque that brakes it is kept."""
    w = World(scenario("arm"))
    lim, vlim = w.effort_limit.tolist(), w.velocity_limit.tolist()
    assert vlim == [2.0] * 6
    w.data.qvel[w.dof_adr] = [0.5, 2.5, -2.5, 2.5, -0.5, 0.0]
    w.command_array(np.array([100.0, 1.0, -1.0, -1.0, -100.0, 2.0]))
    w.apply_commands()
    assert w.data.ctrl[:6].tolist() == [lim[0], 0.0, 0.0, -1.0, -lim[4], 2.0]
    # and the same as the general path (any joint not a simulated effort joint) computes
    w._all_effort = False
    w.data.ctrl[:] = 0.0
    w.apply_commands()
    assert w.data.ctrl[:6].tolist() == [lim[0], 0.0, 0.0, -1.0, -lim[4], 2.0]


def test_lockstep_waits_for_every_participant(scenario: Any, session: zenoh.Session, run_service: Any) -> None:
    sc = scenario("arm", {"services": ["physics", "sensors", "controller", "planner"], "clock.ack_timeout": 1.0})
    keys = Keys.of(sc)
    clocks: list[int] = []
    got = threading.Event()

    def on_clock(s: zenoh.Sample) -> None:
        clocks.append(msgs.ns_of(msgs.decode(msgs.Clock, s.payload.to_bytes()).clock))
        got.set()

    sub = session.declare_subscriber(keys.clock, on_clock)
    sync = transport.publisher(session, keys.sync("planner"))
    cmd = transport.publisher(session, keys.topic("joint_commands"))
    # the test plays the planner and the controller: it announces them as participants, with
    # the writer ids its acknowledgements carry
    gid_sync, gid_cmd = transport.new_gid(), transport.new_gid()
    seq = iter(range(1, 1000))

    def put(pub: Any, msg: Any, gid: bytes) -> None:
        pub.put(msgs.encode(msg), attachment=transport.attachment_bytes(next(seq), gid))

    tokens = [session.liveliness().declare_token(keys.lockstep("planner", 1, 0, "sync", gid_sync.hex())),
              session.liveliness().declare_token(keys.lockstep("controller", 1, 0, "joint_commands", gid_cmd.hex()))]
    tokens += [session.liveliness().declare_token(keys.alive(n)) for n in ("planner", "controller", "sensors")]
    svc = PhysicsService(sc)
    with run_service(svc):
        assert got.wait(10), "physics never published step 0"
        time.sleep(0.3)
        assert clocks == [0], "physics stepped without acknowledgements"
        # only the controller answers: still waiting for the planner
        names = [f"joint_{i}" for i in range(1, 7)]
        put(cmd, msgs.JointState(header=msgs.header(0), name=names, effort=[0.0] * 6), gid_cmd)
        time.sleep(0.3)
        assert clocks == [0]
        # an acknowledgement from a writer other than the one that announced itself does not count
        put(sync, msgs.Clock(clock=msgs.stamp(0)), transport.new_gid())
        time.sleep(0.3)
        assert clocks == [0]
        for k in range(5):
            got.clear()
            put(sync, msgs.Clock(clock=msgs.stamp(k * sc.dt_ns)), gid_sync)
            if k:
                put(cmd, msgs.JointState(header=msgs.header(k * sc.dt_ns), name=names, effort=[0.5] * 6), gid_cmd)
            assert got.wait(5)
            time.sleep(0.05)
        assert clocks == [k * sc.dt_ns for k in range(6)]
        # a joint_commands sample from someone else moves nothing forward
        got.clear()
        put(sync, msgs.Clock(clock=msgs.stamp(5 * sc.dt_ns)), gid_sync)
        put(cmd, msgs.JointState(header=msgs.header(5 * sc.dt_ns), name=names, effort=[0.5] * 6), transport.new_gid())
        time.sleep(0.3)
        assert clocks[-1] == 5 * sc.dt_ns
        # the commanded effort moved the arm
        assert svc.world.velocities()[0] > 0
        # malformed commands: rejected and counted, no step taken, still serving
        now = msgs.header(5 * sc.dt_ns)  # the current step: each is refused for its own fault
        cmd.put(b"\x00\x01\x00\x00garbage")
        cmd.put(msgs.encode(msgs.JointState(header=now, name=["joint_9"], effort=[1.0])))
        cmd.put(msgs.encode(msgs.JointState(header=now, name=names[:3], position=[1.0] * 3)))
        cmd.put(msgs.encode(msgs.JointState(header=now, name=names, effort=[float("nan")] * 6)))
        # well-formed, but for a step that is not the current one: stale, refused
        cmd.put(msgs.encode(msgs.JointState(header=msgs.header(3 * sc.dt_ns), name=names, effort=[0.0] * 6)))
        # beyond joint_1's effort limit: applied at the limit, and counted
        cmd.put(msgs.encode(msgs.JointState(header=now, name=names, effort=[99.0, 0, 0, 0, 0, 0])))
        time.sleep(0.5)
        assert sum(svc.rejected.values()) == 6, svc.rejected  # 5 above + the impostor acknowledgement
        assert svc.world.clipped == 1 and svc.health_values()["clipped_commands"] == 1
        assert clocks[-1] == 5 * sc.dt_ns
        # a silent participant is reported as a fault, not a hang
        time.sleep(1.5)
        assert svc.errors >= 1 and "no lockstep acknowledgement" in svc.last_error
    sub.undeclare()
    for t in tokens:
        t.undeclare()


class PlannerLagRig:
    """The test plays the controller, which answers every step at once, and the planner, acknowledging
    every 4th step, waited for 3 steps later: only the planner holds physics back (:meth:`ack`)."""

    def __init__(self, sc: Any, session: zenoh.Session) -> None:
        self.sc, self.keys = sc, Keys.of(sc)
        names = [f"joint_{i}" for i in range(1, 7)]
        gid_sync, gid_cmd = transport.new_gid(), transport.new_gid()
        self.gid_sync = gid_sync
        self.sync = transport.publisher(session, self.keys.sync("planner"))
        cmd = transport.publisher(session, self.keys.topic("joint_commands"))
        self.seq = iter(range(1, 100000))
        self.clocks: list[int] = []
        self.lock = threading.Lock()

        def on_clock(s: zenoh.Sample) -> None:
            t = msgs.ns_of(msgs.decode(msgs.Clock, s.payload.to_bytes()).clock)
            with self.lock:
                self.clocks.append(t)
                cmd.put(msgs.encode(msgs.JointState(header=msgs.header(t), name=names, effort=[0.0] * 6)),
                        attachment=transport.attachment_bytes(next(self.seq), gid_cmd))

        self.sub = session.declare_subscriber(self.keys.clock, on_clock)
        live = session.liveliness()
        self.tokens = [live.declare_token(self.keys.lockstep("planner", 4, 3, "sync", gid_sync.hex())),
                       live.declare_token(self.keys.lockstep("controller", 1, 0, "joint_commands", gid_cmd.hex()))]
        self.tokens += [live.declare_token(self.keys.alive(n)) for n in ("planner", "controller", "sensors")]

    def ack(self, step: int) -> None:
        self.sync.put(msgs.encode(msgs.Clock(clock=msgs.stamp(step * self.sc.dt_ns))),
                      attachment=transport.attachment_bytes(next(self.seq), self.gid_sync))

    def steps(self) -> list[int]:
        with self.lock:
            return [t // self.sc.dt_ns for t in self.clocks]

    def close(self) -> None:
        self.sub.undeclare()
        for t in self.tokens:
            t.undeclare()


def test_a_lagging_participant_is_waited_for_lag_steps_later(scenario: Any, session: zenoh.Session,
                                                             run_service: Any) -> None:
    """A participant announced with a lag (the planner: its trajectories act later, at a stamp of
    their own) is waited for ``lag`` steps after the step it owes, not at it; physics stops
    there until the acknowledgement comes, and never runs further ahead."""
    sc = scenario("arm", {"services": ["physics", "sensors", "controller", "planner"], "clock.ack_timeout": 5.0})
    rig = PlannerLagRig(sc, session)

    def steps_after(wait: float) -> list[int]:
        time.sleep(wait)
        return rig.steps()

    with run_service(PhysicsService(sc)):
        # tick 0 unanswered: steps 1, 2, 3 still come (the planner may be busy with tick 0), not 4
        assert steps_after(1.0) == [0, 1, 2, 3]
        rig.ack(0)
        # ticks 4 owed from step 7 on
        assert steps_after(0.5) == list(range(8))
        rig.ack(4)
        rig.ack(8)  # early: an acknowledgement of a later tick covers the earlier ones too
        assert steps_after(0.5) == list(range(16))
    rig.close()


def test_realtime_paces_to_the_wall_clock(tmp_path: Any) -> None:
    """Physics alone in realtime, in its own process (it may take SCHED_FIFO there, never in the
    test process): 500 steps of 1 ms take half a second of wall time, each tick measured."""
    import re
    import subprocess
    import sys

    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", "--clock", "realtime", "--duration", "0.5",
                        "--set", "services=[physics]", "--set", "task.targets=[]", "--out", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=120)
    wall = time.monotonic() - t0
    assert r.returncode == 0, r.stdout + r.stderr
    log = (tmp_path / "run" / "physics.log").read_text()
    m = re.search(r"realtime tick jitter: p50 (\d+) µs, p99 (\d+) µs, overruns (\d+) of (\d+) steps", log)
    assert m and int(m[4]) == 500, log  # every tick measured
    assert "reached the end of the scenario duration (0.500 s sim)" in log, log
    rtf = float(r.stdout.split("real-time factor ")[-1].split(",")[0])
    assert 0.9 <= rtf <= 1.05 and wall >= 0.5, r.stdout  # paced, not as fast as it can


def test_bad_model_is_one_line_and_exit_code_2(tmp_path: Any) -> None:
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parent.parent
    cfg = tmp_path / "s.yaml"
    text = (repo / "config" / "arm.yaml").read_text().replace("../models", str(repo / "models"))
    cfg.write_text(text.replace("truth_imu_site: tool", "truth_imu_site: nowhere"))
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "run", "physics", "--config", str(cfg),
                        "--set", "zenoh.connect=[]"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if "ERROR" in ln]
    assert len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
    assert str(cfg) in errors[0] and "physics.truth_imu_site" in errors[0] and "nowhere" in errors[0]


def test_position_actuators_track_a_commanded_position(scenario: Any) -> None:
    w = World(scenario("arm", {"joints.default.interface": "position"}))
    names = w.joint_names
    target = [0.3, -0.2, 0.1, 0.0, 0.2, 0.0]
    w.command(msgs.JointState(name=names, position=target))
    for _ in range(3000):
        w.step()
    assert abs(w.positions() - target).max() < 0.01
    # the effort limit still holds in position mode
    assert (abs(w.data.actuator_force) <= w.effort_limit + 1e-9).all()


def test_a_touch_is_published_on_truth_contacts(scenario: Any) -> None:
    """The arm end-to-end test's "nothing touched" is only worth something if physics publishes a
    touch when there is one: the arm bent down into the obstacle is on ``truth/contacts`` (its
    link and the obstacle's geom, penetration > 0), and the contact ending is published too."""
    import mujoco

    from hilsim.core.inproc import Bus

    sc = scenario("arm", {"clock.mode": "lockstep", "task.targets": []})
    bus = Bus()
    got: list[msgs.Contacts] = []
    ses = bus.session()
    ses.declare_subscriber(Keys.of(sc).truth("contacts"),
                           lambda s: got.append(msgs.decode(msgs.Contacts, s.payload.to_bytes())))
    phys = PhysicsService(sc)
    phys.attach(bus.session())
    w = phys.robots[0].world
    with phys.lock:
        phys._advance()  # step 0: nothing touches
        w.data.qpos[w.qpos_adr] = [0.0, -1.5, 0.0, 0.0, 0.0, 0.0]  # shoulder down: the elbow in the obstacle
        mujoco.mj_forward(w.model, w.data)
        phys._advance()
        w.data.qpos[w.qpos_adr] = [0.0] * 6
        w.data.qvel[:] = 0.0
        mujoco.mj_forward(w.model, w.data)
        phys._advance()
    bus.drain()
    phys.request_stop()
    phys.teardown()
    assert len(got) == 3 and got[0].contacts == [] and got[-1].contacts == [], got
    touch = got[1].contacts
    assert touch and all("world" in (c.body1, c.body2) for c in touch), touch  # the arm against the scene
    assert any("elbow_link" in (c.body1, c.body2) and "obstacle" in (c.geom1, c.geom2) for c in touch), touch
    assert max(c.depth for c in touch) > 0, touch


def test_a_task_result_is_taken_while_the_stepping_holds_the_lock(scenario: Any, session: zenoh.Session,
                                                                  run_service: Any) -> None:
    """Lockstep with a task: sim time stops TASK_END_MARGIN_NS after the task's result, on the same step
    in every run. Zenoh calls each subscription's handler on a thread of its own, so the result's handler
    must not wait for the lock the acknowledgements' handler holds while it steps (in CI it once waited
    200 steps, past the end it sets, and two same-seed runs ended 0.1 s apart): it is taken with the lock
    held, and the run ends exactly on its step."""
    from hilsim.services.physics_lockstep import TASK_END_MARGIN_NS

    sc = scenario("arm", {"services": ["physics", "sensors", "controller", "planner"], "clock.ack_timeout": 5.0})
    assert sc.task.targets
    rig, keys, dt = PlannerLagRig(sc, session), Keys.of(sc), sc.dt_ns
    result = transport.publisher(session, keys.topic("task/result"))

    def wait_steps(n: int) -> None:
        deadline = time.monotonic() + 10
        while len(rig.steps()) < n and time.monotonic() < deadline:
            time.sleep(0.01)

    svc = PhysicsService(sc)
    with run_service(svc):
        wait_steps(4)  # tick 0 unanswered: steps 1-3 come
        rig.ack(0)
        wait_steps(8)
        assert rig.steps() == list(range(8))
        with svc.lock:  # as the stepping holds it
            result.put(msgs.encode(msgs.MoveResult(header=msgs.header(2 * dt), goal_id="task", success=True)),
                       attachment=transport.attachment_bytes(next(rig.seq), transport.new_gid()))
            deadline = time.monotonic() + 5
            while not svc.task_results and time.monotonic() < deadline:
                time.sleep(0.01)
            assert list(svc.task_results) == [(keys.topic("task/result"), 2 * dt)]
        end = -(-(2 * dt + TASK_END_MARGIN_NS) // dt) * dt
        rig.ack(end // dt + 100)  # far ahead: only the task's end stops it
        deadline = time.monotonic() + 20
        while (rig.steps() or [0])[-1] * dt < end and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        assert rig.steps()[-1] * dt == end and svc.ended_by == "the task", (rig.steps()[-3:], end, svc.ended_by)
    rig.close()
