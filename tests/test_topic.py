"""``hilsim topic hz`` and the launcher's summary believe only a key's announced writer: with the
project's injector (``tests/injector.py``) publishing garbage and replayed copies of real samples
on every key, ``clock`` included, the rate figures and the summary's sim time stay those of
physics, and ``hz`` says how many samples it ignored."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys

import pytest
from util import LEAN, REPO, finish, up

from hilsim.core import transport

pytestmark = pytest.mark.e2e
INSIDER_KINDS = "empty,random,truncated,bitflip,huge,nan,copy_no_attachment,copy_foreign_writer"
HZ = re.compile(r"average rate: ([\d.]+) Hz \(wall\).*?\|  ([\d.]+) Hz \(sim time\)(?:  \|  ignored (\d+) samples)?")


def hz(ep: str, *extra: str) -> list[tuple[float, float, int]]:
    """The figures ``hilsim topic hz /clock`` printed over 3 s: (wall Hz, sim-time Hz, ignored)."""
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "topic", "hz", "/clock", "--connect", ep,
                        "--duration", "3", "--window", "400", *extra],
                       capture_output=True, text=True, timeout=60, cwd=REPO)
    found = [(float(m[1]), float(m[2]), int(m[3] or 0)) for m in HZ.finditer(r.stdout)]
    assert found, r.stdout + r.stderr
    return found


def test_an_impostor_on_the_clock_changes_neither_hz_nor_the_summary() -> None:
    """Physics alone, realtime at 500 Hz (the lean arm), for 9 s of sim time; the injector runs
    through the whole of it and after the end."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    p = up(LEAN, "--router", ep, "--clock", "realtime", "--no-logger", "--set", "services=[physics]",
           "--set", "task.targets=[]", "--duration", "9")
    inj: subprocess.Popen[str] | None = None
    try:
        assert p.stdout is not None
        head = []
        for line in p.stdout:
            head.append(line)
            if line.startswith("ready:"):
                break
        # an impostor that does not forge its writer (that one only the credentials keep out: test_trust.py)
        inj = subprocess.Popen([sys.executable, str(REPO / "tests" / "injector.py"), "--connect", ep,
                                "--rate", "400", "--kinds", INSIDER_KINDS], stdout=subprocess.PIPE, text=True,
                               start_new_session=True)
        rightful = hz(ep)
        anyone = hz(ep, "--any-writer")
        out = "".join(head) + finish(p, 60)
        inj.send_signal(signal.SIGINT)
        sent = json.loads(inj.communicate(timeout=30)[0].strip().splitlines()[-1])
    finally:
        for proc in (p, inj):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.communicate()
        router.close()
    assert sent.get("copy_foreign_writer", 0) >= 5 and sent.get("copy_no_attachment", 0) >= 5, sent
    # only physics' clock: one sample per 2 ms step in sim time (never more: a sample lost on a
    # loaded machine can only lower it), about 500 Hz of wall time, and the impostor's samples were
    # seen and ignored
    wall, sim, ignored = rightful[-1]
    assert 450 < sim < 500.5 and 350 < wall < 650 and ignored > 0, rightful
    # counting everyone, the replayed stamps of the past and the extra samples show
    assert any(abs(s - 500.0) >= 0.5 or w > 650 for w, s, _ in anyone), anyone
    # the launcher's summary: physics' own sim time, not a replayed health sample's
    assert p.returncode == 0, out
    assert re.search(r"^  sim time 9\.000 s", out, re.M), out
    assert re.search(r"^  ignored \d+ samples on results, health and logs", out, re.M), out


def test_echo_says_when_nobody_publishes_the_topic(router: str) -> None:
    """``hilsim topic echo`` on a topic nobody publishes says so after a second (the ROS 2 graph has
    no publisher token for it) instead of waiting in silence; with a publisher announced, it waits
    for its samples quietly."""
    from hilsim.core.config import ZenohConfig
    from hilsim.core.keys import Keys
    from hilsim.core.ros2 import wire

    def echo(name: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "hilsim.cli", "topic", "echo", name, "--connect", router,
                               "--duration", "1.8"], capture_output=True, text=True, timeout=60, cwd=REPO)

    nope = echo("/arm/nope")
    assert "no publisher on /arm/nope yet (waiting; Ctrl-C to stop)" in nope.stderr, nope
    key = Keys().topic("joint_states")  # /arm/joint_states: announced by a publisher's graph token, no sample
    dds_type, type_hash = key.split("/")[-2:]
    ses = transport.open_session(ZenohConfig(connect=[router]))
    try:
        token = ses.liveliness().declare_token(wire.entity_token(
            "MP", 0, str(ses.info.zid()), 1, 2, "/", "/arm", "joint_state_publisher", "/arm/joint_states",
            dds_type, type_hash, wire.QOS_DEFAULT))
        announced = echo("/arm/joint_states")
        token.undeclare()
    finally:
        ses.close()
    assert announced.returncode == 0 and "no publisher" not in announced.stderr, announced
