"""End to end under attack, against ``hilsim up``'s own router (a user and password made for the run).

Two injector processes (tests/injector.py) attack the running arm scenario: an outsider without the
run's credentials, with every kind of bad input including forged samples (a real writer's gid and
its next sequence number), cannot even connect; an insider given the credentials floods every key
with garbage, mutated samples and well-formed samples from an unannounced writer. The task is still
done (judged by the physics truth), no service crashes or errs, and the services count what they
rejected. (What an insider's forged gid does, nothing here can stop: tests/test_trust.py and
docs/security.md.)"""

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

from hilsim.core import recording
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.rows import part

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parent.parent
INJECTOR = [sys.executable, str(REPO / "tests" / "injector.py")]
# every kind but the forged writer: given the credentials, that one is believed (docs/security.md)
INSIDER_KINDS = "empty,random,truncated,bitflip,huge,nan,copy_no_attachment,copy_foreign_writer"


def test_the_arm_reaches_its_targets_while_every_key_is_attacked(tmp_path: Path) -> None:
    run = tmp_path / "run"
    # the recorder on every key (logger.batch=0), so the insider's unannounced garbage is recorded as rejected
    # (with batches a writer that announces nothing is not recorded at all: docs/recording.md, "Batches")
    up = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "up", "arm", "--out", str(run),
                           "--set", "logger.batch=0"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                          start_new_session=True)
    inj: subprocess.Popen[str] | None = None
    obs: Observer | None = None
    lines: list[str] = []
    try:
        assert up.stdout is not None
        for line in up.stdout:
            lines.append(line)
            if line.startswith("zenoh router:"):
                ep = line.split()[2]
                obs = Observer(ep, run / "zenoh-client.json5")  # the test holds the run's credentials too
            if line.startswith("ready:"):
                break
        assert obs is not None, "".join(lines)
        # the outsider: forged writers too, but no credentials
        outsider = subprocess.run([*INJECTOR, "--connect", ep, "--rate", "80", "--seconds", "5"],
                                  capture_output=True, text=True, timeout=60)
        refused = json.loads(outsider.stdout.strip().splitlines()[-1])
        inj = subprocess.Popen([*INJECTOR, "--connect", ep, "--rate", "80", "--auth", str(run / "zenoh-client.json5"),
                                "--kinds", INSIDER_KINDS], stdout=subprocess.PIPE, text=True, start_new_session=True)
        out, _ = up.communicate(timeout=280)
        out = "".join(lines) + out
        inj.send_signal(signal.SIGINT)
        sent = json.loads(inj.communicate(timeout=30)[0].strip().splitlines()[-1])
    finally:
        for p in (up, inj):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
        if obs is not None:
            obs.close()
    assert refused.get("connected") is False and "Unable to connect" in refused.get("error", ""), refused
    assert up.returncode == 0, out
    assert "targets reached: 3/3" in out, out
    assert "died" not in out, out
    # the insider really attacked, with every kind of bad input but the forged writer
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
