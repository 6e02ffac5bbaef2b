"""``extends:`` that can take away: ``name!`` replaces a section or list whole, ``unset:`` removes fields of the
scenarios extended (docs/robots.md, "Scenarios that take away"), so a lab's scenario extends a base without
inheriting the Niryo's per-joint gains or targets."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario

ARM = Path(__file__).resolve().parent.parent / "config" / "arm.yaml"


def scenario(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "lab.yaml"
    p.write_text(f"extends: {ARM}\n" + text)
    return p


def test_a_section_marked_with_a_bang_replaces_the_base_s_whole(tmp_path: Path) -> None:
    base = load_scenario(ARM)
    assert set(base.controller.gains) > {"default"}  # the Niryo's per-joint gains
    merged = load_scenario(scenario(tmp_path, "controller:\n  gains:\n    default: {kp: 7.0}\n"))
    assert set(merged.controller.gains) == set(base.controller.gains)  # a plain section merges: they stay
    sc = load_scenario(scenario(tmp_path, "controller:\n  gains!:\n    default: {kp: 7.0, ki: 0, kd: 1}\n"))
    assert set(sc.controller.gains) == {"default"} and sc.controller.gains["default"].kp == 7.0
    assert sc.controller.rate_hz == base.controller.rate_hz  # the rest of the section as the base has it
    # a list too: the targets replaced, not appended to
    sc = load_scenario(scenario(tmp_path, "task:\n  targets!: [[0, 0, 0, 0, 0, 0]]\n"))
    assert sc.task.targets == [[0, 0, 0, 0, 0, 0]]


def test_unset_takes_fields_of_the_base_away(tmp_path: Path) -> None:
    sc = load_scenario(scenario(tmp_path, "unset: [task.targets, controller.gains, physics.gravity_compensation]\n"))
    assert sc.task.targets == [] and sc.controller.gains == {} and sc.physics.gravity_compensation == []
    # and given anew by the same file
    sc = load_scenario(scenario(tmp_path, "unset: [controller.gains]\ncontroller:\n  gains:\n    joint_1: {kp: 3}\n"
                                          "    default: {kp: 1}\n"))
    assert set(sc.controller.gains) == {"joint_1", "default"}


def test_what_cannot_be_taken_away_is_said_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"lab.yaml: unset: controller.gain: no such field in the scenarios it "
                                          r"extends"):
        load_scenario(scenario(tmp_path, "unset: [controller.gain]\n"))
    with pytest.raises(ConfigError, match=r"unset: expected a list of fields"):
        load_scenario(scenario(tmp_path, "unset: controller.gains\n"))
    alone = tmp_path / "alone.yaml"
    alone.write_text(ARM.read_text().replace("name: arm", "name: arm\nunset: [task.targets]"))
    with pytest.raises(ConfigError, match=r"alone.yaml: unset: only a scenario that extends another"):
        load_scenario(alone)
