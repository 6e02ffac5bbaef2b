"""The recorder's loss accounting at its end, and what it must hold: pure functions of its counts.

- :func:`judged_lost`: per key, the samples the recorder dropped itself (exact) plus the gaps in its
  writers' sequence numbers, no more gaps than the writers' own counts (their final health's
  ``published:<key>``) leave unexplained: one count per cause, never negative.
- :func:`expected_keys`: the latched keys a run publishes once at its start and a recording must hold.

Reads and writes no key (services/logger.py gives it its counts).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from hilsim.core import fleet
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys


def judged_lost(gaps: Counter[str], dropped: Counter[str], received: Counter[str], suspect: Counter[str],
                before: Counter[str], published: Counter[str]) -> Counter[str]:
    """Per key, ``dropped`` plus the gaps, the gaps capped at what the key's services say they published
    and did not reach the recorder otherwise (a gap left by a forged number is no loss when every sample
    the writers published arrived). ``published`` holds only keys some service counted."""
    out: Counter[str] = Counter()
    for k in set(gaps) | set(dropped):
        g = gaps[k]
        if g and k in published:
            own = received[k] - suspect[k]
            g = min(g, max(0, published[k] - own - before[k] - dropped[k]))
        out[k] = g + dropped[k]
    return +out


def expected_keys(sc: Scenario, keys: Keys, covers: Callable[[str], bool]) -> set[str]:
    """Physics' ``/tf_static`` and every robot's ``robot_description`` (a robot with a URDF), within what the
    recorder records (``covers``). Not every transient-local writer's: an action's status is latched too,
    and says nothing until a goal comes."""
    out: set[str] = set()
    if "physics" in sc.services and sc.world.urdf is not None:
        out.update([keys.tf_static, *(Keys.of(sc, r).topic("robot_description") for r in fleet.robot_names(sc))])
    return {k for k in out if covers(k)}
