"""Trust by default (docs/security.md, docs/reliability.md).

``hilsim up``'s router admits only the run's own processes (a user and password made for the run,
Zenoh's usrpwd authentication and access control by username); the summary's figures come from the
service that knows them (its final health), not from whatever sample arrives on a key; a lockstep
participant that goes silent (SIGSTOP) ends the run, or is killed and restarted under a restart
policy; two runs on one machine each have their own router and credentials and never cross-talk.
"""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
import zenoh
from test_restart import sim_now
from util import REPO, Observer, alive, wait_until

from hilsim.core import msgs, run_finder, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.scenario import load_scenario
from hilsim.launch.follow import Follower
from hilsim.launch.summary import summarise
from hilsim.services.physics import PhysicsService

HILSIM = [sys.executable, "-m", "hilsim.cli"]
TARGET_A = [0.5, -0.4, 0.2, 0.0, -0.5, 0.0]
TARGET_B = [-0.4, -0.2, 0.1, 0.0, -0.4, 0.0]


# ---------------------------------------------------------------- the summary's figures (unit)
class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    """What the follower reads of a Zenoh sample."""

    def __init__(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        self.key_expr, self.payload = key, _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)
        self.kind = zenoh.SampleKind.PUT


class _Declarations:
    """A stand-in session: which keys the follower subscribes to."""

    def __init__(self) -> None:
        self.keys: list[str] = []

    def declare_subscriber(self, key: str, *_: Any, **__: Any) -> None:
        self.keys.append(key)

    def liveliness(self) -> _Declarations:
        return self


def _health(sim_time: str, final: bool) -> bytes:
    vals = {"state": "done", "sim_time": sim_time, "real_time_factor": "1.000", **({"final": "1"} if final else {})}
    st = msgs.DiagnosticStatus(level=0, name="physics", message="done", hardware_id="hilsim/arm",
                               values=[msgs.KeyValue(key=k, value=v) for k, v in vals.items()])
    return msgs.encode(msgs.DiagnosticArray(header=msgs.header(0), status=[st]))


def test_the_summary_takes_sim_time_from_physics_final_health(tmp_path: Path, capsys: Any) -> None:
    """Physics' final health (its last word, at its exit) is what the summary says, whatever comes later
    on its key: a copy forged with its gid and the next sequence number (believed as physics' own, as
    only the credentials can keep such a writer out) or a stranger's; and nothing on /clock is read."""
    sc = load_scenario("arm", {"services": ["physics"], "task.targets": [], "duration": 9.0})
    keys = Keys.of(sc)
    prov = Provenance()
    gid = transport.new_gid()
    prov.announce(keys.health("physics"), gid)  # physics' health writer, as its graph token says
    lock, changed = threading.Lock(), threading.Event()
    f = Follower(sc, keys, [sc.robot], prov, lock=lock, changed=changed, say=lambda _: None)
    decl = _Declarations()
    f.subscribe(decl)  # type: ignore[arg-type]
    assert not any(k.startswith(keys.clock.split("/")[0] + "/clock") for k in decl.keys), decl.keys
    key = keys.health("physics")
    f._on_health(_Sample(key, _health("5.000", False), transport.attachment_bytes(1, gid)))  # type: ignore[arg-type]
    f._on_health(_Sample(key, _health("9.000", True), transport.attachment_bytes(2, gid)))  # type: ignore[arg-type]
    # later: the forged copy (physics' gid, the next number) and a stranger's
    f._on_health(_Sample(key, _health("99.000", False), transport.attachment_bytes(3, gid)))  # type: ignore[arg-type]
    f._on_health(_Sample(key, _health("77.000", True),  # type: ignore[arg-type]
                         transport.attachment_bytes(9, transport.new_gid())))
    assert f.outcome.health["physics"]["sim_time"] == "9.000"
    assert f.untrusted == 1

    class Finished:  # the launcher, as the summary reads it: no recorder on this host
        def __init__(self) -> None:
            self.sc, self.outcome, self.robots, self.local = sc, f.outcome, [sc.robot], []
            self.run_dir, self.untrusted = tmp_path, f.untrusted

    summarise(Finished())
    out = capsys.readouterr().out
    assert "  sim time 9.000 s, real-time factor 1.000" in out, out


def test_a_forged_writer_is_believed_only_where_the_credentials_let_it_in() -> None:
    """The limit the router's access control is there for (docs/security.md): a writer's gid and sequence
    number are public, and a sample sent with them is indistinguishable from the writer's own, so it is
    believed. It cannot keep the writer's own sample out: that one, the same number with another payload,
    is delivered too, and counted as suspect (hilsim.core.provenance)."""
    prov, key, gid = Provenance(), "0/clock/rosgraph_msgs::msg::dds_::Clock_/RIHS01_x", transport.new_gid()
    prov.announce(key, gid)
    assert prov.check(key, transport.Attachment(1, 0, gid), b"real 1") == (None, 0)
    assert prov.check(key, transport.Attachment(2, 0, gid), b"forged 2") == (None, 0)  # forged: believed
    assert prov.check(key, transport.Attachment(2, 0, gid), b"real 2") == (None, 0)  # the real one: delivered
    assert prov.suspect[key] == 1
    why, _ = prov.check(key, transport.Attachment(2, 0, gid), b"forged 2")  # a replay of the first: a duplicate
    assert why is not None and "duplicate" in why


# ---------------------------------------------------------------- a silent lockstep participant (physics)
@pytest.mark.parametrize("policy", ["no", "on-failure"])
def test_a_participant_gone_silent_is_a_fault_or_named_for_a_restart(scenario: Any, session: zenoh.Session,
                                                                      run_service: Any, policy: str) -> None:
    """A participant whose process stops (SIGSTOP) loses its session when the lease runs out: its token
    goes as if it had died, but no process exits and nothing restarts it. Physics, paused for it, waits
    ``clock.ack_timeout``, then: no restart policy, a fault naming it and "stalled" (hilsim up ends the
    run); restart policy on-failure, it names it in health (``silent``) for hilsim up to kill and restart,
    a warning, no fault. (Before: paused for ever.)"""
    sc = scenario("arm", {"services": ["physics", "controller"], "clock.ack_timeout": 1.0,
                          "restart.services": {"default": policy}})
    keys = Keys.of(sc)
    health: list[dict[str, str]] = []
    step0 = threading.Event()

    def on_health(s: zenoh.Sample) -> None:
        h = msgs.decode(msgs.DiagnosticArray, s.payload.to_bytes())
        health.append({kv.key: kv.value for kv in h.status[0].values})

    subs = [session.declare_subscriber(keys.health("physics"), on_health),
            session.declare_subscriber(keys.clock, lambda _: step0.set())]
    lockstep = session.liveliness().declare_token(keys.lockstep("controller", 1, 0, "joint_commands",
                                                                transport.new_gid().hex()))
    alive = session.liveliness().declare_token(keys.alive("controller"))
    try:
        with run_service(PhysicsService(sc)):
            assert step0.wait(15), "physics never published step 0"
            time.sleep(0.2)
            alive.undeclare()  # the lease ran out: gone, though its process never exited
            lockstep.undeclare()
            # 20 s: the stall was not yet in physics' health after 8 s once, under CI's load
            if policy == "no":
                assert wait_until(lambda: any(h.get("state") == "stalled" for h in health), 20), health
                h = next(h for h in health if h.get("state") == "stalled")
                assert "controller left at t=0.000s and did not come back" in h["last_error"], h
                assert h["errors"] == "1"
            else:
                assert wait_until(lambda: any(h.get("silent") == "controller" for h in health), 20), health
                h = next(h for h in health if h.get("silent") == "controller")
                assert h["state"] == "paused" and h["errors"] == "0", h
    finally:
        for s in subs:
            s.undeclare()


# ---------------------------------------------------------------- end to end
class Run:
    """``hilsim up`` in the background, its output read as it comes."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([*HILSIM, "up", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, cwd=REPO, start_new_session=True)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def out(self) -> str:
        return "".join(self.lines)

    def wait_line(self, start: str, timeout: float) -> str:
        assert wait_until(lambda: any(ln.startswith(start) for ln in self.lines) or self.proc.poll() is not None,
                          timeout), self.out
        line = next((ln for ln in self.lines if ln.startswith(start)), None)
        assert line is not None, self.out
        return line

    def pid_of(self, service: str) -> int:
        return int(self.wait_line("ready:", 120).split(f"{service} (pid ")[1].split(")")[0])

    def finish(self, timeout: float) -> int:
        try:
            rc = self.proc.wait(timeout)
        finally:
            self.kill()
        self.reader.join(5)
        return rc

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


def _physics_nodes(session: zenoh.Session) -> set[str]:
    """The Zenoh ids of the sessions with a ROS 2 node named physics (rmw_zenoh's node tokens)."""
    replies = session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
    keys = [str(r.ok.key_expr) for r in replies if r.ok is not None]
    return {k.split("/")[2] for k in keys if k.split("/")[5] == "NN" and k.endswith("/physics")}


def _private(path: Path) -> bool:
    return path.is_file() and stat.S_IMODE(path.stat().st_mode) == 0o600


def test_two_runs_each_admit_only_their_own_processes_and_never_cross_talk(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Two ``hilsim up`` at once, with the same keys: each has its own router (the second on a free port,
    saying so) and its own user and password, written 0600 (also as a ROS 2 node's
    ``ZENOH_SESSION_CONFIG_URI``) and found by this user's tools through a 0600 pointer file. A Zenoh
    session without them cannot connect (client) or gets nothing (peer); a guest (``zenoh.guests: read``)
    reads but cannot write. Each run sees only its own nodes, reaches its goal (sent by ``hilsim goal``,
    which found the credentials itself), and records only its own samples: the recorder received exactly
    what its physics says it published."""
    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    # this test's pointers apart from those of other runs of this user on the machine (its processes inherit it)
    (tmp_path / "xdg").mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    # lockstep: the recorder takes every sample physics published (an interactive run is realtime by default)
    a = Run("arm", "--interactive", "--clock", "lockstep", "--out", str(a_dir))
    b: Run | None = None
    sessions: list[zenoh.Session] = []
    try:
        ep_a = a.wait_line("zenoh router:", 60).split()[2]
        b = Run("arm", "--interactive", "--clock", "lockstep", "--out", str(b_dir), "--set", "zenoh.guests=read")
        ep_b = b.wait_line("zenoh router:", 60).split()[2]
        a.wait_line("ready:", 120)
        b.wait_line("ready:", 120)
        assert ep_a != ep_b
        if ep_a.endswith(":7447"):  # the second takes a free port and says so
            assert f"port 7447 is taken (another simulation?); using {ep_b}" in b.out, b.out
        # the credentials: written 0600, pointed to (0600) by port for this user's tools
        for d, ep in ((a_dir, ep_a), (b_dir, ep_b)):
            assert _private(d / "zenoh-client.json5") and _private(d / "zenoh-users.txt")
            pointer = run_finder.pointer_path(int(ep.rsplit(":", 1)[1]))
            assert _private(pointer) and json.loads(pointer.read_text())["run_dir"] == str(d.resolve())
            conf = json.loads((d / "zenoh-client.json5").read_text())
            assert conf["mode"] == "client" and conf["connect"]["endpoints"] == [ep]
            assert conf["timestamping"]["enabled"]["client"] is True
        assert not (a_dir / "zenoh-guest.json5").exists() and (b_dir / "zenoh-guest.json5").is_file()
        # without them: a client cannot connect, a peer connects to nothing and hears nothing
        with pytest.raises(ConnectionError):
            transport.open_session(ZenohConfig(mode="client", connect=[ep_a]))
        stranger = transport.open_session(ZenohConfig(connect=[ep_a]))
        sessions.append(stranger)
        heard: list[str] = []
        stranger.declare_subscriber("**", lambda s: heard.append(str(s.key_expr)))
        time.sleep(1.5)
        assert not heard and not list(stranger.info.routers_zid()) and not _physics_nodes(stranger)
        # with them, as a ROS 2 node takes them (ZENOH_SESSION_CONFIG_URI): each run's own physics only
        for d in (a_dir, b_dir):
            s = zenoh.open(zenoh.Config.from_file(str(d / "zenoh-client.json5")))
            sessions.append(s)
            assert len(_physics_nodes(s)) == 1
        # B's guest reads, but what it writes reaches nobody; the tools' does, on a key a person commands (the
        # control), and not on the clock, which is physics' (docs/security.md)
        member, guest = sessions[-1], zenoh.open(zenoh.Config.from_file(str(b_dir / "zenoh-guest.json5")))
        sessions.append(guest)
        got: list[str] = []
        clock_seen = threading.Event()
        cmd_vel = Keys().topic("cmd_vel")
        watch = zenoh.open(zenoh.Config.from_file(str(b_dir / "zenoh-client.json5")))  # not the writers' own session
        sessions.append(watch)
        watch.declare_subscriber(cmd_vel, lambda s: got.append(s.payload.to_string()))
        watch.declare_subscriber(Keys().clock, lambda s: got.append(s.payload.to_string()) if s.attachment is None
                                 else None)
        guest.declare_subscriber(Keys().clock, lambda _: clock_seen.set())
        time.sleep(0.5)
        guest.put(cmd_vel, "guest")
        member.put(cmd_vel, "member")
        member.put(Keys().clock, "tools on the clock")
        time.sleep(0.5)
        assert got == ["member"] and clock_seen.wait(5)
        # every process its own identity, written 0600 in a directory only this user may enter
        for d in (a_dir, b_dir):
            ids = d / transport.IDENTITIES_DIR
            assert stat.S_IMODE(ids.stat().st_mode) == 0o700
            assert {f.name for f in ids.iterdir()} >= {"physics.json5", "controller.json5", "launcher.json5"}
            assert all(_private(f) for f in ids.iterdir())
        # the tools without --connect or --run, two runs of this user up: they ask which, never guess
        both = subprocess.run([*HILSIM, "topic", "list"], capture_output=True, text=True, timeout=60, cwd=REPO,
                              stdin=subprocess.DEVNULL)
        assert both.returncode == 2 and "2 runs of yours are up" in both.stderr, both
        assert str(a_dir.resolve()) in both.stderr and str(b_dir.resolve()) in both.stderr, both.stderr
        # physics' final health in each run, with its counts of what it published
        finals: dict[str, dict[str, str]] = {}

        def on_final(run: str) -> Any:
            def cb(s: zenoh.Sample) -> None:
                h = msgs.decode(msgs.DiagnosticArray, s.payload.to_bytes())
                vals = {kv.key: kv.value for kv in h.status[0].values}
                if vals.get("final") == "1":
                    finals[run] = vals
            return cb

        sessions[1].declare_subscriber(Keys().health("physics"), on_final("a"))
        member.declare_subscriber(Keys().health("physics"), on_final("b"))
        # this user's tools find each run's credentials by its port
        goals = [subprocess.Popen([*HILSIM, "goal", "arm", "--joints", *map(str, t), "--connect", ep, "--timeout",
                                   "150"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
                 for t, ep in ((TARGET_A, ep_a), (TARGET_B, ep_b))]
        listed = subprocess.run([*HILSIM, "topic", "list", "--connect", ep_b], capture_output=True, text=True,
                                timeout=60, cwd=REPO)
        assert "/arm/joint_states" in listed.stdout, listed
        done = [g.communicate(timeout=200)[0] for g in goals]
        assert all(g.returncode == 0 for g in goals), done
        for r in (a, b):
            r.proc.send_signal(signal.SIGINT)
        assert a.finish(120) == 0, a.out
        assert b.finish(120) == 0, b.out
        assert wait_until(lambda: len(finals) == 2, 5), finals
    finally:
        for s in sessions:
            s.close()
        for r in (a, b):
            if r is not None:
                r.kill()
    for r, d, run in ((a, a_dir, "a"), (b, b_dir, "b")):
        assert "reached" in r.out and "FAILED" not in r.out, r.out
        counts = json.loads((d / "record_summary.json").read_text())
        published = {k[len("published:"):]: int(v) for k, v in finals[run].items() if k.startswith("published:")}
        clock = Keys().clock
        assert published[clock] > 100, published
        for key, n in published.items():  # the health key: its final sample is recorded too, or not yet
            if key in counts and "/health/" not in key:
                assert counts[key]["received"] == n, (run, key, counts[key], n)
        # its pointer is gone with it
        assert not run_finder.pointer_path(int((ep_a if run == "a" else ep_b).rsplit(":", 1)[1])).exists()


@pytest.mark.parametrize("policy", ["no", "on-failure"])
def test_a_stopped_controller_ends_the_run_or_is_restarted(tmp_path: Path, policy: str) -> None:
    """SIGSTOP on the controller in a lockstep run (clock.ack_timeout 6 s: the planner's first plan, capped at
    0.5 s of wall time, took 3.1 s on a loaded machine): without a restart policy a
    fault names it, everything stops, the exit code is non-zero and the recording is whole, with no loss
    invented by stopping it (it is killed, not resumed); with ``restart: {services: {default:
    on-failure}}`` it is killed (SIGKILL: a stopped process cannot restart itself) and started again, and
    the target is reached."""
    run = tmp_path / "run"
    r = Run("arm", "--out", str(run), "--set", "clock.ack_timeout=6", "--set", "planner.planning_time=0.5",
            "--set", f"task.targets=[{TARGET_A}]",
            "--set", f"restart.services.default={policy}")
    obs: Observer | None = None
    try:
        ep = r.wait_line("zenoh router:", 60).split()[2]
        pid = r.pid_of("controller")
        procs = psutil.Process(r.proc.pid).children(recursive=True)
        obs = Observer(ep, run / "zenoh-client.json5")
        # stopped at a sim time the test waits for (the arm moving), not after a wall-clock sleep
        assert wait_until(lambda: sim_now(obs) >= 0.3e9, 60), r.out
        os.kill(pid, signal.SIGSTOP)
        with obs.lock:
            assert not obs.results, f"the task ended before the stop: {obs.results}"
        rc = r.finish(150)
    finally:
        r.kill()
        if obs is not None:
            obs.close()
    out = r.out
    if policy == "no":
        assert rc == 1, out
        assert "fault: physics: no lockstep acknowledgement from controller" in out, out
        assert f"killing controller (pid {pid}): silent" in out, out
        assert "result: FAILED" in out
    else:
        assert rc == 0, out
        assert f"error: controller (pid {pid}) silent for clock.ack_timeout (6 s)" in out, out
        assert "restarted controller" in out and "targets reached: 1/1" in out, out
    # the recording is whole, and the stop invented no loss
    counts = json.loads((run / "record_summary.json").read_text())
    assert all(v["received"] == v["recorded"] == v["bagged"] for v in counts.values()), counts
    assert not any(v["lost"] for v in counts.values()), counts
    assert " lost " not in out and "never reached the recorder" not in out and "MISMATCH" not in out, out
    time.sleep(0.5)
    assert not [p for p in procs if alive(p)], "processes left"
