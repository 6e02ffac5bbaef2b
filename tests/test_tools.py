"""How the command-line tools find a running simulation (hilsim.core.transport.tool_*)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from hilsim.cli import main as cli
from hilsim.core import msgs, run_finder, transport
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys
from hilsim.record.bag import BagWriter
from hilsim.record.bag_read import write_metadata


def test_tool_endpoints_and_prefix(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HILSIM_ZENOH_CONNECT", raising=False)
    monkeypatch.delenv("HILSIM_PREFIX", raising=False)
    assert run_finder.tool_endpoints() == ["tcp/127.0.0.1:7447"]
    assert run_finder.tool_prefix() == "hilsim"
    monkeypatch.setenv("HILSIM_ZENOH_CONNECT", "tcp/192.0.2.1:7447, tcp/192.0.2.2:7447,")
    monkeypatch.setenv("HILSIM_PREFIX", "lab2")
    assert run_finder.tool_endpoints() == ["tcp/192.0.2.1:7447", "tcp/192.0.2.2:7447"]
    assert run_finder.tool_prefix() == "lab2"
    # the command line wins over the environment
    assert run_finder.tool_endpoints("tcp/127.0.0.1:9000") == ["tcp/127.0.0.1:9000"]
    assert run_finder.tool_prefix("mine") == "mine"


def test_wait_for_service_sees_liveliness(router: str) -> None:
    keys = Keys("hilsim", "arm")
    with run_finder.open_tool_session(router) as tool, run_finder.open_tool_session(router) as svc:
        assert not transport.wait_for_service(tool, keys, "controller", 0.2)
        token = svc.liveliness().declare_token(keys.alive("controller"))
        try:
            assert transport.wait_for_service(tool, keys, "controller", 5.0)
        finally:
            token.undeclare()


# ---------------------------------------------------------------- which run a tool joins (docs/tools.md)
@pytest.fixture
def runs_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[[str], Path]]:
    """Runs of this user that are up, as the tools see them: a pointer file each (0600), written by a
    launcher that still runs (a process with ``hilsim`` in its command line), naming its directory,
    scenario, router endpoint and the tools' credentials."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    (tmp_path / "xdg").mkdir()
    for name in ("HILSIM_ZENOH_CONNECT", "HILSIM_ZENOH_AUTH", "HILSIM_TLS_ROOT_CA"):
        monkeypatch.delenv(name, raising=False)
    launcher = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", "hilsim-up"])
    # a process just started may show an empty command line for a moment (a real launcher writes its
    # pointer long after): wait until it is the launcher the tools look for
    cmdline = Path(f"/proc/{launcher.pid}/cmdline")
    for _ in range(500):
        if b"hilsim-up" in cmdline.read_bytes():
            break
        time.sleep(0.01)

    def up(name: str) -> Path:
        run = tmp_path / name
        run.mkdir()
        ep = f"tcp/127.0.0.1:{transport.free_port()}"
        client = run / transport.CLIENT_CONFIG
        transport.write_private(client, transport.client_config_text(ep, transport.Credentials("tools", "pw")))
        ptr = run_finder.pointer_path(run_finder.loopback_port(ep) or 0)
        ptr.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        transport.write_private(ptr, json.dumps({"endpoint": ep, "run_dir": str(run.resolve()), "scenario": "arm",
                                                 "client_config": str(client.resolve()), "pid": launcher.pid}))
        return run

    try:
        yield up
    finally:
        launcher.kill()
        launcher.wait()


def test_a_tool_names_the_run_it_joins_and_never_guesses_between_two(runs_up: Callable[[str], Path],
                                                                     monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """One run of yours up: every tool joins it, wherever its port, and says which (directory, scenario,
    endpoint). Two: without --run or --connect a tool lists them and asks on a terminal, and otherwise
    stops in one line; --run DIR picks one, and a --run that is not up is refused."""
    a = runs_up("a")
    t = run_finder.tool_target(tool="hilsim topic list")
    assert t.run is not None and t.run.run_dir == a.resolve(), _pointers_as_read()
    assert t.zenoh.auth == (a / transport.CLIENT_CONFIG).resolve()
    # a client of the router, against a plain one too: one path, samples in order (docs/tools.md)
    assert t.zenoh.mode == "client" and run_finder.tool_target("tcp/127.0.0.1:1").zenoh.mode == "client"
    said = t.describe()
    assert said.startswith("joined run ") and str(a) in said and "(scenario arm) at tcp/" in said, said
    b = runs_up("b")
    with pytest.raises(ConfigError, match=r"hilsim topic list: 2 runs of yours are up \(run .*; run .*\): say which "
                                          r"with --run DIR or --connect ENDPOINT"):
        run_finder.tool_target(tool="hilsim topic list")
    assert cli(["topic", "list"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "2 runs of yours are up" in err and str(a) in err and str(b) in err, err
    assert run_finder.tool_target(run=b).run.run_dir == b.resolve()  # type: ignore[union-attr]
    ep_a = run_finder.tool_target(run=a).zenoh.connect
    assert run_finder.tool_target(",".join(ep_a)).run.run_dir == a.resolve()  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match=r"--run .*c: no run of yours is up there"):
        run_finder.tool_target(run=a.parent / "c")
    # on a terminal: asked
    monkeypatch.setattr(sys, "stdin", _Tty("2\n"))
    monkeypatch.setattr(sys, "stderr", _Tty(""))
    assert run_finder.tool_target(tool="hilsim goal").run.run_dir == b.resolve()  # type: ignore[union-attr]
    assert "1. run " in sys.stderr.getvalue() and "which one (1-2)?" in sys.stderr.getvalue()


def _pointers_as_read() -> list[tuple[str, int, str, int, str, bool, bool]]:
    """Each pointer file as the tools judge it (owner, mode, launcher's command line, read): why none is up."""
    out = []
    for p in sorted(run_finder.pointer_dir().glob("*.json")):
        st = p.stat()
        pid = int(json.loads(p.read_text())["pid"])
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes() if Path(f"/proc/{pid}").exists() else b"(gone)"
        out.append((p.name, st.st_uid, oct(st.st_mode), os.getuid(), cmd.decode(errors="replace"),
                    p.name.endswith(f"-{run_finder._net_namespace()}.json"), run_finder.read_pointer(p) is not None))
    return out


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def _tiny_bag(path: Path, n: int = 200) -> Path:
    """A bag of ``n`` clock samples, 1 ms apart, and as many joint-state samples."""
    w = BagWriter(path)
    keys = Keys()
    js = msgs.encode(msgs.JointState(header=msgs.header(0), name=["j"], position=[0.0], velocity=[0.0], effort=[0.0]))
    for k in range(n):
        w.append((keys.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(k * 1_000_000))), (k + 1, 0, b"g" * 16), k))
        w.append((keys.topic("joint_states"), js, (k + 1, 0, b"h" * 16), k))
    w.flush()
    w.close()
    write_metadata(path)
    return path


def test_a_tool_against_an_empty_port_fails(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing listening there: play, topic and gains stop with an error saying plainly that no run is up (no
    "joined …" first), never report an empty success; the same mistake, the same exit code (2) in each, as goal."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    empty = f"tcp/127.0.0.1:{transport.free_port()}"
    assert cli(["play", str(_tiny_bag(tmp_path / "bag")), "--connect", empty, "--rate", "0"]) == 2
    err = capsys.readouterr().err
    assert f"hilsim play: no run is up: none of yours, and nothing answers at {empty}" in err, err
    assert "joined" not in err and "played " not in err, err
    assert cli(["topic", "list", "--connect", empty]) == 2
    err = capsys.readouterr().err
    assert f"hilsim topic list: no run is up: none of yours, and nothing answers at {empty}" in err, err
    assert "joined" not in err, err
    assert cli(["gains", "arm", "joint_2.kp=80", "--connect", empty]) == 2
    assert "no run is up" in capsys.readouterr().err
    assert cli(["gains", "arm"]) == 2  # reading back: from a run's files, and none is up
    assert "no run of yours is up" in capsys.readouterr().err
    # a mistake in what is asked: 2 before connecting anywhere
    assert cli(["gains", "arm", "kp=80", "--connect", empty]) == 2
    assert "'kp=80': expected JOINT.GAIN=NUMBER, a joint's name first" in capsys.readouterr().err
    assert cli(["gains", "arm", "joint_2.feedforward=-1", "--connect", empty]) == 2  # the controller's rule
    assert "hilsim gains: joint_2.feedforward: value -1.0 must be >= 0" in capsys.readouterr().err


def test_play_says_who_hears_it_and_counts_what_it_played(router: str, tmp_path: Path) -> None:
    """A key nobody subscribes to is said; stopped early, the summary counts the messages played and the sim
    time they span, not the bag's."""
    from hilsim.record.bag_read import open_bag
    from hilsim.tools.recording.play import Selector, play, schedule

    items = schedule(open_bag(_tiny_bag(tmp_path / "bag")), Selector(None), None, skip_clock=False)
    stop = threading.Event()
    with run_finder.open_tool_session(router) as s:
        sub = s.declare_subscriber(Keys().clock, lambda _: None)
        threading.Timer(0.6, stop.set).start()  # 0.1 s to announce, then 0.5 s of the 0.2 s bag at 0.25x
        res = play(s, items, domain=0, rate=0.25, delay=0.1, quiet=True, stop=stop)
        sub.undeclare()
    assert res["deaf"] == [Keys().topic("joint_states")]  # the clock has a subscriber, the joint states none
    assert 0 < res["messages"] < len(items) and res["keys"] == 2, res
    # what was played (the first `messages` of the schedule: exact, however late the stop came on a loaded
    # machine), not the bag's 0.199 s
    played = (items[res["messages"] - 1].sim_ns - items[0].sim_ns) / 1e9
    assert res["sim_s"] == pytest.approx(played, abs=1e-9) and res["sim_s"] < (items[-1].sim_ns - items[0].sim_ns) / 1e9


@pytest.mark.e2e
@pytest.mark.timeout(900)  # a tool's start reads the run's files: slow on a machine loaded many times over
def test_gains_read_back_and_say_old_to_new_and_goal_counts_joints_first(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run of yours up (its own router, its files): ``hilsim gains arm`` lists the gains the controller runs
    with, a change prints old -> new and is listed after; a joint the run's robot has not, and a goal with
    the wrong number of joints, are refused with exit code 2 before anything is sent."""
    import signal

    run = tmp_path / "run"
    up = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--interactive", "--out", str(run)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    lines: list[str] = []
    try:
        assert up.stdout is not None
        for line in up.stdout:
            lines.append(line)
            if line.startswith("ready:"):
                break
        assert any(ln.startswith("ready:") for ln in lines), "".join(lines)
        capsys.readouterr()

        def tool(*args: str) -> tuple[int, str, str]:
            rc = cli([*args, "--run", str(run)])
            got = capsys.readouterr()
            return rc, got.out, got.err

        rc, out, err = tool("gains", "arm")
        assert rc == 0, (out, err)
        row = next(ln.split() for ln in out.splitlines() if ln.startswith("joint_2 "))
        assert row[1:4] == ["32.81", "0", "5.594"], out  # config/arm.yaml's kp, ki, kd
        rc, out, err = tool("gains", "arm", "joint_2.kp=80")
        assert rc == 0 and "  joint_2.kp: 32.81 -> 80" in out, (out, err)
        rc, out, err = tool("gains", "arm")
        assert next(ln.split() for ln in out.splitlines() if ln.startswith("joint_2 "))[1] == "80", out
        rc, out, err = tool("gains", "arm", "joint_9.kp=1")
        assert rc == 2 and "unknown joint 'joint_9'" in err and "joined" not in err, (out, err)
        rc, out, err = tool("goal", "arm", "--joints", "0.1", "0.2")
        assert rc == 2 and "--joints: 2 values, but arm has 6 joints" in err, (out, err)
        assert "joined" not in err, err  # before connecting
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
            up.communicate()


def test_every_option_says_what_it_does() -> None:
    """Help text for every option and argument of every command (units and defaults where they have them),
    and ``hilsim --version``."""
    import argparse

    from hilsim import __version__
    from hilsim.cli import build_parser

    def silent(p: argparse.ArgumentParser, path: str) -> list[str]:
        out = []
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    out += silent(sp, f"{path} {name}")
            elif a.help is None:
                out.append(f"{path} {'/'.join(a.option_strings) or a.dest}")
        return out

    # `hilsim creds` is issue 41's (security): its names are positional and said by the command's help
    assert [m for m in silent(build_parser(), "hilsim") if not m.startswith("hilsim creds")] == []
    # the README's command table names every benchmark (bench ros2 was missing)
    bench = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["bench"]
    names = next(a for a in bench._actions if isinstance(a, argparse._SubParsersAction)).choices
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    assert [n for n in names if f"`hilsim bench {n}" not in readme] == []
    got = subprocess.run([sys.executable, "-m", "hilsim.cli", "--version"], capture_output=True, text=True, timeout=60)
    assert got.returncode == 0 and got.stdout.strip() == f"hilsim {__version__}", got
