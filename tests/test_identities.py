"""Who may put, serve and query what, against a live router: docs/security.md's table, row by row.

The router is ``hilsim up``'s own (:func:`hilsim.launch.router.open_run_router`: a user, a password and the
access control of every identity of the arm scenario, with two lab credentials from ``hilsim creds`` and a
guest). Each identity connects with its own file and tries every probed key; what it may do is read from
docs/security.md ("Each identity, probed against a live router"), so the document says exactly what the
router enforces: every cell holds, and every probed key not in a cell is refused. The ROS 2 bridge to DDS (not
in the arm's table) is held to its ``from_dds`` on the rover's run router, narrowed as a lab narrows it.
"""

from __future__ import annotations

import itertools
import os
import re
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zenoh
from util import REPO, wait_until

from hilsim.core import rights, run_finder, transport
from hilsim.core.config import ConfigError, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario, parse_overrides
from hilsim.launch import creds
from hilsim.launch.router import RunRouter, identity_file, open_run_router

FJT = "control_msgs/action/FollowJointTrajectory"
DOC = REPO / "docs" / "security.md"
TABLE = "### Each identity, probed against a live router"
BRIDGE = "bridge-ros2-dds"


def _probes(k: Keys) -> tuple[dict[str, str], dict[str, str]]:
    """(put probes, serve/query probes): the name the table uses -> the key."""
    # batch: the identity's own batch key (its name a chunk of it); batch/physics: physics' own
    puts = {"/clock": k.clock, "batch": k.all_batches, "batch/physics": k.batch("probe", 1, "physics"),
            "health/physics": k.health("physics")}
    puts |= {t: k.topic(t) for t in ("truth/joint_states", "joint_states", "joint_commands", "joint_trajectory",
                                      "planner/joint_trajectory", "cmd_vel", "task/result", "navigator/result")}
    served = {n: k.service(n) for n in ("planner/goal", "controller/set_parameters", "controller/has_trajectory")}
    served["send_goal"] = k.action("follow_joint_trajectory", FJT).send_goal
    return puts, served


def _table() -> dict[str, dict[str, set[str]]]:
    """identity -> {put, serve, query} -> the probed names, from docs/security.md."""
    text = DOC.read_text().split(TABLE, 1)[1]
    lines = text.split("\n\n| identity | put | serve | query |\n", 1)[1].splitlines()[1:]  # after |---|
    out: dict[str, dict[str, set[str]]] = {}
    for ln in itertools.takewhile(lambda x: x.startswith("|"), lines):
        cells = [c.strip() for c in ln.strip("|").split("|")]
        name = re.match(r"`([\w-]+)`", cells[0])[1]
        out[name] = {what: set(re.findall(r"`([^`]+)`", cell)) for what, cell in zip(("put", "serve", "query"),
                                                                                    cells[1:], strict=True)}
    return out


def _own_pointer_and_creds(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """This router's pointer and lab credentials in ``tmp_path``: nobody else's tools, none of this user's creds."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    (tmp_path / "xdg").mkdir(mode=0o700)
    monkeypatch.setenv(creds.ENV, str(tmp_path / "creds"))


def _close(rr: RunRouter) -> None:
    if rr.pointer is not None:
        rr.pointer.unlink(missing_ok=True)
    rr.session.close()


@pytest.fixture
def run_router(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[RunRouter, dict[str, Path]]]:
    """The arm's run router with a guest and two lab credentials; identity -> its client config."""
    _own_pointer_and_creds(tmp_path, monkeypatch)
    files = {"teleop": creds.add("teleop", ["cmd_vel"], [], connect="tcp/127.0.0.1:7447"),
             "viewer": creds.add("viewer", [], [], connect="tcp/127.0.0.1:7447")}
    sc = load_scenario("arm", {"zenoh.guests": "read"})
    run = tmp_path / "run"
    rr = open_run_router(run, sc)
    files |= {u: p for u, p in rr.identities.items()}
    files |= {"tools": rr.client_config, "launcher": rr.launcher_config, "guest": rr.guest_config,
              "play": identity_file(run, "play"), "panel": identity_file(run, "panel")}
    try:
        yield rr, files
    finally:
        _close(rr)


def test_each_identity_may_put_serve_and_query_exactly_what_this_table_says(
        run_router: tuple[RunRouter, dict[str, Path]]) -> None:
    rr, files = run_router
    # hilsim play and the panel find their own identity through the run's pointer, the other tools theirs
    ptr = run_finder.RunPointer(rr.endpoint, rr.client_config.parent, "arm", rr.client_config, os.getpid())
    for tool, own in (("hilsim play", files["play"]), ("hilsim ui", files["panel"]), ("hilsim topic", files["tools"])):
        assert run_finder.tool_identity(ptr, tool) == own, tool
    table = _table()
    assert set(table) == set(files), (sorted(table), sorted(files))  # the doc names every identity of the run
    puts, served = _probes(Keys())

    def session(who: str) -> zenoh.Session:
        return transport.open_session(ZenohConfig(mode="client", connect=[rr.endpoint], auth=files[who]))

    sessions = {who: session(who) for who in files}
    reader = session("launcher")
    got: set[tuple[str, str]] = set()  # (who, probe) of every put that reached the reader
    lock = threading.Lock()

    def on(sample: zenoh.Sample) -> None:
        with lock:
            got.add(tuple(sample.payload.to_string().split(" ", 1)))

    subs = [reader.declare_subscriber(key, on) for key in puts.values()]  # all_batches: every batch key
    try:
        time.sleep(0.5)  # the subscriptions reach the router before the first put (else nothing is judged)
        for who, s in sessions.items():
            for name, key in puts.items():
                s.put(Keys().batch("probe", 1, who) if name == "batch" else key, f"{who} {name}")
        expected = {(who, name) for who, row in table.items() for name in row["put"]}
        assert wait_until(lambda: expected <= got, 20), sorted(expected - got)
        time.sleep(1.0)  # the refused ones would have come by now (the allowed ones took one path with them)
        assert got == expected, f"not refused: {sorted(got - expected)}"

        # a queryable of each identity on every probed key, asked by one allowed to ask it (the tools; the
        # planner for has_trajectory, its asker), from a session of its own
        asker = {name: "planner" if name == "controller/has_trajectory" else "tools" for name in served}

        def ask(s: zenoh.Session, key: str) -> list[str]:
            return [r.ok.payload.to_string() for r in s.get(key, timeout=3.0) if r.ok is not None]

        for who, s in sessions.items():
            qs = [s.declare_queryable(key, lambda q, w=who: q.reply(q.key_expr, w)) for key in served.values()]
            try:
                with ThreadPoolExecutor(len(served)) as ex:
                    answers = dict(zip(served, ex.map(lambda n: ask(session(asker[n]), served[n]), served),
                                       strict=True))
                answered = {n for n, a in answers.items() if who in a}
                assert answered == table[who]["serve"], (who, answered, table[who]["serve"])
            finally:
                for q in qs:
                    q.undeclare()

        # each key's own server answers; each identity asks every key
        servers = {"planner/goal": "planner", "controller/set_parameters": "controller",
                   "controller/has_trajectory": "controller", "send_goal": "controller"}
        qs = [sessions[servers[n]].declare_queryable(key, lambda q: q.reply(q.key_expr, "served"))
              for n, key in served.items()]
        try:
            time.sleep(0.5)
            for who in files:
                s = session(who)  # not the server's own session: a query inside one never reaches the router
                with ThreadPoolExecutor(len(served)) as ex:
                    answers = dict(zip(served, ex.map(lambda n, s=s: ask(s, served[n]), served), strict=True))
                replied = {n for n, a in answers.items() if a}
                assert replied == table[who]["query"], (who, replied, table[who]["query"])
                s.close()
        finally:
            for q in qs:
                q.undeclare()
    finally:
        for sub in subs:
            sub.undeclare()
        reader.close()
        for s in sessions.values():
            s.close()


def test_a_credential_is_given_only_what_a_person_may_command(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``hilsim creds add``: a topic a service writes, or an unknown queryable, is refused in one line; a file
    that is not this user's 0600 is not admitted."""
    monkeypatch.setenv(creds.ENV, str(tmp_path / "creds"))
    with pytest.raises(ConfigError, match=r"--may-write joint_states: written by sensors only .* a credential may "
                                          r"write joint_trajectory, cmd_vel"):
        creds.add("sneaky", ["joint_states"], [], connect="tcp/127.0.0.1:7447")
    with pytest.raises(ConfigError, match="--may-ask controller/has_trajectory: not a queryable a person may ask"):
        creds.add("sneaky", [], ["controller/has_trajectory"], connect="tcp/127.0.0.1:7447")
    path = creds.add("ok", ["cmd_vel"], ["actions"], connect="tcp/127.0.0.1:7447")
    assert oct(path.stat().st_mode & 0o777) == "0o600" and oct(path.parent.stat().st_mode & 0o777) == "0o700"
    assert [g.describe() for g in creds.load_all()] == ["ok: may write cmd_vel; may ask actions"]
    (path.parent / "ok.json").chmod(0o644)
    with pytest.raises(ConfigError, match="must be this user's and mode 0600"):
        creds.load_all()


def test_the_dds_bridge_puts_only_what_its_from_dds_names(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """DDS has no identities (no SROS2 in the wheels): the bridge's ``from_dds`` is what every DDS node of the
    domain may send. ``hilsim up rover --hil config/ros2/dds.yaml --set bridge-ros2-dds.from_dds=[cmd_vel]``
    narrows it, and the run's router holds the bridge's identity to it: its ``cmd_vel`` reaches a subscriber,
    its ``joint_trajectory`` (the table's, without that line) and ``odom`` (the controller's) do not."""
    _own_pointer_and_creds(tmp_path, monkeypatch)
    overlay = [REPO / "config" / "ros2" / "dds.yaml"]
    sc = load_scenario("rover", parse_overrides(["bridge-ros2-dds.from_dds=[cmd_vel]"]), overlay)
    k = Keys.of(sc)
    # the overlay alone takes both of the table's topics from DDS, and its identity may put both
    assert rights.unit_rights(load_scenario("rover", {}, overlay), BRIDGE).may_put(k.topic("joint_trajectory"))
    rr = open_run_router(tmp_path / "run", sc)
    cfg = {who: ZenohConfig(mode="client", connect=[rr.endpoint], auth=f)
           for who, f in (("bridge", rr.identities[BRIDGE]), ("tools", rr.client_config),
                          ("reader", rr.launcher_config))}
    sessions = {who: transport.open_session(c) for who, c in cfg.items()}
    got: list[tuple[str, str]] = []  # (who, topic) of every put that reached the reader, in order
    probes = ("odom", "joint_trajectory", "cmd_vel")
    # joint_trajectory's last: once the tools' put on it arrives, every subscription has reached the router
    subs = [sessions["reader"].declare_subscriber(k.topic(t), lambda s: got.append(
        tuple(s.payload.to_string().split(" ", 1)))) for t in probes]
    try:
        assert wait_until(lambda: sessions["tools"].put(k.topic("joint_trajectory"), "tools joint_trajectory")
                          or ("tools", "joint_trajectory") in got, 10), "the control never arrived"
        for t in probes:  # in this order on one session and one path: the refused ones would come before cmd_vel
            sessions["bridge"].put(k.topic(t), f"bridge {t}")
        assert wait_until(lambda: ("bridge", "cmd_vel") in got, 10), got
        assert {g for g in got if g[0] == "bridge"} == {("bridge", "cmd_vel")}, got
    finally:
        for sub in subs:
            sub.undeclare()
        for s in sessions.values():
            s.close()
        _close(rr)
