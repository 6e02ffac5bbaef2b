"""End to end: a recorder too slow for a realtime run loses samples, says so, never slows physics, and the
run fails for it (more lost than ``logger.max_loss``)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hilsim.core import transport
from hilsim.core.keys import Keys
from hilsim.launch.priorities import PLANNING_NICE, WRITING_NICE

pytestmark = [pytest.mark.e2e, pytest.mark.serial]  # realtime physics timed
REPO = Path(__file__).resolve().parent.parent
DURATION_S = 6  # long enough for a blocking publisher to fill the kernel's socket buffers and stall
DELAY_US = 2000  # the logger takes at most ~500 samples/s; the arm publishes ~6,000/s


def test_slow_recorder_loses_samples_but_never_slows_realtime_physics(tmp_path: Path) -> None:
    out = tmp_path / "run"
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    env = {**os.environ, "HILSIM_LOGGER_DELAY_US": str(DELAY_US)}
    p = subprocess.Popen(
        [sys.executable, "-m", "hilsim.cli", "up", "arm", "--clock", "realtime", "--duration", str(DURATION_S),
         "--router", ep, "--out", str(out), "--set", "logger.batch=0"],  # the per-sample receive path, slowed
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env, start_new_session=True,
    )
    try:
        stdout, _ = p.communicate(timeout=240)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        router.close()
    # realtime: a loss past logger.max_loss (5 %) fails the run and says why (--allow-loss: reported only)
    assert p.returncode == 1 and re.search(r"^result: FAILED \(recording lost \d+\.\d%\)$", stdout, re.M), stdout
    assert re.search(r"^  the recording missed \d+\.\d% of the samples \(more than logger.max_loss", stdout, re.M)

    # physics kept its deadlines, by its own figures
    rtf = float(stdout.split("real-time factor ")[-1].split(",")[0])
    assert rtf >= 0.95, stdout
    physics_log = (out / "physics.log").read_text()
    m = re.search(r"overruns (\d+) of (\d+) steps", physics_log)
    assert m, physics_log
    overruns, steps = int(m[1]), int(m[2])
    assert steps == DURATION_S * 1000, physics_log
    if "running with SCHED_FIFO" in physics_log:  # without it, overruns depend on the machine's load
        assert overruns <= 0.05 * steps, physics_log

    # the recorder could not keep up, and every sample of physics' clock is accounted for
    counts = json.loads((out / "record_summary.json").read_text())
    assert all(c["received"] == c["recorded"] for c in counts.values()), counts
    clock = counts[Keys().clock]
    published = steps + 1  # step 0, then one per step
    assert clock["before_first"] == 0, clock  # the logger heard physics from its first sample on
    assert clock["received"] < 0.8 * published, clock
    never = published - clock["received"] - clock["lost"]
    assert never >= 0, (clock, published)
    if never:  # samples still in flight when the run stopped leave no gap: the launcher reports them
        m = re.search(r"(\d+) published samples never reached the recorder: (.*)", stdout)
        assert m, stdout
        assert f"clock {never}" in m[2] or ", …" in m[2], stdout
    lost = {k: c["lost"] for k, c in counts.items() if c["lost"]}
    if lost:
        assert f"; lost {sum(lost.values())} " in stdout and "the recorder could not keep up" in stdout, stdout
    logger_out = (out / "logger.out").read_text()
    assert f"recorded {Keys().clock}: received {clock['received']} recorded {clock['received']}" in logger_out
    assert f"lost {sum(lost.values())} in {len(counts)} keys" in logger_out, logger_out


def threads_of(pid: int) -> dict[str, set[int]]:
    """A process's threads by the OS's name for them: the scheduling classes of each name."""
    import psutil

    out: dict[str, set[int]] = {}
    for t in psutil.Process(pid).threads():
        try:
            comm = Path(f"/proc/{pid}/task/{t.id}/comm").read_text().strip()
            out.setdefault(comm, set()).add(os.sched_getscheduler(t.id))
        except OSError:
            continue
    return out


def nice_of(pid: int, name: str) -> int | None:
    """The niceness of the first thread of ``pid`` whose OS name starts with ``name`` (None: there is none)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        if Path(f"/proc/{pid}/task/{tid}/comm").read_text().startswith(name):
            return os.getpriority(os.PRIO_PROCESS, int(tid))
    return None


def test_a_realtime_recorder_receives_on_sched_fifo_and_a_quiet_run_passes(tmp_path: Path) -> None:
    """Realtime with the run's own router: the recorder's receiving threads (Zenoh's) on SCHED_FIFO like the
    loop's services, its writing (the worker, Rerun's threads) in the ordinary class, niced up; the run
    loses less than logger.max_loss and is not failed for it."""
    import psutil

    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--clock", "realtime", "--duration", "4",
                          "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                         start_new_session=True)
    lines: list[str] = []
    policies: dict[str, set[int]] = {}
    planning: dict[str, set[int]] = {}
    try:
        assert p.stdout is not None
        for line in p.stdout:
            lines.append(line)
            if line.startswith("ready:"):
                break
        pid = int(re.search(r"logger \(pid (\d+)\)", "".join(lines))[1])  # type: ignore[index]
        planner = int(re.search(r"planner \(pid (\d+)\)", "".join(lines))[1])  # type: ignore[index]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and p.poll() is None:
            policies, planning = threads_of(pid), threads_of(planner)
            if os.SCHED_FIFO in policies.get("net-0", set()) and "logger-worker" in policies and \
                    os.SCHED_FIFO in planning.get("net-0", set()):
                break
            time.sleep(0.2)
        worker_nice, writer_nice = nice_of(planner, "planner-worker"), nice_of(pid, "logger-worker")
        nice = psutil.Process(pid).nice()
        rest, _ = p.communicate(timeout=240)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    stdout = "".join(lines) + rest
    if "SCHED_FIFO not permitted" in stdout or os.geteuid() != 0:
        pytest.skip("SCHED_FIFO not permitted here")
    assert policies.get("net-0") == {os.SCHED_FIFO}, policies  # Zenoh's receiving
    assert policies.get("logger-worker") == {os.SCHED_OTHER}, policies  # the worker: writing the files
    assert writer_nice == WRITING_NICE, writer_nice  # …niced up: other work on the machine gets less than it
    assert all(policies.get(n, {os.SCHED_OTHER}) == {os.SCHED_OTHER} for n in ("file_writer", "RecordingStream"))
    assert nice == 0, nice
    # the planner's planning thread ordinary and niced up, its receiving on SCHED_FIFO: planning on SCHED_FIFO held
    # a core for a second per plan, and every ordinary thread (the recorder's worker with its GIL) waited
    assert planning.get("planner-worker") == {os.SCHED_OTHER} and planning.get("net-0") == {os.SCHED_FIFO}, planning
    assert worker_nice == PLANNING_NICE, worker_nice
    if p.returncode == 1 and "result: FAILED (recording lost" in stdout:
        # Seen before the planner's planning thread left SCHED_FIFO (closing note of stop 51): on a 2-core
        # machine a little busier or slower than quiet, the recorder heard nothing from anyone for ~1 s,
        # every key at once, while a plan held a core; 23 % of a 4 s run lost (CI of stop 50's main). The
        # loss is said and fails the run, as promised; not seen since (docs/hil.md), kept as a known risk.
        pytest.xfail("the realtime recorder's ~1 s deafness after a plan on a busy 2-core machine: " +
                     next((ln.strip() for ln in stdout.splitlines() if "never reached" in ln), ""))
    assert p.returncode == 3 and "result: STOPPED (duration)" in stdout and "missed" not in stdout, stdout
