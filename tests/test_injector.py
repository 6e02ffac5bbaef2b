"""End to end under attack, against ``hilsim up``'s own router (an identity per process, docs/security.md).

Two injector processes (tests/injector.py) attack the running arm scenario: an outsider without the
run's credentials, with every kind of bad input, cannot even connect; an insider holding the *tools'*
credentials (``<run dir>/zenoh-client.json5``, what a person's tools and ROS 2 nodes are given) sends on
every key it sees garbage, mutated samples, samples from an unannounced writer, forged ones (a real
writer's gid with its next sequence number and with one 10,000 ahead) and replays of real samples with
their recorded ids, and malformed goals and gains. The router refuses every write on a key the tools may
not write (nothing of it reaches anyone: the recorder received exactly what the services say they
published there); on the keys they may write (the trajectory), the controller rejects or counts what is
suspect and still takes the planner's own trajectories. (A forged sample carries a real sample's content,
the writer's latest: content of its own to elsewhere the tools may send anyway, as themselves, and it
would move the arm there; docs/security.md, "What is not protected".) The task is done (judged by the physics truth),
the summary is true, and ``hilsim play`` of a bag into that run is refused for a key a service writes."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zenoh
from util import Observer

from hilsim.core import msgs, recording, transport
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.bag import BagWriter
from hilsim.record.bag_read import open_bag, write_metadata
from hilsim.record.rows import part

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parent.parent
INJECTOR = [sys.executable, str(REPO / "tests" / "injector.py")]


def _capture_bag(session: zenoh.Session, key: str, out: Path, n: int = 50) -> Path:
    """A small real bag: ``n`` samples of ``key`` as they came, with their writer's ids."""
    got: list[tuple[bytes, transport.Attachment | None]] = []
    done = threading.Event()

    def on(s: zenoh.Sample) -> None:
        if len(got) < n:
            got.append((s.payload.to_bytes(), transport.read_attachment(s)))
        else:
            done.set()

    sub = session.declare_subscriber(key, on)
    assert done.wait(30), len(got)
    sub.undeclare()
    w = BagWriter(out)
    for i, (data, att) in enumerate(got):
        w.append((key, data, (att.seq, att.source_ns, att.gid) if att else (0, 0, None), i))
    w.flush()
    w.close()
    write_metadata(out)
    return out


def _finals(run: Path) -> dict[str, int]:
    """What every service says it published, per key (its final health, in the bag)."""
    published: Counter[str] = Counter()
    last: dict[str, dict[str, str]] = {}
    for m in open_bag(run).messages():
        if "/health/" in m.topic:
            h = msgs.decode(msgs.DiagnosticArray, m.data)
            vals = {kv.key: kv.value for kv in h.status[0].values}
            if vals.get("final") == "1":
                last[m.topic] = vals
    for vals in last.values():
        published.update({k[10:]: int(v) for k, v in vals.items() if k.startswith("published:")})
    return dict(published)


# the attack races the run: judged as the run is timed alone
@pytest.mark.serial
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
    tools = run / "zenoh-client.json5"
    try:
        assert up.stdout is not None
        for line in up.stdout:
            lines.append(line)
            if line.startswith("zenoh router:"):
                ep = line.split()[2]
                obs = Observer(ep, tools)  # the test holds the tools' credentials too: they read everything
            if line.startswith("ready:"):
                break
        assert obs is not None, "".join(lines)
        # the outsider: forged writers too, but no credentials
        outsider = subprocess.run([*INJECTOR, "--connect", ep, "--rate", "80", "--seconds", "3"],
                                  capture_output=True, text=True, timeout=60)
        refused = json.loads(outsider.stdout.strip().splitlines()[-1])
        inj = subprocess.Popen([*INJECTOR, "--connect", ep, "--rate", "100", "--auth", str(tools)],
                               stdout=subprocess.PIPE, text=True, start_new_session=True)
        # a bag of this run's own joint states (their writer's ids in it), played into it by mistake: refused
        bag = _capture_bag(obs.session, Keys().topic("joint_states"), tmp_path / "js-bag")
        play = subprocess.run([sys.executable, "-m", "hilsim.cli", "play", str(bag), "--run", str(run), "--rate", "0"],
                              capture_output=True, text=True, timeout=60, cwd=REPO)
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
    assert refused.get("connected") is False and "refused these credentials" in refused.get("error", ""), refused
    first, rest = play.stderr.split("\n", 1)
    assert play.returncode == 1 and first.startswith("hilsim play: joined run ") and "(scenario arm)" in first, play
    # the service seen writing it live, or (its token not seen in time on a busy machine) the key table's owner
    assert rest.startswith("hilsim play: /arm/joint_states") and "written by sensors" in rest, play
    assert "into a run without" in rest, play
    assert rest.count("\n") == 1, play.stderr  # one line
    assert up.returncode == 0, out
    assert "targets reached: 3/3" in out, out
    assert "died" not in out and " lost " not in out and "never reached the recorder" not in out, out
    # the insider really attacked, with every kind of bad input, on many keys
    kinds = {k: v for k, v in sent.items() if k != "keys"}
    assert len(kinds) == 12 and min(kinds.values()) >= 3 and sent["keys"] >= 15, sent
    # judged by the physics truth, not the planner's word
    sc = load_scenario("arm")
    for i, target in enumerate(sc.task.targets, 1):
        stamp, ok = obs.results[f"task-{i}"]
        assert ok and np.abs(obs.truth_at(stamp) - np.asarray(target)).max() <= sc.task.tolerance + 0.002
    # the router refused every write on a key the tools may not write: nothing of it reached the recorder
    # (which keeps everything it receives), on keys of every service
    counts = json.loads((run / "record_summary.json").read_text())
    published = _finals(run)
    keys = Keys()
    trajectory = keys.topic("joint_trajectory")
    not_theirs = [k for k in published if k != trajectory and "/health/" not in k]
    assert {keys.clock, keys.truth("joint_states"), keys.topic("joint_commands"), keys.topic("joint_states"),
            keys.topic("task/result")} <= set(not_theirs), not_theirs
    for k in not_theirs:
        assert counts[k]["received"] == published[k] and counts[k]["rejected"] == 0, (k, counts[k], published[k])
    # on the trajectory a person may send, the injected samples arrived (the control; the planner hands its own
    # on planner/joint_trajectory, refused above): the controller refused them (a writer that announced
    # nothing, in a run with credentials), and still followed the planner's own (3/3 above)
    t = counts[trajectory]
    assert t["received"] > published.get(trajectory, 0), t
    found = re.finditer(r"^  (\w+): (\d+) rejected, (\d+) errors", out, re.M)
    rejected = {m[1]: (int(m[2]), int(m[3])) for m in found}
    assert "controller" in rejected and "planner" in rejected, out  # the trajectory; garbage goals and gains
    assert "physics" not in rejected and "sensors" not in rejected, out  # nothing reached them
    assert all(errors == 0 for _, errors in rejected.values()), out
    log = (run / "controller.log").read_text()
    # a forged number with the planner's gid is no longer believed on the trajectory: only the router's
    # identities keep the planner's key, and on joint_trajectory its gid is not an announced writer's
    assert "has not announced itself for this key" in log and "no attachment" in log
    # "recorded" means in the file: the rows match the recorder's counts, what it could not decode kept too
    rows = recording.entity_rows(run / "recording.rrd")
    assert all(v["received"] == v["recorded"] == v["bagged"] for v in counts.values()), counts
    rejected_rows = sum(n for e, n in rows.items() if e.startswith("/rejected/"))
    assert rejected_rows == sum(c["rejected"] for c in counts.values()) > 0, rejected_rows
    assert rows.get("/rejected/" + part(keys.clock), 0) == 0  # the clock: none of the garbage reached it
