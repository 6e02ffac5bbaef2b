"""The recording survives a recorder killed with SIGKILL: what it had flushed (twice a second)
is in the file, ``hilsim.core.recording.recover_rrd`` makes the footerless file one that
``rerun rrd verify`` accepts without losing a row, and ``hilsim up`` does so and reports what
the recording holds; under the restart policy the recorder goes on in a part of its own."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import psutil
import pytest
import zenoh
from test_restart import Output, ended, sim_now
from util import Observer, up, wait_until

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.recording import RecordingError, contents, part_name, recover_rrd, verify_rrd

# a process that records 20 batches of 100 rows (sim_time 0…1.999 s), flushing each to the file
# as the logger does, then is killed with SIGKILL: no footer is ever written
WRITER = """
import os, signal, sys
from hilsim.core.recording import disable_analytics
disable_analytics()
import numpy as np
import rerun as rr
rec = rr.RecordingStream("test", send_properties=True)
rec.save(sys.argv[1])
for b in range(20):
    t = np.arange(b * 100, (b + 1) * 100) * 1e-3
    rec.send_columns("joint", indexes=[rr.TimeColumn("sim_time", duration=t)],
                     columns=rr.Scalars.columns(scalars=np.sin(t)))
    rec.flush()
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_writers_recording_is_recovered_whole(tmp_path: Path) -> None:
    rrd = tmp_path / "recording.rrd"
    p = subprocess.run([sys.executable, "-c", WRITER, str(rrd)], capture_output=True, text=True, timeout=60)
    assert p.returncode == -signal.SIGKILL, p.stderr
    with pytest.raises(RecordingError, match="footer"):
        verify_rrd(rrd)  # as the kill left it
    assert recover_rrd(rrd) is True
    verify_rrd(rrd)
    c = contents(rrd)
    assert c.rows["/joint"] == 2000 and c.last_sim_ns == 1_999_000_000
    assert recover_rrd(rrd) is False  # complete now: left alone
    # killed in the middle of writing a message: everything before it is kept
    cut = tmp_path / "cut.rrd"
    subprocess.run([sys.executable, "-c", WRITER, str(cut)], capture_output=True, timeout=60)
    os.truncate(cut, cut.stat().st_size - 1000)
    assert recover_rrd(cut) is True
    verify_rrd(cut)
    assert 1800 <= contents(cut).rows["/joint"] < 2000
    # not a recording at all: refused, and left as it was
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"\x00" * 4096)
    with pytest.raises(RecordingError):
        recover_rrd(junk)
    assert junk.read_bytes() == b"\x00" * 4096


def _written(health: dict[str, float]) -> Callable[[zenoh.Sample], None]:
    """A subscriber's callback keeping the recorder's ``written_sim_time`` (its health: how far in sim time
    its file holds every row) in ``health["written"]``."""

    def on(sample: zenoh.Sample) -> None:
        try:
            h = msgs.decode(msgs.DiagnosticArray, sample.payload.to_bytes())
            value = {kv.key: kv.value for kv in h.status[0].values}.get("written_sim_time", "none")
            health["written"] = float(value) if value != "none" else -1.0
        except (msgs.BadMessage, IndexError, ValueError):
            pass

    return on


@pytest.mark.e2e
def test_a_recorder_killed_mid_run_leaves_a_verified_recording(tmp_path: Path) -> None:
    """Lockstep arm, its three targets, the recorder under restart: on-failure. It is killed with SIGKILL
    while the arm moves, once sim time passed 0.3 s and its health says its file holds that far (both
    waited for: the kill falls where the test says, whatever the machine's speed, some 9 s of sim time
    before the task ends); hilsim up recovers its file (verified, everything up to that point), restarts
    it into a second part, and the run ends OK."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    health: dict[str, float] = {"written": -1.0}
    watch = obs.session.declare_subscriber(Keys().health("logger"), _written(health))
    run = tmp_path / "run"
    p = up("arm", "--router", ep, "--out", str(run),
           "--set", "restart.services.logger=on-failure", "--set", "restart.backoff=0.2")
    out = Output(p)
    pids: set[int] = set()
    try:
        ready = out.wait(r"^ready: (.*)$", 120)[1]
        pids = {int(pid) for pid in re.findall(r"\(pid (\d+)\)", ready)}
        logger = int(re.search(r"logger \(pid (\d+)\)", ready)[1])  # type: ignore[index]
        assert wait_until(lambda: sim_now(obs) >= 0.3e9 and health["written"] >= 0.3, 60), (health, out.text())
        written = health["written"]
        psutil.Process(logger).send_signal(signal.SIGKILL)
        with obs.lock:
            assert "task-3" not in obs.results, f"the task ended before the kill: {obs.results}"
        pids.add(int(out.wait(r"^  logger is back \(pid (\d+)\)", 60)[1]))
        ended(p, out, 240)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        watch.undeclare()
        obs.close()
        router.close()
    text = out.text()
    assert p.returncode == 0, text
    assert "targets reached: 3/3" in text and "restarted logger (exit code -9" in text, text
    # lockstep: sim time waited for the recorder (nothing was published while it was gone)
    stop = re.search(r"^  physics: sim time paused at t=([\d.]+) s until logger is back\n"
                     r"(?:.*\n)*?  physics: sim time runs again from t=([\d.]+) s", text, re.M)
    assert stop and 0 <= float(stop[2]) - float(stop[1]) <= 0.1, text
    first, second = run / "recording.rrd", run / part_name(1)
    assert re.search(rf"^  recording {re.escape(str(first))}: \d+ rows on \d+ entities up to t=[\d.]+ s sim "
                     r"\(the recorder was killed: recovered, verified\)", text, re.M), text
    # checked here again, independently of what hilsim up says: rerun's verify and its Python reader
    for part in (first, second):
        verify_rrd(part)
    c1, c2 = contents(first), contents(second)
    # the physics truth, up to where its health said the file held (the clock as recorded says how far)
    assert any("truth" in e and n > 100 for e, n in c1.rows.items()), c1.rows
    assert c1.last_sim_ns is not None and c1.last_sim_ns >= written * 1e9 - 1, (c1.last_sim_ns, written)
    # the second part goes on to the end of the run
    stamp, ok = obs.results["task-3"]
    assert ok and any("truth" in e and n > 100 for e, n in c2.rows.items()), c2.rows
    assert c2.last_sim_ns is not None and c2.last_sim_ns >= stamp, (c2.last_sim_ns, stamp)
    assert wait_until(lambda: not any(psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
                                      for pid in pids), 10), pids
