"""Who may write what on ``hilsim up``'s router: each identity's rights, from the key table (hilsim.core.rights).

The end-to-end proof (the router refusing what an identity does not own, with the tools' credentials):
``tests/test_injector.py``; the files and the guest: ``tests/test_trust.py``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from hilsim.core import keys as keyscheme
from hilsim.core import rights
from hilsim.core.config import ConfigError
from hilsim.core.keys import Keys

DOCS = Path(__file__).resolve().parent.parent / "docs" / "keys.md"


def test_each_identity_may_write_what_the_key_table_gives_it(scenario: Any) -> None:
    """The tools: what a person commands, and what no service of the run writes; never truth, the clock,
    joint commands or a service's health. Physics: its truth and clock, not the commands. The recorder: its
    own health and log. A composed process: its members' together. A robot's chunk is every robot's."""
    sc = scenario("arm")
    k, k3 = Keys.of(sc), Keys.of(sc, "arm3")
    tools = rights.tools_rights(sc)
    for key in (k.topic("joint_trajectory"), k3.topic("joint_trajectory"), k.topic("cmd_vel")):
        assert tools.may_put(key), key
    for key in (k.truth("joint_states"), k.clock, k.topic("joint_commands"), k.topic("joint_states"),
                k.health("physics"), k.log("controller"), k.sync("planner"), k.topic("task/result"), "0/**",
                k.alive("physics")):
        assert not tools.may_put(key), key
    assert tools.may_ask(k.service("planner/goal")) and tools.may_ask(k3.service("controller/set_parameters"))
    assert tools.may_ask(k.action("follow_joint_trajectory", "control_msgs/action/FollowJointTrajectory").send_goal)
    assert not tools.may_ask(k.service("controller/has_trajectory"))
    assert not tools.may_serve(k.service("planner/goal"))
    assert not tools.may_serve(k.service("controller/has_trajectory"))
    assert rights.unit_rights(sc, "planner").may_serve(k.service("planner/goal"))
    physics = rights.unit_rights(sc, "physics")
    assert physics.may_put(k.truth("joint_states")) and physics.may_put(k.clock) and physics.may_put(k.tf_static)
    assert not physics.may_put(k.topic("joint_commands")) and not physics.may_put(k.health("controller"))
    logger = rights.unit_rights(sc, "logger")
    assert {e for e in logger.put if "/@adv/" not in e} == {k3.health("logger").replace("arm3", "*"),
                                                           k3.log("logger").replace("arm3", "*"),
                                                           k3.sync("logger").replace("arm3", "*"),
                                                           k3.server_state("logger").replace("arm3", "*"),
                                                           k3.server_setpoints("logger").replace("arm3", "*")}
    assert not logger.tokens & {f"{sc.prefix}/batch/0/**"}  # the recorder sends no batches
    composed = rights.unit_rights(sc, "physics+sensors+controller")
    assert composed.may_put(k.clock) and composed.may_put(k.topic("joint_commands"))
    assert not composed.may_put(k.topic("joint_trajectory"))
    # the planner hands its trajectory on a key only it may write; a person's command goes on joint_trajectory
    planner = rights.unit_rights(sc, "planner")
    assert planner.may_put(k.topic("planner/joint_trajectory"))
    assert not tools.may_put(k.topic("planner/joint_trajectory"))
    assert not planner.may_put(k.topic("joint_trajectory"))
    # a run without the sensors: their joint states are the tools' to write (played from a bag)
    assert rights.tools_rights(scenario("arm", {"services": ["physics", "controller", "logger"]})).may_put(
        k.topic("joint_states"))
    assert rights.owners(sc, "joint_states") == ["sensors"] and rights.owners(sc, "cmd_vel") == []


def test_a_writer_the_table_does_not_name_is_refused_before_the_run(scenario: Any) -> None:
    sc = scenario("rover", {"services": ["physics", "sensors", "controller", "logger", "bridge-ros2-dds"],
                            "bridge-ros2-dds": {"from_dds": ["cmd_vel", "odom"]}})
    with pytest.raises(ConfigError, match=r"bridge-ros2-dds\.from_dds: odom: written by controller"):
        rights.unit_rights(sc, "bridge-ros2-dds")


def test_the_access_control_allows_only_and_denies_the_rest() -> None:
    acl = rights.access_control({"tools": rights.Rights(put={"0/*/cmd_vel/T/H"}), "guest": None})
    assert acl["default_permission"] == "deny" and all(r["permission"] == "allow" for r in acl["rules"])
    (pol,) = [p for p in acl["policies"] if p["id"] == "guest"]
    assert pol["rules"] == ["read", "deliver"]


def test_the_docs_name_every_writer_of_the_table() -> None:
    """docs/keys.md's "written by" column names the writers keys.py's table gives each topic."""
    rows = {}
    for line in DOCS.read_text().splitlines():
        m = re.match(r"^\| `([^`]+)` \|[^|]*\| ([^|]*) \|", line)
        if m:
            rows[m[1].lstrip("/")] = m[2]
    table = {**keyscheme.TOPIC_TABLE, **keyscheme.GLOBAL_TABLE}
    checked = 0
    for topic, row in table.items():
        if topic not in rows:
            continue
        for w in row.writers:
            assert w in rows[topic], (topic, w, rows[topic])
        checked += 1
    assert checked >= 25, checked
