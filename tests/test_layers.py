"""The house: every import points down the layers of docs/architecture.md, and no circle exists.

Read from the code's own imports with ``ast`` (every ``import`` anywhere in a module, inside functions
too: a lazy import is a use all the same), so the picture in docs/architecture.md is checked, not
believed. A module may import modules of its own layer or of the layers below; siblings in one layer
(services and bridges; record and navigation) stay independent; inside the core, each module may
import only the ones listed before it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# top to bottom; each row is one layer, its entries independent of each other
LAYERS: list[list[str]] = [
    ["hilsim.cli"],
    ["hilsim.ui"],
    ["hilsim.tools"],
    ["hilsim.launch"],
    ["hilsim.services", "hilsim.bridges"],
    ["hilsim.record", "hilsim.navigation"],
    ["hilsim.planning"],
    ["hilsim.sim"],
    ["hilsim.core"],
]
# inside the core, bottom to top: a module imports only modules listed before it
CORE_ORDER = ["threads", "simclock", "msgs", "ros2", "geometry", "recording", "inproc", "fleet", "keys", "config",
              "rights", "registry", "scenario", "restart", "transport", "run_finder", "provenance", "batch", "signals",
              "publisher", "ros2_node", "service"]


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[0] in ("services", "bridges"):  # installed as hilsim.services / hilsim.bridges (pyproject)
        parts.insert(0, "hilsim")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def source_files() -> list[Path]:
    return sorted([*ROOT.glob("hilsim/**/*.py"), *ROOT.glob("services/*.py"), *ROOT.glob("bridges/*.py")])


def imports_of(path: Path, known: set[str]) -> set[str]:
    """The project modules ``path`` imports (``from hilsim.core import msgs`` names ``hilsim.core.msgs``)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.startswith("hilsim"):
            for a in node.names:
                full = f"{node.module}.{a.name}"
                out.add(full if full in known else node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("hilsim"))
    return {m for m in out if m in known}


def graph() -> dict[str, set[str]]:
    files = source_files()
    known = {module_name(p) for p in files}
    # a package's __init__ is not a use of the package's modules; an import of a package is a use of it
    return {module_name(p): imports_of(p, known) - {module_name(p)} for p in files}


def layer_of(mod: str) -> tuple[int, str] | None:
    for i, row in enumerate(LAYERS):
        for pkg in row:
            if mod == pkg or mod.startswith(pkg + "."):
                return i, pkg
    return None


def test_every_module_has_a_layer() -> None:
    homeless = [m for m in graph() if m != "hilsim" and layer_of(m) is None]
    assert not homeless, f"modules outside every layer of docs/architecture.md: {homeless}"


def test_no_import_runs_up_or_sideways() -> None:
    bad: list[str] = []
    for mod, deps in graph().items():
        here = layer_of(mod)
        if here is None:
            continue
        for d in sorted(deps):
            there = layer_of(d)
            if there is None:
                continue
            if there[0] < here[0]:
                bad.append(f"{mod} -> {d} (up from {here[1]} to {there[1]})")
            elif there[0] == here[0] and there[1] != here[1]:
                bad.append(f"{mod} -> {d} (sideways: {here[1]} and {there[1]} are independent)")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_the_core_is_ordered() -> None:
    bad: list[str] = []
    rank = {f"hilsim.core.{m}": i for i, m in enumerate(CORE_ORDER)}

    def rank_of(mod: str) -> int | None:
        for name, r in rank.items():
            if mod == name or mod.startswith(name + "."):
                return r
        return None

    for mod, deps in graph().items():
        r = rank_of(mod)
        if not mod.startswith("hilsim.core") or mod == "hilsim.core":
            continue
        assert r is not None, f"{mod} is not in CORE_ORDER (tests/test_layers.py)"
        for d in deps:
            rd = rank_of(d)
            if rd is not None and rd > r:
                bad.append(f"{mod} -> {d}")
    assert not bad, "core modules importing ones above them:\n" + "\n".join(bad)


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp: list[str] = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_no_circles() -> None:
    g = graph()
    # a package's __init__ re-exporting its modules is not a circle with them
    g = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in g.items()}
    assert not cycles(g), f"import circles: {cycles(g)}"


@pytest.mark.parametrize(("edge", "check"), [
    (("hilsim.core.config", "hilsim.core.scenario"), "test_the_core_is_ordered"),
    (("hilsim.sim.world", "hilsim.launch.launcher"), "test_no_import_runs_up_or_sideways"),
    (("hilsim.services.physics", "hilsim.bridges.can_bus"), "test_no_import_runs_up_or_sideways"),
])
def test_the_check_sees_a_wrong_arrow(edge: tuple[str, str], check: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The checks fail on an upward or sideways arrow and on a circle (so they cannot pass vacuously)."""
    g = graph()
    src, dst = edge
    g[src] = {*g[src], dst}
    module = __import__(__name__)
    monkeypatch.setattr(module, "graph", lambda: g)
    with pytest.raises(AssertionError):
        getattr(module, check)()
    g[dst] = {*g[dst], src}
    assert cycles(g)
