"""``hilsim up SCENARIO --world NAME``: which scenario file runs a scenario in another world.

A scenario's world is its own (``world.model``, ``models/worlds/NAME.xml``) or that of a variant
``<scenario>-NAME.yaml`` next to it, which sets the world and what goes with it. Used by ``hilsim up``,
the panel and the benchmarks.

Reads and writes no Zenoh key: only scenario files.
"""

from __future__ import annotations

from pathlib import Path

from hilsim.core.scenario import load_scenario


def _world_of(path: Path) -> str | None:
    try:
        return load_scenario(path).world.model.stem
    except Exception:  # not a scenario (an overlay), or a broken one: no world to offer
        return None


def world_scenario(scenario: str, world: str) -> str:
    """``hilsim up SCENARIO --world NAME``: the scenario itself when its world is
    ``models/worlds/NAME.xml``, else its variant ``<scenario>-NAME.yaml`` next to it (which sets that
    world and what goes with it: the GPS and its datum, the goals); anything else is a one-line error."""
    from hilsim.core.config import ConfigError
    from hilsim.core.scenario import scenario_path

    base = scenario_path(scenario)
    own = load_scenario(base).world.model.stem
    if world == own:
        return str(base)
    variant = base.with_name(f"{base.stem}-{world}.yaml")
    if variant.exists():
        return str(variant)
    variants = {p.stem[len(base.stem) + 1:]: p for p in base.parent.glob(f"{base.stem}-*.yaml")}
    worlds = [own, *sorted(w for w, p in variants.items() if _world_of(p) == w)]
    raise ConfigError(f"--world {world}: scenario {base.stem} has no such world (worlds: {', '.join(worlds)}; "
                      f"a world W needs {base.parent.name}/{base.stem}-W.yaml)")
