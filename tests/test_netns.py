"""Several machines without docker: network namespaces joined by veth pairs stand in for hosts.

    ns "a" (workstation): hilsim router on 10.x.1.1 and 10.x.2.1, physics and sensors
    ns "b" (robot computer): controller and logger, reaching the router over veth a<->b only
    ns "c" (planning host): the planner, over veth a<->c only (b and c cannot reach each other)

Each host runs ``hilsim up arm --only … --router tcp/<a's address>:7447``; the test itself sits in
the root namespace with a third veth to "a" and judges the run by physics' truth as a Zenoh
client there. Namespaces need root (CAP_SYS_ADMIN) and ``ip`` (iproute2): without them the test
skips and says why, except that under ``CI=true`` as root a missing ``ip`` is a failure
(scripts/test.sh installs it). Every namespace and process is removed even when the test fails.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from util import LEAN, REPO, Observer, sim_rate

from hilsim.core import transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario

pytestmark = pytest.mark.e2e
TARGET = [0.5, -0.4, 0.2, 0.0, -0.5, 0.0]
LEAN_ARGS = ["--set", f"task.targets=[{TARGET}]"]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


class Hosts:
    """Three namespaces a, b, c and the root one, wired as a star around a (one /30 per veth)."""

    def __init__(self) -> None:
        tag = f"{os.getpid() % 100000}"
        self.ns = {h: f"hs{tag}{h}" for h in "abc"}
        net = 100 + os.getpid() % 100  # 10.<net>.x.y: another test run's pid gives another net
        self.router_addr = {"b": f"10.{net}.1.1", "c": f"10.{net}.2.1", "root": f"10.{net}.3.1"}
        self._links = [("b", f"hs{tag}ab", f"hs{tag}ba", 1), ("c", f"hs{tag}ac", f"hs{tag}ca", 2),
                       ("root", f"hs{tag}ar", f"hs{tag}ra", 3)]
        self._net = net
        self.made: list[str] = []
        self.root_link = ""

    def make(self) -> None:
        for ns in self.ns.values():
            _ip("netns", "add", ns)
            self.made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        a = self.ns["a"]
        for other, in_a, in_other, i in self._links:
            _ip("link", "add", in_a, "type", "veth", "peer", "name", in_other)
            if other == "root":
                self.root_link = in_other
            _ip("link", "set", in_a, "netns", a)
            _ip("-n", a, "addr", "add", f"10.{self._net}.{i}.1/30", "dev", in_a)
            _ip("-n", a, "link", "set", in_a, "up")
            if other == "root":
                _ip("addr", "add", f"10.{self._net}.{i}.2/30", "dev", in_other)
                _ip("link", "set", in_other, "up")
            else:
                _ip("link", "set", in_other, "netns", self.ns[other])
                _ip("-n", self.ns[other], "addr", "add", f"10.{self._net}.{i}.2/30", "dev", in_other)
                _ip("-n", self.ns[other], "link", "set", in_other, "up")

    def remove(self) -> None:
        for ns in self.made:
            # anything still running in it (a process the test lost track of) goes first
            pids = _ip("netns", "pids", ns, check=False).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", ns, check=False)
        if self.root_link:
            _ip("link", "del", self.root_link, check=False)  # gone with ns a already, unless a failed early
        self.made.clear()

    def spawn(self, host: str, *args: str, log: Path) -> subprocess.Popen[str]:
        """``hilsim ARGS`` inside host's namespace, in its own process group (killed as a whole)."""
        with open(log, "w") as f:
            return subprocess.Popen(["ip", "netns", "exec", self.ns[host], sys.executable, "-m", "hilsim.cli", *args],
                                    stdout=f, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                                    start_new_session=True)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    ci = os.environ.get("CI") == "true"
    if shutil.which("ip") is None:
        if ci and os.geteuid() == 0:
            pytest.fail("`ip` (iproute2) is missing: scripts/test.sh installs it; as root under CI=true this "
                        "test must run")
        pytest.skip("`ip` (iproute2) is not installed: cannot make network namespaces")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (run as root, or in CI as root, to prove several hosts)")
    h = Hosts()
    try:
        try:
            h.make()
        except subprocess.CalledProcessError as e:
            h.remove()
            pytest.skip(f"cannot make network namespaces here ({' '.join(e.cmd)}: {e.stderr.strip()})")
        yield h
    finally:
        h.remove()
        leftover = [ns for ns in _ip("netns", "list", check=False).stdout.split() if ns in h.ns.values()]
        assert not leftover, f"namespaces left behind: {leftover}"


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def _wait_all(procs: dict[str, subprocess.Popen[str]], timeout: float) -> None:
    end = time.monotonic() + timeout
    for name, p in procs.items():
        try:
            p.wait(timeout=max(1.0, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            raise AssertionError(f"hilsim up on host {name} still running after {timeout:.0f} s") from None


def _run_across_hosts(hosts: Hosts, tmp_path: Path, scenario: str, extra: list[str]) -> tuple[dict[str, str], Observer]:
    """Router + physics + sensors on a, controller + logger on b, planner on c; returns each
    host's launcher output and the test's observer (closed by the caller)."""
    port = 7447
    router_eps = {h: f"tcp/{addr}:{port}" for h, addr in hosts.router_addr.items()}
    procs: list[subprocess.Popen[str]] = []
    obs: Observer | None = None
    try:
        # the router listens on a's two host-facing addresses and the test's
        listen = ",".join(router_eps.values())
        cfg = tmp_path / "router.json5"
        cfg.write_text(json.dumps({"mode": "router", "listen": {"endpoints": listen.split(",")},
                                   "scouting": {"multicast": {"enabled": False}}}))
        router = hosts.spawn("a", "router", "--config", str(cfg), log=tmp_path / "router.log")
        procs.append(router)
        # the test's own view, as a client (never a peer gossiping into another test's network)
        ep = router_eps["root"]
        deadline = time.monotonic() + 30
        while obs is None:
            try:
                obs = _client_observer(ep)
            except ConnectionError:
                if time.monotonic() > deadline or router.poll() is not None:
                    raise AssertionError("router did not come up: " + (tmp_path / "router.log").read_text()) from None
                time.sleep(0.3)
        b_only = "controller" if "--no-logger" in extra else "controller,logger"
        ups = {
            "a": hosts.spawn("a", "up", scenario, "--only", "physics,sensors", "--router", router_eps["root"],
                             "--out", str(tmp_path / "a"), *extra, log=tmp_path / "a.log"),
            "b": hosts.spawn("b", "up", scenario, "--only", b_only, "--router", router_eps["b"],
                             "--out", str(tmp_path / "b"), *extra, log=tmp_path / "b.log"),
            "c": hosts.spawn("c", "up", scenario, "--only", "planner", "--router", router_eps["c"],
                             "--out", str(tmp_path / "c"), *extra, log=tmp_path / "c.log"),
        }
        procs.extend(ups.values())
        try:
            _wait_all(ups, 240)
        except AssertionError as e:
            logs = "\n".join(f"--- {h}:\n{(tmp_path / f'{h}.log').read_text()}" for h in ups)
            raise AssertionError(f"{e}\n{logs}") from None
        time.sleep(0.3)
        out = {h: (tmp_path / f"{h}.log").read_text() for h in ups}
        for h, p in ups.items():
            assert p.returncode == 0, f"host {h}: exit {p.returncode}\n" + "\n".join(
                f"--- {k}:\n{v}" for k, v in out.items())
        return out, obs
    except BaseException:
        if obs is not None:
            obs.close()
        raise
    finally:
        _stop(procs)


def _client_observer(endpoint: str) -> Observer:
    """tests/util.py's Observer, but a Zenoh client of the router (see _run_across_hosts)."""
    real = transport.open_session

    def as_client(zc: ZenohConfig) -> object:
        return real(ZenohConfig(mode="client", connect=zc.connect))

    transport.open_session = as_client  # type: ignore[assignment]
    try:
        return Observer(endpoint)
    finally:
        transport.open_session = real  # type: ignore[assignment]


def _judge(obs: Observer, out: dict[str, str], scenario: str) -> None:
    sc = load_scenario(scenario)
    stamp, ok = obs.results["task-1"]
    assert ok, obs.results
    # the physics truth when the planner declared the target reached, seen from the root namespace
    err = np.abs(obs.truth_at(stamp) - np.asarray(TARGET)).max()
    assert err <= sc.task.tolerance + 0.002, err
    with obs.lock:
        assert len(obs.truth) > 500, len(obs.truth)
    for h, text in out.items():
        assert "targets reached: 1/1" in text and "result: OK" in text, (h, text)
    assert "ready: physics" in out["a"] or "ready: sensors" in out["a"], out["a"]
    assert "remote: " in out["b"] and "planner" in out["b"].split("remote: ")[1].splitlines()[0], out["b"]


def test_arm_across_three_hosts_in_lockstep(hosts: Hosts, tmp_path: Path) -> None:
    """Lockstep through one router across three namespaces: the target is reached in the truth, and
    the recorder on host b (whose launcher alone summarises the recording) lost nothing."""
    out, obs = _run_across_hosts(hosts, tmp_path, "arm", LEAN_ARGS)
    try:
        _judge(obs, out, "arm")
    finally:
        obs.close()
    assert "recorded" in out["b"] and "recording summary missing" not in out["b"], out["b"]
    assert "recording" not in out["a"] and "recording" not in out["c"], out["a"]
    counts = json.loads((tmp_path / "b" / "record_summary.json").read_text())
    assert counts[Keys().truth("joint_states")]["received"] > 500
    assert all(v["received"] == v["recorded"] for v in counts.values()), counts
    # the planner's host saw the others only through the router (no route from c to b exists)
    assert "remote: " in out["c"], out["c"]


def test_arm_across_three_hosts_in_realtime(hosts: Hosts, tmp_path: Path) -> None:
    """The lean arm in realtime across the same three hosts, without a recorder: the target is
    reached in the truth, and sim time kept the wall clock as the test measured it (truth stamps
    against their arrival in the root namespace), every sample through the router."""
    # clock.max_age: a realtime service drops a stream's sample older than this as stale (0.05 s by
    # default, one host); two hops through the router on a loaded 2-core machine take longer now and
    # then, as docs/deployment.md advises for several hosts
    out, obs = _run_across_hosts(hosts, tmp_path, LEAN, ["--clock", "realtime", "--no-logger",
                                                         "--set", "clock.max_age=0.25", *LEAN_ARGS])
    try:
        _judge(obs, out, LEAN)
        with obs.lock:
            marks = list(obs.truth_wall)
    finally:
        obs.close()
    assert all("clock realtime" in text for text in out.values()), out
    # from the first sim second on (start-up behind us) to the end
    assert marks[-1][0] - 1_000_000_000 > 1.5e9, marks[-1]
    rate = sim_rate(marks)
    assert 0.9 <= rate <= 1.1, rate


def test_only_names_services_of_the_scenario() -> None:
    from hilsim.core.config import ConfigError
    from hilsim.launch.launcher import local_units

    sc = load_scenario("arm")
    assert local_units(sc, ["logger", "physics"]) == ["physics", "logger"]
    assert local_units(sc, None) == sc.launch_units()
    with pytest.raises(ConfigError, match=r"--only physics,radar: radar not among this scenario's services"):
        local_units(sc, ["physics", "radar"])
    composed = load_scenario("arm", {"compose": [["physics", "sensors", "controller"]]})
    assert local_units(composed, ["physics+sensors+controller"]) == ["physics+sensors+controller"]
    with pytest.raises(ConfigError, match="runs as one process"):
        local_units(composed, ["physics"])


def test_missing_remote_services_are_named_and_nothing_is_left(tmp_path: Path) -> None:
    """On loopback: only physics here, nobody else anywhere; the launcher says who it is waiting
    for, gives up after --wait with one line naming them and the router, and stops physics."""
    import psutil

    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    try:
        p = subprocess.run([sys.executable, "-m", "hilsim.cli", "up", "arm", "--only", "physics", "--router", ep,
                            "--wait", "7", "--no-logger", "--out", str(tmp_path / "run")],
                           capture_output=True, text=True, cwd=REPO, timeout=120)
    finally:
        router.close()
    assert p.returncode == 1, p.stdout + p.stderr
    assert "waiting for: sensors (remote), controller (remote), planner (remote)" in p.stdout, p.stdout
    err = next(ln for ln in p.stdout.splitlines() if ln.startswith("error:"))
    assert "within 7s: sensors (remote), controller (remote), planner (remote)" in err and ep in err, err
    assert "physics" not in err  # it came up here
    left = [q for q in psutil.process_iter(["cmdline"]) if str(tmp_path) in " ".join(q.info["cmdline"] or [])]
    assert not left, left
