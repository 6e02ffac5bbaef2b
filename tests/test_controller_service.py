"""The controller service in a thread against the test router."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import mujoco
import numpy as np
import pytest
from util import wait_until

from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys
from hilsim.services.controller import ControllerService
from hilsim.services.sensors import SensorService

DT_NS = 1_000_000
NAMES = [f"joint_{i}" for i in range(1, 7)]


def js(k: int, pos: list[float] | None = None, vel: list[float] | None = None) -> msgs.JointState:
    return msgs.JointState(
        header=msgs.header(k * DT_NS), name=NAMES, position=pos or [0.0] * 6, velocity=vel or [0.0] * 6
    )


class Rig:
    """A running controller plus the test's publishers and a queue of its outputs."""

    def __init__(self, svc: ControllerService, session: Any) -> None:
        self.svc = svc
        self.session = session
        self.keys = Keys.of(svc.sc)
        self.cmds: list[msgs.JointState] = []
        self.refs: list[msgs.JointState] = []
        self.health: list[msgs.DiagnosticArray] = []
        self.cv = threading.Condition()
        self._decl = [
            session.declare_subscriber(self.keys.topic("joint_commands"), self._cb(self.cmds, msgs.JointState)),
            session.declare_subscriber(self.keys.topic("controller/reference"), self._cb(self.refs, msgs.JointState)),
            session.declare_subscriber(self.keys.health("controller"), self._cb(self.health, msgs.DiagnosticArray)),
        ]
        self.pub_js = transport.publisher(session, self.keys.topic("joint_states"))
        self.pub_traj = transport.publisher(session, self.keys.topic("joint_trajectory"))
        self._decl += [self.pub_js, self.pub_traj]
        assert wait_until(lambda: self.pub_js.matching_status.matching and self.pub_traj.matching_status.matching)
        # and the service's publishers know of this rig's subscribers: a key nobody subscribes to is not
        # put, so a first step before that news arrived (a loaded machine) would get no answer
        assert wait_until(lambda: svc.cmd_pub.matching and svc.ref_pub.matching)

    def _cb(self, into: list[Any], cls: type) -> Callable[[Any], None]:
        def cb(sample: Any) -> None:
            with self.cv:
                into.append(msgs.decode(cls, sample.payload.to_bytes()))
                self.cv.notify_all()

        return cb

    def step(self, msg: msgs.JointState) -> msgs.JointState:
        """Publish joint_states and wait for the command answering it (the lockstep ack)."""
        n, m = len(self.cmds), len(self.refs)
        self.pub_js.put(msgs.encode(msg))
        with self.cv:
            assert self.cv.wait_for(lambda: len(self.cmds) > n and len(self.refs) > m, 5.0), "no joint_commands"
            return self.cmds[-1]

    def trajectory(self, tr: msgs.JointTrajectory | bytes) -> None:
        """Publish a trajectory and wait until the service has handled it (accepted or rejected)."""
        before = self.svc.counts_in[self.keys.topic("joint_trajectory")]
        self.pub_traj.put(tr if isinstance(tr, bytes) else msgs.encode(tr))
        assert wait_until(lambda: self.svc.counts_in[self.keys.topic("joint_trajectory")] > before)
        with self.svc.lock:  # the handler has finished once the lock is free
            pass

    def set_parameters(self, payload: bytes) -> msgs.SetParametersResult:
        replies = list(self.session.get(self.keys.topic("controller/set_parameters"), payload=payload, timeout=5.0))
        assert len(replies) == 1 and replies[0].ok is not None, replies
        return msgs.decode(msgs.SetParametersResult, replies[0].ok.payload.to_bytes())

    def close(self) -> None:
        for d in self._decl:
            d.undeclare()


@pytest.fixture
def rig(scenario: Callable[..., Any], session: Any, run_service: Callable[[Any], Any]) -> Iterator[Rig]:
    with run_service(ControllerService(scenario())) as svc:
        assert svc.state == "running"
        r = Rig(svc, session)
        try:
            yield r
        finally:
            r.close()


def effort(cmd: msgs.JointState) -> np.ndarray:
    return np.asarray(cmd.effort)


def test_commands_answer_joint_states_with_the_same_stamp(rig: Rig) -> None:
    c = rig.step(js(0, [0.1, -0.2, 0.0, 0.0, 0.0, 0.0]))
    assert msgs.ns_of(c.header.stamp) == 0 and c.name == NAMES and len(c.effort) == 6
    assert np.allclose(effort(c), 0.0)  # holds the first measurement
    c = rig.step(js(1, [0.1, -0.19, 0.0, 0.0, 0.0, 0.0]))
    assert msgs.ns_of(c.header.stamp) == DT_NS
    kp = rig.svc.pids[1].kp
    assert c.effort[1] == pytest.approx(-0.01 * kp, rel=0.01)  # pushed back to the held -0.2
    assert rig.refs[-1].position[1] == pytest.approx(-0.2)
    assert msgs.ns_of(rig.refs[-1].header.stamp) == DT_NS
    # Effort never exceeds the actuator range (joint_6: 3 N*m).
    c = rig.step(js(2, [0.1, -0.2, 0.0, 0.0, 0.0, 2.0]))
    assert c.effort[5] == pytest.approx(-3.0)


def test_reference_follows_a_trajectory(rig: Rig) -> None:
    rig.step(js(0))
    tr = msgs.JointTrajectory(
        header=msgs.header(10 * DT_NS),
        joint_names=["joint_2", "joint_1"],  # reordered subset
        points=[
            msgs.JointTrajectoryPoint(positions=[0.0, 0.0], time_from_start=msgs.duration(0.0)),
            msgs.JointTrajectoryPoint(positions=[0.2, -0.1], time_from_start=msgs.duration(0.02)),
        ],
    )
    rig.trajectory(tr)
    assert rig.svc.rejected[rig.keys.topic("joint_trajectory")] == 0
    for k in range(1, 40):
        rig.step(js(k))
    ref = {msgs.ns_of(r.header.stamp) // DT_NS: r for r in rig.refs}
    assert ref[5].position == pytest.approx([0.0] * 6)  # before the start: hold
    mid = ref[20]  # halfway through the 20 ms segment
    assert mid.position[:2] == pytest.approx([-0.05, 0.1]) and mid.position[2:] == [0.0] * 4
    assert mid.velocity[:2] == pytest.approx([-7.5, 15.0])  # Hermite midpoint: 1.5 x mean speed
    assert ref[39].position[:2] == pytest.approx([-0.1, 0.2]) and ref[39].velocity == [0.0] * 6
    h = {kv.key: kv.value for kv in rig.svc.health().status[0].values}
    assert h["trajectory_active"] == "no" and float(h["trajectory_progress"]) == 1.0
    assert float(h["max_tracking_error"]) == pytest.approx(0.2, abs=1e-6)
    # An empty trajectory holds the measured position (the latest measurement when it arrives).
    rig.step(js(40, [0.05] * 6))
    rig.trajectory(msgs.JointTrajectory(joint_names=NAMES))
    rig.step(js(41, [0.07] * 6))
    assert rig.refs[-1].position == pytest.approx([0.05] * 6)


def to(target: float, start_step: int, seconds: float = 0.02, joint: str = "joint_1") -> msgs.JointTrajectory:
    """joint_1 (alone) to ``target`` in ``seconds``, stamped to start at ``start_step`` (0: now)."""
    return msgs.JointTrajectory(header=msgs.header(start_step * DT_NS), joint_names=[joint], points=[
        msgs.JointTrajectoryPoint(positions=[target], time_from_start=msgs.duration(seconds))])


def test_a_trajectory_is_timed_as_ros2s_joint_trajectory_controller_times_it(rig: Rig) -> None:
    """A future stamp starts then; a newer trajectory replaces what was commanded from its own start (an
    earlier-stamped one is never refused for being earlier, so one far-stamped message cannot lock the
    next out); one that ended before it arrived is refused; stamp zero is now."""
    key = rig.keys.topic("joint_trajectory")
    rig.step(js(0))
    rig.trajectory(to(0.3, 2))  # ends at step 22
    for k in range(1, 30):
        rig.step(js(k))
    assert rig.refs[-1].position[0] == pytest.approx(0.3)
    rig.trajectory(to(-0.2, 60, 0.1))  # pending: starts at step 60
    rig.trajectory(to(0.1, 40, 0.01))  # newer, starts earlier: replaces the pending one from step 40 on
    for k in range(30, 40):
        rig.step(js(k))
    assert rig.refs[-1].position[0] == pytest.approx(0.3)  # before step 40 the old command went on
    for k in range(40, 200):
        rig.step(js(k))
    assert rig.refs[-1].position[0] == pytest.approx(0.1), "the earlier-stamped newer one was not followed"
    assert rig.svc.rejected[key] == 0, dict(rig.svc.rejected)
    # one that starts later replaces only from its start: until then the current command goes on
    rig.trajectory(to(0.25, 250, 0.01))
    rig.trajectory(to(-0.1, 220, 0.01))  # newer, earlier: the 250 one is dropped (it started after 220)
    for k in range(200, 300):
        rig.step(js(k))
    assert rig.refs[-1].position[0] == pytest.approx(-0.1)
    # ended before it arrived: refused, said in the health
    rig.trajectory(to(0.3, 100, 0.02))
    assert rig.svc.rejected[key] == 1
    h = {kv.key: kv.value for kv in rig.svc.health().status[0].values}
    assert "ended at 0.120 s, before it arrived" in h["last_refused"], h
    assert h["command_from"] == "joint_trajectory" and h["trajectories_refused"] == "1"
    rig.trajectory(to(0.05, 0, 0.01))  # stamp zero: now
    for k in range(300, 320):
        rig.step(js(k))
    assert rig.svc.rejected[key] == 1 and rig.refs[-1].position[0] == pytest.approx(0.05)


def test_a_stamp_far_ahead_or_on_the_wall_clock_is_refused_naming_use_sim_time(rig: Rig) -> None:
    """A node not on sim time stamps with the wall clock (1.7e9 s ahead): refused with a reason naming
    use_sim_time, as is any stamp beyond controller.params.max_start_ahead; the next trajectory is taken."""
    key = rig.keys.topic("joint_trajectory")
    rig.step(js(0))
    wall = msgs.JointTrajectory(header=msgs.header(time.time_ns()), joint_names=["joint_1"], points=[
        msgs.JointTrajectoryPoint(positions=[0.3], time_from_start=msgs.duration(0.01))])
    rig.trajectory(wall)
    assert rig.svc.rejected[key] == 1
    assert "wall-clock time" in rig.svc.last_refused and "use_sim_time" in rig.svc.last_refused, rig.svc.last_refused
    ahead = rig.svc.params.max_start_ahead
    rig.trajectory(to(0.3, round((ahead + 1) * 1000)))  # an hour ahead would be the same
    assert rig.svc.rejected[key] == 2
    assert "max_start_ahead" in rig.svc.last_refused and "use_sim_time" in rig.svc.last_refused
    rig.trajectory(to(0.2, 5))
    for k in range(1, 40):
        rig.step(js(k))
    assert rig.svc.rejected[key] == 2 and rig.refs[-1].position[0] == pytest.approx(0.2)


def test_partial_joints_only_where_allowed(scenario: Callable[..., Any], session: Any,
                                           run_service: Callable[[Any], Any]) -> None:
    """allow_partial_joints_goal: false refuses a subset (and says so), takes all joints in any order."""
    sc = scenario(overrides={"controller.params": {"allow_partial_joints_goal": False}})
    with run_service(ControllerService(sc)) as svc:
        r = Rig(svc, session)
        try:
            key = r.keys.topic("joint_trajectory")
            r.step(js(0))
            r.trajectory(to(0.2, 0))
            assert svc.rejected[key] == 1 and "allow_partial_joints_goal" in svc.last_refused
            names = list(reversed(NAMES))
            r.trajectory(msgs.JointTrajectory(joint_names=names, points=[msgs.JointTrajectoryPoint(
                positions=[0.0, 0.0, 0.0, 0.0, 0.0, 0.2], time_from_start=msgs.duration(0.01))]))
            for k in range(1, 20):
                r.step(js(k))
            assert svc.rejected[key] == 1 and r.refs[-1].position[0] == pytest.approx(0.2)
        finally:
            r.close()


def test_live_gain_change_changes_the_output(rig: Rig) -> None:
    rig.step(js(0))
    before = rig.step(js(1, [0.0, 0.01, 0.0, 0.0, 0.0, 0.0]))
    req = msgs.SetParameters(parameters=[msgs.Parameter("joint_2.kp", 80.0), msgs.Parameter("joint_2.ki", 0.0)])
    res = rig.set_parameters(msgs.encode(req))
    assert res.successful, res.reason
    after = rig.step(js(2, [0.0, 0.01, 0.0, 0.0, 0.0, 0.0]))
    assert after.effort[1] == pytest.approx(-0.8)
    assert after.effort[1] != pytest.approx(before.effort[1])
    # All-or-nothing: one bad item and nothing changes.
    for bad in (
        [msgs.Parameter("joint_2.kp", 10.0), msgs.Parameter("joint_2.kd", -1.0)],
        [msgs.Parameter("joint_2.kp", 10.0), msgs.Parameter("joint_2.kp", float("nan"))],
        [msgs.Parameter("joint_2.kp", 10.0), msgs.Parameter("elbow.kp", 1.0)],
        [msgs.Parameter("joint_2.kp", 10.0), msgs.Parameter("joint_2.gain", 1.0)],
    ):
        res = rig.set_parameters(msgs.encode(msgs.SetParameters(parameters=bad)))
        assert not res.successful and (bad[1].name in res.reason or "not finite" in res.reason), res.reason
    assert rig.svc.pids[1].kp == 80.0
    res = rig.set_parameters(b"\x00\x01\x00\x00junk")
    assert not res.successful and res.reason
    assert rig.step(js(3, [0.0, 0.01, 0.0, 0.0, 0.0, 0.0])).effort[1] == pytest.approx(-0.8)


def test_malformed_inputs_are_rejected_and_counted(rig: Rig) -> None:
    rig.step(js(0))
    key_js = rig.keys.topic("joint_states")
    key_tr = rig.keys.topic("joint_trajectory")
    good = msgs.encode(js(1))
    nan = js(1)
    nan.position[0] = float("nan")
    five = js(1)
    five.name, five.position, five.velocity = NAMES[:5], [0.0] * 5, [0.0] * 5
    strangers = js(1)
    strangers.name = [*NAMES[:5], "gripper"]
    for payload in (b"garbage!", good[:-9], msgs.encode(nan), msgs.encode(five), msgs.encode(strangers)):
        rig.pub_js.put(payload)
    assert wait_until(lambda: rig.svc.rejected[key_js] == 5), dict(rig.svc.rejected)

    p = msgs.JointTrajectoryPoint
    bad_trajs: list[bytes] = [
        b"\x00\x01\x00\x00\xff\xff",
        msgs.encode(msgs.JointTrajectory(joint_names=NAMES, points=[p(positions=[0.1] * 6)]))[:-5],
        msgs.encode(msgs.JointTrajectory(joint_names=NAMES, points=[p(positions=[0.1] * 5)])),
        msgs.encode(msgs.JointTrajectory(joint_names=NAMES, points=[p(positions=[float("nan")] * 6)])),
        msgs.encode(msgs.JointTrajectory(joint_names=["joint_1", "wrist"], points=[p(positions=[0.1, 0.1])])),
        msgs.encode(msgs.JointTrajectory(joint_names=["joint_2"], points=[p(positions=[3.0])])),  # beyond limit
    ]
    for b in bad_trajs:
        rig.trajectory(b)
    assert rig.svc.rejected[key_tr] == len(bad_trajs), dict(rig.svc.rejected)
    # Still answering, still holding the first position.
    c = rig.step(js(2))
    assert msgs.ns_of(c.header.stamp) == 2 * DT_NS and np.allclose(effort(c), 0.0)
    assert rig.refs[-1].position == [0.0] * 6
    # Health reports the rejections (published at 1 Hz and at exit).
    with rig.cv:
        assert rig.cv.wait_for(lambda: bool(rig.health), 3.0)
        h = {kv.key: kv.value for kv in rig.health[-1].status[0].values}
    assert int(h["rejected"]) == 5 + len(bad_trajs)
    assert h[f"rejected:{key_js}"] == "5"


def test_each_joint_gets_the_command_of_its_interface(
    scenario: Callable[..., Any], session: Any, run_service: Callable[[Any], Any]
) -> None:
    """Mixed interfaces: joint_1 position, joint_2 velocity, the others effort — one message,
    every joint, each field filled for the joints whose interface reads it."""
    sc = scenario(overrides={"joints.joint_1": {"interface": "position"}, "joints.joint_2": {"interface": "velocity"}})
    with run_service(ControllerService(sc)) as svc:
        r = Rig(svc, session)
        try:
            r.step(js(0, [0.3] * 6))  # the first measurement is the setpoint
            c = r.step(js(1, [0.25] * 6))  # 0.05 rad behind on every joint
            assert c.name == NAMES and c.position == pytest.approx([0.3] * 6)
            gain = sc.controller.velocity_gain
            assert c.velocity[1] == pytest.approx(gain * 0.05)  # velocity joint: position error closed
            assert c.velocity[0] == 0.0  # position joint: the reference velocity (feed-forward)
            assert c.effort[0] == 0.0 and c.effort[1] == 0.0  # no PID output for non-effort joints
            assert all(e > 0 for e in c.effort[2:])  # effort joints push towards the setpoint
        finally:
            r.close()


def test_missing_gains_are_a_config_error(scenario: Callable[..., Any]) -> None:
    with pytest.raises(ConfigError, match=r"controller.gains: no gains for joint_1 and no 'default'"):
        ControllerService(scenario(overrides={"controller.gains": {"joint_2": {"kp": 1.0}}}))
    with pytest.raises(ConfigError, match=r"controller.gains.elbow: not a joint"):
        ControllerService(scenario(overrides={"controller.gains.elbow": {"kp": 1.0}}))


def test_lockstep_chain_with_sensors_and_mujoco(
    scenario: Callable[..., Any], session: Any, run_service: Callable[[Any], Any]
) -> None:
    """Physics stand-in in the test: truth -> sensors -> joint_states -> controller -> commands -> step."""
    sc = scenario(overrides={"services": ["physics", "sensors", "controller"]})
    keys = Keys.of(sc)
    spec = mujoco.MjSpec.from_file(str(sc.world.model))
    for b in spec.bodies:
        b.gravcomp = 1.0  # must be set before compiling to take effect
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    cmds: list[msgs.JointState] = []
    acks: list[int] = []
    cv = threading.Condition()

    def on_cmd(sample: Any) -> None:
        with cv:
            cmds.append(msgs.decode(msgs.JointState, sample.payload.to_bytes()))
            cv.notify_all()

    def on_ack(sample: Any) -> None:
        with cv:
            acks.append(msgs.ns_of(msgs.decode(msgs.Clock, sample.payload.to_bytes()).clock))
            cv.notify_all()

    decl = [
        session.declare_subscriber(keys.topic("joint_commands"), on_cmd),
        session.declare_subscriber(keys.sync("sensors"), on_ack),
    ]
    pub_js = transport.publisher(session, keys.truth("joint_states"))
    pub_imu = transport.publisher(session, keys.truth("imu"))
    pub_traj = transport.publisher(session, keys.topic("joint_trajectory"))
    decl += [pub_js, pub_imu, pub_traj]
    try:
        with run_service(SensorService(sc)), run_service(ControllerService(sc)) as ctl:
            assert wait_until(lambda: pub_js.matching_status.matching and pub_traj.matching_status.matching)
            target = 0.2
            for k in range(400):
                t = k * DT_NS
                if k == 10:  # as the planner does: publish, starting a little later in sim time
                    pub_traj.put(
                        msgs.encode(
                            msgs.JointTrajectory(
                                header=msgs.header(t + 20 * DT_NS),
                                joint_names=["joint_2"],
                                points=[
                                    msgs.JointTrajectoryPoint(positions=[0.0]),
                                    msgs.JointTrajectoryPoint(positions=[target], time_from_start=msgs.duration(0.15)),
                                ],
                            )
                        )
                    )
                    assert wait_until(lambda: ctl.taken is not None)
                pub_imu.put(msgs.encode(msgs.Imu(header=msgs.header(t))))
                pub_js.put(
                    msgs.encode(
                        msgs.JointState(
                            header=msgs.header(t),
                            name=NAMES,
                            position=d.qpos[:6].tolist(),
                            velocity=d.qvel[:6].tolist(),
                            effort=d.ctrl[:6].tolist(),
                        )
                    )
                )
                with cv:
                    # with a controller, its command is the acknowledgement: the sensors send none (30 s: a
                    # fresh clone's suite, two at a time, once waited more than 5 s for step 0's)
                    assert cv.wait_for(lambda k=k: len(cmds) > k, 30.0), f"step {k} not acknowledged"
                    assert msgs.ns_of(cmds[k].header.stamp) == t and not acks
                    d.ctrl[:] = cmds[k].effort
                mujoco.mj_step(m, d)
            assert abs(d.qpos[1] - target) < 0.01
            assert max(abs(d.qpos[i]) for i in (0, 2, 3, 4, 5)) < 0.01
            assert ctl.max_tracking_error < 0.05
    finally:
        for x in decl:
            x.undeclare()


def test_realtime_drops_a_stale_joint_state_but_never_a_trajectory(
        scenario: Callable[..., Any], session: Any, run_service: Callable[[Any], Any]) -> None:
    """Realtime: a joint state older than clock.max_age is dropped (a newer one follows, the loop
    works on fresh data), a trajectory just as old is taken (given once: dropped, a task would
    never start; seen on a loaded machine as a target never moved to)."""
    sc = scenario("arm", {"clock.mode": "realtime", "clock.max_age": 0.05})
    with run_service(ControllerService(sc)) as svc:
        rig = Rig(svc, session)
        try:
            gid = transport.new_gid()
            old = time.time_ns() - 1_000_000_000  # sent a second ago: queued behind a busy core

            def att(seq: int, ns: int) -> bytes:
                return transport.Attachment(seq, ns, gid).encode()

            k_js = rig.keys.topic("joint_states")
            rig.pub_js.put(msgs.encode(js(0)), attachment=att(1, old))
            assert wait_until(lambda: svc.stale[k_js] == 1, 5.0), svc.stale
            time.sleep(0.2)
            assert rig.cmds == [], "a stale joint state was answered"
            rig.pub_js.put(msgs.encode(js(1)), attachment=att(2, time.time_ns()))
            with rig.cv:
                assert rig.cv.wait_for(lambda: len(rig.cmds) == 1, 5.0), "a fresh joint state was not answered"
            tr = msgs.JointTrajectory(header=msgs.header(2 * DT_NS), joint_names=["joint_1"], points=[
                msgs.JointTrajectoryPoint(positions=[0.0], time_from_start=msgs.duration(0.0)),
                msgs.JointTrajectoryPoint(positions=[0.3], time_from_start=msgs.duration(1.0))])
            k_tr = rig.keys.topic("joint_trajectory")
            rig.pub_traj.put(msgs.encode(tr), attachment=att(1, old))
            # counted on receipt, judged by its handler after: wait for the verdict (taken, stale or refused),
            # not the count (CI, under load: checked between the two, "not taken")
            assert wait_until(lambda: svc.counts_in[k_tr] == 1 and (
                svc.taken is not None or svc.stale[k_tr] or svc.rejected[k_tr]), 5.0)
            with svc.lock:
                assert svc.stale[k_tr] == 0 and svc.rejected[k_tr] == 0
                assert svc.taken is not None, "the trajectory was not taken"
        finally:
            rig.close()
