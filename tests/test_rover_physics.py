"""Physics truth of a mobile base: truth/odom (chassis pose, body-frame twist) and tf of the chassis
and its sensor sites, published before truth/joint_states; a fixed-base robot publishes neither."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import zenoh

from hilsim.core import msgs
from hilsim.core.keys import Keys, topic_name
from hilsim.services.physics import PhysicsService
from hilsim.sim.world import World


def test_truth_odom_pose_and_body_twist(scenario: Any) -> None:
    w = World(scenario("rover"))
    assert w.base is not None and w.base.name == "base_link"
    # turned 90 degrees to the left and pushed along world +y: forward in its own frame
    yaw = math.pi / 2
    w.data.qpos[3:7] = (math.cos(yaw / 2), 0, 0, math.sin(yaw / 2))
    w.data.qpos[0:3] = (1.0, 2.0, 0.3)
    w.data.qvel[0:3] = (0.0, 0.7, 0.0)
    w.data.qvel[3:6] = (0.0, 0.0, 0.2)
    import mujoco

    mujoco.mj_forward(w.model, w.data)
    od = w.base.odometry(123)
    assert od.header.frame_id == "world" and od.child_frame_id == "base_link" and msgs.ns_of(od.header.stamp) == 123
    p, q = od.pose.pose.position, od.pose.pose.orientation
    assert (p.x, p.y, p.z) == (1.0, 2.0, 0.3)
    assert np.allclose((q.w, q.z), (math.cos(yaw / 2), math.sin(yaw / 2)))
    t = od.twist.twist
    assert np.allclose((t.linear.x, t.linear.y, t.angular.z), (0.7, 0.0, 0.2), atol=1e-9), t
    tf = w.base.transforms(123).transforms
    assert [x.child_frame_id for x in tf] == ["base_link", "imu", "laser", "gps"]
    assert tf[0].header.frame_id == "world" and tf[2].header.frame_id == "base_link"
    assert np.allclose([tf[2].transform.translation.x, tf[2].transform.translation.z], [0.38, 0.16])


def test_arm_has_no_mobile_base(scenario: Any) -> None:
    assert World(scenario("arm")).base is None


def test_rover_settles_on_its_wheels(scenario: Any) -> None:
    w = World(scenario("rover"))
    for _ in range(500):
        w.step()
    od = w.base.odometry(w.time_ns)  # type: ignore[union-attr]
    assert abs(od.pose.pose.position.z - 0.25) < 0.005 and abs(od.pose.pose.position.x) < 1e-3
    assert abs(od.twist.twist.linear.z) < 1e-3


def _order(sc: Any, session: zenoh.Session, run_service: Any) -> list[tuple[str, int]]:
    keys = Keys.of(sc)
    seen: list[tuple[str, int]] = []
    lock = threading.Lock()

    def name(s: zenoh.Sample) -> str:  # /rover/truth/odom -> truth/odom; /tf -> tf
        return topic_name(str(s.key_expr)).removeprefix(f"/{sc.robot}/").lstrip("/")

    def on(s: zenoh.Sample) -> None:
        k = name(s)
        m = msgs.decode(keys_type[k], s.payload.to_bytes())
        stamp = m.transforms[0].header.stamp if isinstance(m, msgs.TFMessage) else m.header.stamp
        with lock:
            seen.append((k, msgs.ns_of(stamp)))

    keys_type = {"truth/odom": msgs.Odometry, "tf": msgs.TFMessage, "truth/joint_states": msgs.JointState,
                 "truth/imu": msgs.Imu}
    def on_any(s: zenoh.Sample) -> None:
        if name(s) in keys_type:
            on(s)

    # one subscriber for every key: it sees them in the order they were sent
    subs = [session.declare_subscriber(keys.everything, on_any)]
    time.sleep(0.3)
    with run_service(PhysicsService(sc)) as svc:
        t0 = time.monotonic()
        while svc.state != "done" and time.monotonic() - t0 < 20:
            time.sleep(0.02)
        time.sleep(0.3)
    for s in subs:
        s.undeclare()
    return seen


def test_physics_publishes_odom_and_tf_before_joint_states(scenario: Any, session: zenoh.Session,
                                                          run_service: Any) -> None:
    sc = scenario("rover", {"services": ["physics"], "duration": 0.02})
    seen = _order(sc, session, run_service)
    by_stamp: dict[int, list[str]] = {}
    for k, t in seen:
        by_stamp.setdefault(t, []).append(k)
    assert len(by_stamp) == 11, by_stamp  # steps 0..10 at 2 ms
    urdf_every = round(1 / (sc.physics.tf_rate_hz * sc.clock.dt))  # the URDF's moving joints on /tf too
    for t, ks in by_stamp.items():
        urdf = ["tf"] if (t // sc.dt_ns) % urdf_every == 0 else []
        assert ks == ["truth/imu", "truth/odom", "tf", *urdf, "truth/joint_states"], (t, ks)


def test_fixed_base_publishes_no_odom(scenario: Any, session: zenoh.Session, run_service: Any) -> None:
    sc = scenario("arm", {"services": ["physics"], "duration": 0.005})
    seen = _order(sc, session, run_service)
    # no odometry; /tf only with the URDF's joints, at step 0 (50 Hz), not a base every step
    assert {k for k, _ in seen} == {"truth/imu", "truth/joint_states", "tf"}
    assert [t for k, t in seen if k == "tf"] == [0], seen


def test_lockstep_steps_through_steps_nobody_is_due_at(scenario: Any, session: zenoh.Session,
                                                      run_service: Any) -> None:
    """A 100 Hz controller over 500 Hz physics acknowledges every 5th step: physics takes the four
    steps between on its own and waits again at the next control step."""
    from hilsim.core import transport

    sc = scenario("rover", {"services": ["physics", "controller"]})
    keys = Keys.of(sc)
    clocks: list[int] = []
    sub = session.declare_subscriber(keys.clock, lambda s: clocks.append(
        msgs.ns_of(msgs.decode(msgs.Clock, s.payload.to_bytes()).clock)))
    gid = transport.new_gid()
    cmd = transport.publisher(session, keys.topic("joint_commands"))
    tokens = [session.liveliness().declare_token(keys.lockstep("controller", 5, 0, "joint_commands", gid.hex())),
              session.liveliness().declare_token(keys.alive("controller"))]
    with run_service(PhysicsService(sc)) as svc:
        deadline = time.monotonic() + 10
        while not clocks and time.monotonic() < deadline:
            time.sleep(0.01)
        names = svc.world.joint_names
        for k, step in enumerate((0, 5)):
            js = msgs.JointState(header=msgs.header(step * sc.dt_ns), name=names, effort=[0.0] * len(names))
            cmd.put(msgs.encode(js), attachment=transport.attachment_bytes(k + 1, gid))
            time.sleep(0.5)
        assert clocks == [k * sc.dt_ns for k in range(11)], clocks  # waits at step 10 for its ack
    sub.undeclare()
    for t in tokens:
        t.undeclare()


def test_contacts_in_the_truth_name_what_touches(scenario: Any) -> None:
    """A rover standing on its wheels touches the floor with four wheels, and only with them; the
    arm at rest touches nothing. (tests/test_e2e.py::test_arm_scenario_end_to_end checks, from
    truth/contacts, that the arm never touches the table or the obstacle.)"""
    w = World(scenario("rover"))
    for _ in range(500):
        w.step()
    c = w.contacts()
    assert c.contacts and w.contact_pairs()
    wheels = {x.body1 if "wheel" in x.body1 else x.body2 for x in c.contacts}
    assert len(wheels) == 4 and all("wheel" in b for b in wheels), wheels
    assert all(x.depth > -0.01 and abs(x.position.z) < 0.2 for x in c.contacts), c.contacts
    arm = World(scenario("arm"))
    arm.step()
    assert arm.contacts().contacts == [] and arm.contact_pairs() == frozenset()
