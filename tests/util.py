"""Helpers shared by test modules (pytest puts this directory on sys.path)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from hilsim.core import geometry, msgs, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys

# The arm at half its rates (config/arm-lean.yaml): realtime end-to-end tests run on it, so a slow
# or busy 2-core CI machine still keeps the wall clock (at 1 kHz the pipeline needs most of 2 cores)
LEAN = str(Path(__file__).resolve().parent.parent / "config" / "arm-lean.yaml")


def wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll ``cond`` until it holds or ``timeout`` seconds pass; the last answer is returned."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def alive(p: Any) -> bool:
    """Whether the psutil process ``p`` still runs (a zombie does not); one that goes while asked is
    gone, not an error (``is_running`` and ``status`` are two reads of /proc)."""
    import psutil

    try:
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def sim_rate(marks: list[tuple[int, float]], from_ns: int = 1_000_000_000, window_s: float = 0.5) -> float:
    """Sim seconds per wall second from (sim stamp ns, wall arrival s) marks, from ``from_ns`` on.

    An arrival is the sample's instant on the wall clock plus a delivery delay that is never
    negative but comes and goes (a callback queue behind a busy core): the promptest arrival in
    the first and in the last ``window_s`` of sim time stand for the run's two ends, so a late
    last sample is not read as physics falling behind, while physics truly behind is still seen.
    """
    pts = [(s / 1e9, w) for s, w in marks if s >= from_ns]
    if len(pts) < 2:
        raise AssertionError(f"too few truth samples after {from_ns / 1e9:g} s of sim time: {len(pts)}")
    first, last = pts[0][0], pts[-1][0]
    sh, wh = min((p for p in pts if p[0] <= first + window_s), key=lambda p: p[1] - p[0])
    st, wt = min((p for p in pts if p[0] >= last - window_s), key=lambda p: p[1] - p[0])
    return (st - sh) / (wt - wh)


class Observer:
    """The test's own view of a run: physics truth, the joint server's reports, task results."""

    def __init__(self, endpoint: str, auth: Path | None = None) -> None:
        """``auth``: the run's credentials (``<run dir>/zenoh-client.json5``), for ``hilsim up``'s own router."""
        self.keys = Keys()
        self.session = transport.open_session(ZenohConfig(connect=[endpoint], auth=auth))
        self.lock = threading.Lock()
        self.truth: list[tuple[int, list[float]]] = []
        self.server: list[tuple[int, list[float]]] = []
        self.results: dict[str, tuple[int, bool]] = {}
        self.contacts: list[msgs.Contacts] = []
        self.truth_wall: list[tuple[int, float]] = []  # (sim stamp, wall time it arrived)
        s = self.session
        self.subs = [
            s.declare_subscriber(self.keys.truth("contacts"), self._on_contacts),
            s.declare_subscriber(self.keys.truth("joint_states"), self._on_truth),
            s.declare_subscriber(self.keys.server_state("motor-model"), self._on_server),
            s.declare_subscriber(self.keys.topic("planner/result"), self._on_result),
        ]

    def _on_truth(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is None:
            return
        with self.lock:
            self.truth.append((msgs.ns_of(m.header.stamp), list(m.position)))
            self.truth_wall.append((msgs.ns_of(m.header.stamp), time.monotonic()))

    def _on_server(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is None:
            return
        with self.lock:
            self.server.append((msgs.ns_of(m.header.stamp), list(m.position)))

    def _on_contacts(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.Contacts)
        if m is not None:
            with self.lock:
                self.contacts.append(m)

    def _on_result(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.MoveResult)
        if m is None:
            return
        with self.lock:
            self.results[m.goal_id] = (msgs.ns_of(m.header.stamp), m.success)

    @staticmethod
    def _decode(sample: zenoh.Sample, cls: type) -> Any:
        """Only well-formed samples from a hilsim writer (a test may run an injector)."""
        if transport.read_attachment(sample) is None:
            return None
        try:
            return msgs.decode(cls, sample.payload.to_bytes())
        except msgs.BadMessage:
            return None

    def truth_at(self, ns: int) -> np.ndarray:
        with self.lock:
            return np.array(min(self.truth, key=lambda t: abs(t[0] - ns))[1])

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


REPO = Path(__file__).resolve().parent.parent


def up(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=REPO, start_new_session=True)


@contextlib.contextmanager
def network_namespace(tag: str, *, ipv6: bool = True) -> Iterator[str]:
    """A fresh network namespace with only ``lo`` (up; ``ipv6=False``: IPv6 off), removed with
    every process in it afterwards; the test is skipped where there are none (root and ``ip``).
    Run a command in it with ``["ip", "netns", "exec", ns, …]``."""
    import pytest

    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("ip netns unavailable (needs root and iproute2)")
    ns = f"hs{tag}{os.getpid() % 100000}"

    def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)

    try:
        ip("netns", "add", ns)
    except subprocess.CalledProcessError as e:
        pytest.skip(f"ip netns unavailable here: {e.stderr.strip()}")
    try:
        ip("-n", ns, "link", "set", "lo", "up")
        if not ipv6:
            ip("netns", "exec", ns, "sysctl", "-qw", "net.ipv6.conf.all.disable_ipv6=1")
        yield ns
    finally:
        for pid in ip("netns", "pids", ns, check=False).stdout.split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
        ip("netns", "del", ns, check=False)


def until_ready(p: subprocess.Popen[str], lines: list[str]) -> str:
    """Read ``hilsim up``'s output into ``lines`` up to its ``ready:`` line (returned); fail with all it
    printed if it ends before."""
    assert p.stdout is not None
    for line in p.stdout:
        lines.append(line)
        if line.startswith("ready:"):
            return line
    raise AssertionError("".join(lines))


def finish(p: subprocess.Popen[str], timeout: float) -> str:
    """Wait for ``hilsim up`` to end; past ``timeout`` kill its process group and fail with
    everything it printed (a hang on a slow machine must say where it got to)."""
    try:
        out, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, _ = p.communicate()
        raise AssertionError(f"hilsim up still running after {timeout:.0f} s; it printed:\n{out}") from None
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    return out


ROVER = Keys("hilsim", "rover")


def yaw_of(o: msgs.Odometry) -> float:
    return geometry.yaw_of(o.pose.pose.orientation)


class Capture:
    """Raw samples of some keys, by key, in arrival order."""

    def __init__(self, endpoint: str, topics: list[str], keys: Keys = ROVER) -> None:
        self.session = transport.open_session(ZenohConfig(connect=[endpoint]))
        self.lock = threading.Lock()
        self.raw: dict[str, list[bytes]] = {t: [] for t in topics}
        self.subs = [self.session.declare_subscriber(keys.topic(t), self._make(t)) for t in topics]

    def _make(self, topic: str):  # type: ignore[no-untyped-def]
        def on(s: zenoh.Sample) -> None:
            with self.lock:
                self.raw[topic].append(s.payload.to_bytes())
        return on

    def decoded(self, topic: str, cls: type) -> list:  # type: ignore[type-arg]
        with self.lock:
            return [msgs.decode(cls, b) for b in self.raw[topic]]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


class UpRun:
    """``hilsim up ARGS --router ROUTER`` as its own process group, stopped with SIGINT like Ctrl-C."""

    def __init__(self, args: list[str], router: str, tmp_path: Path) -> None:
        self.p = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", *args, "--router", router,
                                   "--out", str(tmp_path / "run")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True, cwd=tmp_path, start_new_session=True)

    def stop(self) -> str:
        """Ctrl-C (SIGKILL after a minute); everything it printed."""
        if self.p.poll() is None:
            os.killpg(self.p.pid, signal.SIGINT)
        try:
            out, _ = self.p.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(self.p.pid, signal.SIGKILL)
            out, _ = self.p.communicate()
        return out



def ros2_python(distro: str, wait: float = 600.0) -> Path:
    """The Python of a real ROS 2 venv (``scripts/ros2-venvs.sh``: Kilted or Jazzy wheels), waiting for
    ``scripts/test.sh``'s install running beside the suite; skipped without it, failed under CI."""
    import pytest

    d = REPO / ".venv-ros2" / distro
    end = time.monotonic() + wait
    while not (d / ".ready").exists() and not (d / ".failed").exists() and time.monotonic() < end:
        try:
            os.kill(int((d / ".installing").read_text()), 0)  # its installer is still at it
        except FileNotFoundError:
            if time.monotonic() > end - wait + 5:
                break  # nobody is installing it (five seconds for an installer just started)
        except (OSError, ValueError):
            break  # an installer that died half way
        time.sleep(1.0)
    if (d / ".ready").exists():
        return d / "bin" / "python"
    why = (d / ".failed").read_text().strip() if (d / ".failed").exists() else "not installed"
    msg = f"real ROS 2 {distro} ({d}): {why}; bash scripts/ros2-venvs.sh installs it"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg)
    pytest.skip(msg)


def lan_netns(tag: str) -> contextlib.AbstractContextManager[str]:
    """A network namespace as a lab's LAN host has it for DDS: ``lo`` up with multicast and the multicast
    route (ROS 2 nodes on default settings discover each other by multicast on 239.255.0.1); nothing
    in it reaches a real interface."""
    @contextlib.contextmanager
    def make() -> Iterator[str]:
        with network_namespace(tag) as ns:
            for args in (["link", "set", "lo", "multicast", "on"], ["route", "add", "224.0.0.0/4", "dev", "lo"]):
                subprocess.run(["ip", "-n", ns, *args], check=True, capture_output=True, timeout=20)
            yield ns
    return make()


def chromium() -> tuple[Any, str]:
    """Playwright's sync API and the system chromium; skip (fail under CI=true) without them."""
    why = ""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        why = "playwright is not installed (pip install -e '.[test]')"
        sync_playwright = None
    exe = shutil.which("chromium") or shutil.which("chromium-browser") or ""
    if not why and not exe:
        why = "no chromium on PATH (apt-get install chromium; scripts/test.sh does it as root)"
    if why:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true: the browser test must run, but {why}")
        pytest.skip(why)
    return sync_playwright, exe


def foxglove_subscribe(ws: Any, advert: dict[str, Any], wanted: Any, channels: dict[str, dict[str, Any]],
                       subs: dict[int, str]) -> None:
    """A client to Foxglove's WebSocket spec, on an ``advertise`` (JSON): subscribe to the ``wanted`` topics not
    subscribed yet; ``channels`` (topic -> the advertised channel) and ``subs`` (subscription id -> topic) grow."""
    new = []
    for c in advert["channels"]:
        if c["topic"] in wanted and c["topic"] not in channels:
            channels[c["topic"]] = c
            subs[len(subs) + 1] = c["topic"]
            new.append({"id": len(subs), "channelId": c["id"]})
    if new:
        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))

