"""The logger service (Rerun recorder) and `hilsim view`."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.core import msgs, recording, transport
from hilsim.core.keys import Keys

N_STEPS = 300
JOINTS = [f"joint_{i}" for i in range(1, 7)]
DT_NS = 1_000_000


def _wait(cond: Any, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def _js(t: int, k: int) -> msgs.JointState:
    q = [0.3 * np.sin(0.01 * k + i) for i in range(6)]
    return msgs.JointState(
        header=msgs.header(t), name=list(JOINTS), position=q, velocity=[0.1 * i for i in range(6)], effort=[0.5] * 6
    )


def _trajectory(t: int, n: int) -> msgs.JointTrajectory:
    pts = [
        msgs.JointTrajectoryPoint(
            positions=[0.05 * j * (i + 1) / 6 for i in range(6)], time_from_start=msgs.duration(0.1 * j)
        )
        for j in range(n)
    ]
    return msgs.JointTrajectory(header=msgs.header(t), joint_names=list(JOINTS), points=pts)


def test_logger_records_every_message(
    scenario: Any, session: Any, run_service: Any, tmp_path: Path, capsys: Any
) -> None:
    from hilsim.services.logger import LoggerService

    run_dir = tmp_path / "run"
    sc = scenario("arm", {"logger.run_dir": str(run_dir), "logger.batch": 0})
    keys = Keys.of(sc)
    svc = LoggerService(sc)
    st = run_service(svc)
    topics = {
        "truth_js": keys.truth("joint_states"),
        "truth_imu": keys.truth("imu"),
        "clock": keys.clock,
        "js": keys.topic("joint_states"),
        "imu": keys.topic("imu"),
        "cmd": keys.topic("joint_commands"),
        "sync": keys.sync("sensors"),
        "health": keys.health("physics"),
        "log": keys.log("physics"),
        "traj": keys.topic("joint_trajectory"),
        "path": keys.topic("planner/path"),
    }
    sent: dict[str, int] = dict.fromkeys(topics.values(), 0)
    n_garbage = 5
    with st:
        pubs = {name: transport.publisher(session, key) for name, key in topics.items()}
        try:
            _wait(lambda: all(p.matching_status.matching for p in pubs.values()), 10, "the logger's subscriber")

            # Encoded before publishing: in this one test process, encoding while the logger's worker
            # decodes would race on pycdr2's per-class serialization buffer (separate processes in real runs).
            batch: list[tuple[str, bytes]] = []
            for k in range(N_STEPS):
                t = k * DT_NS
                batch.append(("truth_imu", msgs.encode(msgs.Imu(header=msgs.header(t)))))
                batch.append(("truth_js", msgs.encode(_js(t, k))))
                batch.append(("clock", msgs.encode(msgs.Clock(clock=msgs.stamp(t)))))
                batch.append(("js", msgs.encode(_js(t, k))))
                batch.append(
                    ("cmd", msgs.encode(msgs.JointState(header=msgs.header(t), name=JOINTS, effort=[0.1] * 6)))
                )
                batch.append(("sync", msgs.encode(msgs.Clock(clock=msgs.stamp(t)))))
                if k % 5 == 0:
                    imu = msgs.Imu(header=msgs.header(t), linear_acceleration=msgs.Vector3(z=9.81))
                    batch.append(("imu", msgs.encode(imu)))
                if k % 100 == 0:
                    status = msgs.DiagnosticStatus(
                        level=0, name="physics", message="running", values=[msgs.KeyValue("steps", str(k))]
                    )
                    batch.append(("health", msgs.encode(msgs.DiagnosticArray(header=msgs.header(t), status=[status]))))
                    log = msgs.Log(stamp=msgs.stamp(t), level=30, name="physics", msg=f"step {k}")
                    batch.append(("log", msgs.encode(log)))
                if k == 150:  # garbage in the middle: rejected, recorded as text, and the service carries on
                    batch += [("js", bytes([g]) * (3 + g)) for g in range(n_garbage)]
                    batch.append(("path", msgs.encode(_trajectory(t, 8))))
                    batch.append(("traj", msgs.encode(_trajectory(t + 20 * DT_NS, 10))))
            for name, payload in batch:
                pubs[name].put(payload)
                sent[topics[name]] += 1
            total = sum(sent.values())
            _wait(lambda: sum(svc.counts_in[k] for k in sent) == total, 15, "every message to arrive")
            assert svc.state == "running"
        finally:
            for p in pubs.values():
                p.undeclare()
    assert st.rc == 0

    # counts: everything received was recorded; garbage counted as rejected
    summary = json.loads((run_dir / "record_summary.json").read_text())
    for key, n in sent.items():
        assert summary[key]["received"] == n, key
    for key, c in summary.items():
        assert c["recorded"] == c["received"], key
    assert summary[keys.topic("joint_states")]["rejected"] == n_garbage
    assert sum(c["rejected"] for c in summary.values()) == n_garbage, summary
    out = capsys.readouterr().out
    assert f"recorded {keys.clock}: received {N_STEPS} recorded {N_STEPS}" in out
    assert "recorded total:" in out
    assert (run_dir / "scenario.yaml").is_file()

    # the file: valid, and holding what was sent
    rrd = run_dir / "recording.rrd"
    recording.verify_rrd(rrd)
    rows = recording.entity_rows(rrd)
    for j in JOINTS:
        for q in ("position", "velocity", "effort"):
            assert rows[f"/joints/{j}/{q}/truth"] == N_STEPS, (j, q)
            assert rows[f"/joints/{j}/{q}/measured"] == N_STEPS, (j, q)  # including those after the garbage
        assert rows[f"/joints/{j}/effort/command"] == N_STEPS
        assert rows[f"/joints/{j}/position/planned"] == 10
        assert rows[f"/robot/joint_transforms/{j}"] == N_STEPS // 10  # 3D pose every 10 ms of sim time
    assert rows["/clock"] == N_STEPS
    assert rows["/imu/truth/angular_velocity/x"] == N_STEPS
    assert rows["/imu/measured/linear_acceleration/z"] == N_STEPS // 5
    assert rows["/health/physics/level"] == rows["/health/physics/steps"] == N_STEPS // 100
    assert rows["/log/physics"] == N_STEPS // 100
    assert sum(n for e, n in rows.items() if e.startswith("/rejected/")) == n_garbage
    assert rows["/joint_trajectory/tool_path"] >= 1 and rows["/planner/path/joint_space"] == 1
    from rerun.chunk import RrdReader  # rerun is imported after the logger switched analytics off

    assert RrdReader(rrd).blueprints(), "the default viewer layout is stored with the recording"
    model = [e for e in rows if e.startswith("/robot/") and "visual_geometries" in e]
    for link in ("base_link", "shoulder_link", "hand_link"):
        assert any(f"/{link}/" in e for e in model), link


def test_tool_kinematics_matches_mujoco() -> None:
    """Tool path forward kinematics from the URDF agrees with MuJoCo loading the same URDF."""
    import mujoco

    from hilsim.core.config import MODELS_DIR
    from hilsim.sim.kinematics import ToolKinematics, UrdfTree

    urdf = MODELS_DIR / "arm" / "arm.urdf"
    kin = ToolKinematics(UrdfTree.from_file_path(urdf))
    assert kin.tool == "tool_link"
    m = mujoco.MjModel.from_xml_path(str(urdf))
    d = mujoco.MjData(m)
    names = [m.joint(i).name for i in range(m.njnt)]
    rng = np.random.default_rng(0)
    q = rng.uniform(-1.0, 1.0, size=(5, len(names)))
    ours = kin.positions(names, q)
    base = m.body("base_link").id
    for row, p in zip(q, ours, strict=True):
        d.qpos[:] = row
        mujoco.mj_kinematics(m, d)
        # relative to the root link (MuJoCo may place the URDF root anywhere in its world)
        want = d.xmat[base].reshape(3, 3).T @ (d.xpos[m.body("tool_link").id] - d.xpos[base])
        np.testing.assert_allclose(p, want, atol=1e-9)


def test_latest_recording(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    with pytest.raises(recording.RecordingError, match="does not exist"):
        recording.latest_recording(runs)
    (runs / "a").mkdir(parents=True)
    with pytest.raises(recording.RecordingError, match="no recordings in"):
        recording.latest_recording(runs)
    old, new = runs / "a" / "recording.rrd", runs / "b" / "recording.rrd"
    new.parent.mkdir()
    old.write_bytes(b"x")
    new.write_bytes(b"x")
    os.utime(old, (1_000_000, 1_000_000))
    assert recording.latest_recording(runs) == new


def test_view_errors(tmp_path: Path, capsys: Any, monkeypatch: Any) -> None:
    rc = recording.cmd_view(argparse.Namespace(rrd=None, runs=str(tmp_path / "runs")))
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith("hilsim view: no recordings") and err.count("\n") == 1
    rc = recording.cmd_view(argparse.Namespace(rrd=str(tmp_path / "missing.rrd"), runs="runs"))
    assert rc == 1 and "missing.rrd: no such recording" in capsys.readouterr().err
    # headless: prints the path and the command instead of starting a viewer
    rrd = tmp_path / "runs" / "r1" / "recording.rrd"
    rrd.parent.mkdir(parents=True)
    rrd.write_bytes(b"x")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    rc = recording.cmd_view(argparse.Namespace(rrd=None, runs=str(tmp_path / "runs")))
    err = capsys.readouterr().err
    assert rc == 1 and "no display" in err and f"{recording.rerun_executable()} --bind 127.0.0.1 {rrd}" in err


def test_verify_rejects_a_broken_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not a recording at all")
    with pytest.raises(recording.RecordingError, match="rrd verify failed"):
        recording.verify_rrd(bad)


def test_rerun_analytics_off_in_a_private_config(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    env = recording.rerun_env()
    assert Path(env["XDG_CONFIG_HOME"]).is_relative_to(tmp_path)
    r = subprocess.run(
        [recording.rerun_executable(), "analytics", "config"],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    cfg = json.loads(r.stdout)
    assert cfg["analytics_enabled"] is False
    assert cfg["config_file_path"].startswith(env["XDG_CONFIG_HOME"])


def test_logger_counts_lost_samples_per_key(
    scenario: Any, session: Any, run_service: Any, tmp_path: Path, monkeypatch: Any
) -> None:
    """Realtime: gaps in each writer's sequence numbers and samples refused by the full queue
    are counted as lost per key; samples published before a writer's first one are not."""
    from hilsim.services.logger import LoggerService

    monkeypatch.setenv("HILSIM_LOGGER_DELAY_US", "50")
    run_dir = tmp_path / "run"
    sc = scenario("arm", {"logger.run_dir": str(run_dir), "logger.batch": 0, "clock.mode": "realtime"})
    keys = Keys.of(sc)
    svc = LoggerService(sc)
    assert svc.delay_s == pytest.approx(50e-6)
    assert LoggerService(scenario("arm", {"logger.run_dir": str(tmp_path / "ls")})).queue_limit is None  # lockstep
    clock = msgs.encode(msgs.Clock(clock=msgs.stamp(0)))
    js = msgs.encode(_js(0, 0))
    a, b, c = transport.new_gid(), transport.new_gid(), transport.new_gid()
    st = run_service(svc)
    with st:
        pub_clock = session.declare_publisher(keys.clock)
        pub_js = session.declare_publisher(keys.truth("joint_states"))
        try:
            _wait(lambda: pub_clock.matching_status.matching and pub_js.matching_status.matching, 10, "the logger")
            # writer a: 1 2 3 _ _ 6 7 (2 lost); writer b seen from 5 on: 5 6 _ 8 (1 lost, 4 before its first)
            for gid, seq in [(a, 1), (a, 2), (a, 3), (b, 5), (a, 6), (b, 6), (a, 7), (b, 8)]:
                pub_clock.put(clock, attachment=transport.attachment_bytes(seq, gid))
            pub_clock.put(clock)  # no attachment (a foreign publisher): recorded, not sequence-checked
            _wait(lambda: svc.counts_in[keys.clock] == 9, 10, "the clock samples")
            assert svc.health_values()["lost"] == 3
            # a stalled worker (held on the codec lock) and a queue of 3: the rest is refused
            svc.queue_limit = 3
            with svc._codec_lock:
                for seq in range(1, 11):
                    pub_js.put(js, attachment=transport.attachment_bytes(seq, c))
                _wait(lambda: svc.counts_in[keys.truth("joint_states")] + svc.dropped[keys.truth("joint_states")] == 10,
                      10, "the joint states")
                hv = svc.health_values()
            assert svc.state == "running"
        finally:
            pub_clock.undeclare()
            pub_js.undeclare()
    assert st.rc == 0
    truth = keys.truth("joint_states")
    assert hv[f"lost:{keys.clock}"] == 3 and hv[f"lost:{truth}"] == hv["dropped"] >= 6, hv
    summary = json.loads((run_dir / "record_summary.json").read_text())
    assert summary[keys.clock] == {
        "received": 9, "recorded": 9, "bagged": 9, "rejected": 0, "lost": 3, "dropped": 0, "before_first": 4,
        "unannounced": 0,
    }, summary[keys.clock]
    t = summary[truth]
    assert t["received"] == t["recorded"] and t["received"] + t["lost"] == 10 and t["lost"] == t["dropped"] >= 6, t


def test_a_strangers_gaps_are_not_the_recorders_losses(
    scenario: Any, session: Any, run_service: Any, tmp_path: Path
) -> None:
    """Lockstep, where any loss fails the run: samples from a writer that did not announce itself
    for the key are recorded, counted as unannounced, and their sequence gaps are no loss."""
    from hilsim.services.logger import LoggerService

    run_dir = tmp_path / "run"
    sc = scenario("arm", {"logger.run_dir": str(run_dir), "logger.batch": 0})
    keys = Keys.of(sc)
    svc = LoggerService(sc)
    clock = msgs.encode(msgs.Clock(clock=msgs.stamp(0)))
    token_key, real = keys.writer_token(keys.clock)
    stranger = transport.new_gid()
    token = session.liveliness().declare_token(token_key)
    st = run_service(svc)
    with st:
        pub = session.declare_publisher(keys.clock)
        try:
            _wait(lambda: pub.matching_status.matching and keys.clock in svc.provenance.restricted, 10, "the logger")
            for gid, seq in [(real, 1), (stranger, 1), (real, 2), (stranger, 5), (stranger, 9), (real, 3)]:
                pub.put(clock, attachment=transport.attachment_bytes(seq, gid))
            _wait(lambda: svc.counts_in[keys.clock] == 6, 10, "the clock samples")
        finally:
            pub.undeclare()
    token.undeclare()
    assert st.rc == 0
    c = json.loads((run_dir / "record_summary.json").read_text())[keys.clock]
    assert c["received"] == c["recorded"] == 6 and c["lost"] == 0 and c["unannounced"] == 3, c


@pytest.mark.parametrize("mode", ["realtime", "lockstep"])
def test_launcher_summary_reports_losses(scenario: Any, tmp_path: Path, capsys: Any, mode: str) -> None:
    """`hilsim up` shows what the recorder lost, one count per cause; any loss fails a lockstep run, a realtime
    one past ``logger.max_loss``."""
    from hilsim.launch.launcher import Launcher, summarise

    sc = scenario("arm", {"clock.mode": mode, "duration": 1.0, "task.targets": []})
    keys = Keys.of(sc)
    clock, imu, health = keys.clock, keys.truth("imu"), keys.health("physics")
    la = Launcher(sc, tmp_path)
    la.outcome.physics_done = True
    la.outcome.health["physics"] = {"steps": "1000", "sim_time": "1.000", "real_time_factor": "1.000", "final": "1",
                                    f"published:{clock}": "1001", f"published:{imu}": "1001"}
    counts = {
        clock: {"received": 700, "recorded": 700, "rejected": 0, "lost": 250, "dropped": 50, "before_first": 0},
        imu: {"received": 900, "recorded": 900, "rejected": 0, "lost": 101, "dropped": 0},
        health: {"received": 1, "recorded": 1, "rejected": 0},  # an older summary
    }
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    rc = summarise(la)
    out = capsys.readouterr().out
    assert ("recorded 1601 of 1601 received messages on 3 keys; lost 351 (301 in transport, 50 dropped by the "
            "recorder)") in out, out
    assert ": truth/imu 101, clock 250" not in out and ": clock 250, truth/imu 101" in out, out
    # every service's own per-key published count shows what left no gap (after the last sample seen)
    assert "51 published samples never reached the recorder: clock 51\n" in out, out
    # 402 of 2003 published missed (20.1 %): past logger.max_loss (5 %) a realtime run fails too, and says why
    assert rc == 1 and "not judged" not in out, out
    if mode == "realtime":
        assert "the recording missed 20.1% of the samples (more than logger.max_loss, 5.0%)" in out, out
        assert out.rstrip().endswith("result: FAILED (recording lost 20.1%)"), out
        la.sc = scenario("arm", {"clock.mode": mode, "duration": 1.0, "task.targets": [], "logger.max_loss": 1.0})
        assert summarise(la) == 0  # --allow-loss: said, not a failure (as before)
        out = capsys.readouterr().out
        assert "lost 351" in out and "missed" not in out and out.rstrip().endswith("OK"), out
    else:
        assert out.rstrip().endswith("result: FAILED") and "missed" not in out, out  # lockstep: any loss fails
    # counts whose dropped part exceeds what is lost (a summary of before the fix): never a negative count
    counts[clock]["dropped"] = 300
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    summarise(la)
    out = capsys.readouterr().out
    assert "lost 351 (101 in transport, 250 dropped by the recorder)" in out, out
    counts[clock]["dropped"] = 50
    # a service killed before its final health: what it counted as published and never sent (its unsent batch)
    # is no loss of the recorder's; said, not judged
    la.outcome.health["physics"].pop("final")
    la.outcome.health["physics"][f"published:{clock}"] = "951"  # 1 unseen of its periodic count
    counts[clock]["lost"], counts[clock]["dropped"], counts[imu]["lost"] = 0, 0, 0
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    assert summarise(la) == 0
    out = capsys.readouterr().out
    assert "never reached the recorder" not in out and "lost" not in out, out
    assert "not judged: 352 samples counted as published by physics (killed before its final health)" in out, out
    la.outcome.health["physics"]["final"] = "1"
    counts[clock]["lost"], counts[clock]["dropped"], counts[imu]["lost"] = 250, 50, 101
    # received but not recorded fails either way
    counts[clock]["recorded"] = 699
    (tmp_path / "record_summary.json").write_text(json.dumps(counts))
    assert summarise(la) == 1
    assert f"MISMATCH (received but not recorded) on ['{clock}']" in capsys.readouterr().out


def test_the_recorders_summary_and_lines_say_every_count() -> None:
    """hilsim.record.report: the summary holds each key's counts (bagged with a bag; duplicates with
    batches; after_stop, and the stop entry, for a recording stopped early); the lines say the totals,
    what a late subscription missed and the losses."""
    from collections import Counter

    from hilsim.core.recording import STOPPED_ENTRY
    from hilsim.record import report

    k, t = "0/arm/joint_states/x/RIHS01_1", "0/lab/burst/x/RIHS01_2"
    c = report.Counts(received=Counter({k: 10, t: 3}), recorded=Counter({k: 10, t: 3}), bagged=Counter({k: 10, t: 3}),
                      rejected=Counter({k: 1}), lost=Counter({k: 2}), dropped=Counter({k: 1}),
                      before_first=Counter({t: 4}), unannounced=Counter(), duplicates=Counter({k: 5}),
                      after_stop=Counter({k: 7}), suspect=Counter(), contested=Counter({k: 1}), plain={t})
    stop = {"reason": "logger.max_size 1 MB reached", "sim_time": 2.5}
    s = report.summary(c, bag=True, batching=True, stopped_at=stop)
    assert s[k] == {"received": 10, "recorded": 10, "bagged": 10, "rejected": 1, "lost": 2, "dropped": 1,
                    "before_first": 0, "unannounced": 0, "duplicates": 5, "after_stop": 7, "contested": 1}
    assert s[t]["key_subscribed"] and s[t]["before_first"] == 4 and "suspect" not in s[t]
    assert s[STOPPED_ENTRY] == {**stop, "after_stop": 7}
    plain = report.summary(c, bag=False, batching=False, stopped_at=None)
    assert "bagged" not in plain[t] and "after_stop" not in plain[k] and STOPPED_ENTRY not in plain
    out = report.lines(c, rrd=Path("r.rrd"), bag_dir=Path("bag"), clock="realtime", stopped_at=stop)
    assert out[0] == f"recorded {k}: received 10 recorded 10 bagged 10 lost 2"
    assert "recorded total: received 13 recorded 13 rejected 1 lost 2 in 2 keys -> r.rrd; bagged 13 -> bag" in out
    assert f"{t} 4" in out[3] and out[3].startswith("not recorded: 4 samples")
    assert out[4] == ("recording stopped at sim time 2.5 s: logger.max_size 1 MB reached; "
                      "7 samples after it not recorded")
    assert out[5] == ("lost 2 samples (realtime: the recorder could not keep up): 1 in transport, "
                      "1 dropped by the logger (queue full)")


def test_losses_are_counted_once_per_cause_and_never_negative(scenario: Any, tmp_path: Path) -> None:
    """The recorder's losses per key: what it dropped itself (exact) plus the gaps in its writers' sequences,
    no more gaps than the writers' own counts leave unexplained. A summary once said
    'lost 101920 (-3 in transport, 101923 dropped by the recorder)': the cap took in the dropped samples too."""
    from collections import Counter

    from hilsim.services.logger import LoggerService

    sc = scenario("arm", {"logger.run_dir": str(tmp_path / "run")})
    svc = LoggerService(sc)
    k = Keys.of(sc).clock
    # the writer says it published 1000; 600 arrived, 300 dropped at the full queue, gaps of 103 seen
    svc.accounts.published = {"h": {k: 1000}}
    lost = svc.accounts.judged_lost(Counter({k: 103}), Counter({k: 300}), Counter({k: 600}))
    assert lost[k] == 100 + 300  # 100 gaps at most (1000 - 600 - 300), the 300 dropped once
    # every sample the writer published arrived or was dropped: the gaps are no loss (forged numbers), drops are
    lost = svc.accounts.judged_lost(Counter({k: 5}), Counter({k: 400}), Counter({k: 600}))
    assert lost[k] == 400
    # the writer's count short of what arrived and was dropped (its count taken before its last samples):
    # the drops stand whole, the gaps count nothing (the old cap said 400 lost, 403 of them dropped: -3)
    lost = svc.accounts.judged_lost(Counter({k: 2}), Counter({k: 403}), Counter({k: 600}))
    assert lost[k] == 403
    # a key no service counts for: gaps and drops as seen
    other = Keys.of(sc).topic("cmd_vel")
    assert svc.accounts.judged_lost(Counter({other: 7}), Counter({other: 2}), Counter({other: 10}))[other] == 9
