"""End to end under attack: a separate process floods every key of the running arm scenario with
garbage, mutated samples and well-formed samples from an unannounced writer. The task is still
done (judged by the physics truth), no service crashes or errs, and the services count what they
rejected."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from util import Observer

from hilsim.core import recording, transport
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.rows import part

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parent.parent


def test_the_arm_reaches_its_targets_while_every_key_is_attacked(tmp_path: Path) -> None:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    obs = Observer(ep)
    run = tmp_path / "run"
    up = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--router", ep, "--out", str(run)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                          start_new_session=True)
    inj: subprocess.Popen[str] | None = None
    lines: list[str] = []
    try:
        assert up.stdout is not None
        for line in up.stdout:
            lines.append(line)
            if line.startswith("ready:"):
                break
        inj = subprocess.Popen([sys.executable, str(REPO / "tests" / "injector.py"), "--connect", ep, "--rate", "80"],
                               stdout=subprocess.PIPE, text=True, start_new_session=True)
        out, _ = up.communicate(timeout=280)
        out = "".join(lines) + out
        inj.send_signal(signal.SIGINT)
        sent = json.loads(inj.communicate(timeout=30)[0].strip().splitlines()[-1])
    finally:
        for p in (up, inj):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
        obs.close()
        router.close()
    assert up.returncode == 0, out
    assert "targets reached: 3/3" in out, out
    assert "died" not in out, out
    # the injector really attacked, with every kind of bad input
    assert len(sent) == 8 and min(sent.values()) >= 5, sent
    # judged by the physics truth, not the planner's word
    sc = load_scenario("arm")
    for i, target in enumerate(sc.task.targets, 1):
        stamp, ok = obs.results[f"task-{i}"]
        assert ok and np.abs(obs.truth_at(stamp) - np.asarray(target)).max() <= sc.task.tolerance + 0.002
    # every service that reads data rejected samples, counted them, and had no handler error
    found = re.finditer(r"^  (\w+): (\d+) rejected, (\d+) errors", out, re.M)
    rejected = {m[1]: (int(m[2]), int(m[3])) for m in found}
    for svc in ("physics", "sensors", "controller", "planner"):
        assert svc in rejected and rejected[svc][0] > 0, (svc, out)
    assert all(errors == 0 for _, errors in rejected.values()), out
    # and their logs give each rejection its key and reason (e.g. an impostor's well-formed copy)
    logs = "".join((run / f"{s}.log").read_text() for s in ("physics", "controller", "sensors"))
    # (garbage, NaN and truncated samples come from a stranger too: they are refused for that
    # before anything is decoded; the decoder's own checks are unit-tested in test_core.py)
    assert "has not announced itself for this key" in logs and "no attachment" in logs
    # "recorded" means in the file: read back with Rerun's own reader, the rows match the
    # recorder's counts, and what it could not decode is kept too (rejected/<key>, its bytes' story)
    counts = json.loads((run / "record_summary.json").read_text())
    rows = recording.entity_rows(run / "recording.rrd")
    clock = counts[Keys().clock]
    assert clock["rejected"] > 0, clock  # the injector's garbage on the clock
    rejected_clock = rows["/rejected/" + part(Keys().clock)]  # the whole key, as one entity path part
    assert rejected_clock == clock["rejected"], (rejected_clock, clock)
    assert rows["/clock"] + rejected_clock == clock["recorded"] == clock["received"], (rows["/clock"], clock)
    rejected_rows = sum(n for e, n in rows.items() if e.startswith("/rejected/"))
    assert rejected_rows == sum(c["rejected"] for c in counts.values()), rejected_rows
