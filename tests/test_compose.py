"""Composition (hilsim.launch.compose): services sharing one process exchange message objects, and the
outside still sees every key on Zenoh, exactly once. The lockstep equivalence with the distributed
pipeline, bit for bit, is tests/test_e2e.py::test_lockstep_runs_are_bit_identical."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from util import LEAN, Observer, finish, up, wait_until

from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.launch.compose import ComposedSession

REPO = Path(__file__).resolve().parent.parent


def test_compose_groups_become_one_process_each() -> None:
    sc = load_scenario("arm", {"compose": [["physics", "sensors", "controller"]]})
    assert sc.launch_units() == ["physics+sensors+controller", "planner", "logger"]
    assert load_scenario("arm").launch_units() == sc.processes()


@pytest.mark.parametrize(
    ("groups", "says"),
    [
        ([["physics", "nobody"]], "compose[0]: 'nobody' is not one of this scenario's services"),
        ([["physics", "sensors"], ["sensors", "controller"]], "compose[1]: 'sensors' is in two groups"),
        ([["physics"]], "compose[0]: a group needs at least two services"),
    ],
)
def test_bad_compose_groups_are_one_line_errors(groups: list[list[str]], says: str) -> None:
    with pytest.raises(ConfigError, match=r"compose\[") as e:
        load_scenario("arm", {"compose": groups})
    assert says in str(e.value) and "\n" not in str(e.value)


def test_hilsim_up_refuses_a_bad_group_in_one_line() -> None:
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", "--compose", "physics,nobody"],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "'nobody' is not one of this scenario's services" in lines[0], r.stderr


def test_local_subscribers_get_the_object_and_remote_ones_the_bytes_once() -> None:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    real = transport.open_session(ZenohConfig(connect=[ep]))
    outside = transport.open_session(ZenohConfig(connect=[ep]))
    cs = ComposedSession(real)
    try:
        local: list[tuple[str, object, transport.Attachment]] = []
        remote: list[bytes] = []
        cs.local_subscriber("t/**", lambda k, m, a: local.append((k, m, a)))
        cs.declare_subscriber("t/**", lambda s: local.append(("zenoh", s, None)))  # from outside only
        outside.declare_subscriber("t/x", lambda s: remote.append(s.payload.to_bytes()))
        time.sleep(0.5)
        pub = cs.declare_publisher("t/x")
        assert wait_until(lambda: pub.remote, 5.0)  # the outside subscriber is matched
        msg = msgs.Clock(clock=msgs.stamp(42))
        att = transport.Attachment(1, time.time_ns(), transport.new_gid())
        pub.deliver(msg, att)
        pub.put(msgs.encode(msg), attachment=att.encode())
        assert wait_until(lambda: len(local) == 1 and len(remote) == 1, 5.0), (local, remote)
        time.sleep(0.3)  # nothing more arrives: the local subscriber did not get it through Zenoh too
        assert len(local) == 1 and len(remote) == 1
        k, got, a = local[0]
        assert k == "t/x" and got is msg and a == att  # the object itself: no encoding in between
        assert msgs.decode(msgs.Clock, remote[0]) == msg
        # and what comes from outside reaches the process through Zenoh, once
        outside.put("t/y", b"hello")
        assert wait_until(lambda: len(local) == 2, 5.0)
        time.sleep(0.3)
        assert len(local) == 2 and local[1][0] == "zenoh"
    finally:
        cs.close()
        outside.close()
        router.close()


def test_composed_realtime_arm_reaches_a_target_in_the_truth(tmp_path: Path) -> None:
    """Realtime, physics + sensors + controller in one process (its own OS process), planner
    apart: the target is reached in the physics truth, at wall speed."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    target = [0.5, -0.4, 0.2, 0.0, -0.5, 0.0]
    try:
        p = up(LEAN, "--clock", "realtime", "--compose", "physics,sensors,controller", "--router", ep,
               "--no-logger", "--out", str(tmp_path / "run"), "--set", f"task.targets=[{target}]")
        out = finish(p, 240)
        assert p.returncode == 0, out
        assert "physics+sensors+controller (pid" in out and "targets reached: 1/1" in out, out
        rtf = float(out.split("real-time factor ")[-1].split(",")[0])
        assert 0.9 <= rtf <= 1.05, out
        time.sleep(0.3)
        stamp, ok = obs.results["task-1"]
        assert ok
        assert np.abs(obs.truth_at(stamp) - np.asarray(target)).max() <= 0.012
    finally:
        obs.close()
        router.close()


def test_a_composed_recorder_records_every_sample_as_it_was_published(tmp_path: Path) -> None:
    """The recorder composed with physics, sensors and controller (``--compose
    physics,sensors,controller,logger``): lockstep, every sample of the process's own services
    (which never cross Zenoh now) and of the planner outside is recorded, and the truth in the
    file is the truth physics published, value for value (seen over Zenoh by this test); the
    latched /tf_static and robot_description once each."""
    import datetime
    import json

    from rerun.chunk import RrdReader

    from hilsim.core.recording import recording_files

    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    run = tmp_path / "run"
    try:
        p = up("arm", "--compose", "physics,sensors,controller,logger", "--router", ep, "--duration", "2",
               "--set", "task.targets=[]", "--out", str(run))
        out = finish(p, 240)
        assert p.returncode == 0, out
        assert "physics+sensors+controller+logger (pid" in out, out
        time.sleep(0.3)
        with obs.lock:
            truth = dict(obs.truth)
    finally:
        obs.close()
        router.close()
    summary = json.loads((run / "record_summary.json").read_text())
    steps = 2001  # t = 0 and 2000 steps of 1 ms
    k = Keys()
    for key in (k.clock, k.truth("joint_states"), k.topic("joint_states"), k.topic("joint_commands"), k.truth("imu")):
        assert summary[key]["received"] == summary[key]["recorded"] == steps, (key, summary[key])
    assert summary[k.sync("planner")]["recorded"] > 100, summary  # from the process outside
    # the process's own latched samples (put once in physics' setup, maybe before the recorder was there)
    for key in (k.tf_static, k.topic("robot_description")):
        got = summary.get(key, {"received": 0, "recorded": 0})
        assert got["received"] == got["recorded"] == 1, (key, got)
    assert all(v["received"] == v["recorded"] and v["lost"] == 0 for v in summary.values()), summary
    recorded: dict[int, float] = {}
    for chunk in (c for f in recording_files(run) for c in RrdReader(f).stream().to_chunks()):
        if chunk.entity_path == "/joints/joint_2/position/truth":
            rb = chunk.to_record_batch().to_pydict()
            col = next(k for k in rb if "scalar" in k.lower())
            for t, v in zip(rb["sim_time"], rb[col], strict=True):
                recorded[t // datetime.timedelta(microseconds=1) * 1000] = v[0]  # steps: whole ms
    assert len(recorded) == steps and len(truth) >= steps - 5, (len(recorded), len(truth))
    assert all(recorded[t] == q[1] for t, q in truth.items()), "recorded truth differs from the published"
