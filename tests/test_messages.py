"""What a user reads first: ``hilsim up --help`` names files that exist and every scenario of
``config/``; the summary's line per service with rejected samples or errors gives the last error
only when there is one (no empty ``(last: )``)."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from hilsim.cli import build_parser
from hilsim.core.scenario import load_scenario
from hilsim.launch.follow import Outcome
from hilsim.launch.summary import summarise

REPO = Path(__file__).resolve().parent.parent


def test_up_help_names_existing_files_and_every_scenario(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("COLUMNS", "400")  # no wrapping inside a path
    with pytest.raises(SystemExit):
        build_parser().parse_args(["up", "--help"])
    text = capsys.readouterr().out
    named = re.findall(r"config/[\w./-]+\.yaml", text)
    assert named and all((REPO / n).is_file() for n in named), named
    scenarios = [p.stem for p in sorted((REPO / "config").glob("*.yaml"))
                 if {"world", "extends"} & set(yaml.safe_load(p.read_text()))]
    assert "arm-lean" in scenarios
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("scenario "))
    assert all(re.search(rf"\b{re.escape(s)}\b", line) for s in scenarios), (scenarios, line)


def test_the_summary_gives_the_last_error_only_when_there_is_one(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    sc = load_scenario("arm", {"task.targets": [], "duration": 1.0})
    o = Outcome()
    o.physics_done = True
    o.health = {"planner": {"rejected": "1", "errors": "0", "last_error": ""},
                "controller": {"rejected": "0", "errors": "2", "last_error": "gain out of range"}}
    run = SimpleNamespace(sc=sc, outcome=o, robots=[sc.robot], local=[], run_dir=tmp_path, untrusted=0)
    summarise(run)
    out = capsys.readouterr().out
    assert "  planner: 1 rejected, 0 errors\n" in out, out
    assert "  controller: 0 rejected, 2 errors (last: gain out of range)\n" in out, out
    assert "(last: )" not in out, out
