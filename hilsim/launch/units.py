"""Which processes a run starts here, and in what order they stop.

A scenario's launch units (a service, one per robot for a per-robot service ``controller@arm0``, or a
composed group ``a+b``) in the order they stop, each class's ``stop_rank`` (:func:`stop_order`: physics
first, the recorder last; they start in the reverse order), and the units of ``--only`` that this host
starts (:func:`local_units`). Reads and writes no key.
"""

from __future__ import annotations

from hilsim.core import fleet
from hilsim.core.config import Scenario


def stop_order(sc: Scenario) -> list[str]:
    """The scenario's processes in the order they stop (each class's ``stop_rank``: physics
    first, the recorder last); they start in the reverse order."""
    from hilsim.core.registry import service_class

    names = sc.launch_units()

    def rank(unit: str) -> int:
        # a composed process a+b+c stops at the rank of its first-stopping member, except one that
        # holds the recorder: it stops last, recording what the others publish as they stop
        ranks = {b: service_class(b, sc).stop_rank for b in (fleet.split_id(m)[0] for m in unit.split("+"))}
        return ranks["logger"] if "logger" in ranks else min(ranks.values())

    return sorted(names, key=lambda n: (rank(n), names.index(n)))


def local_units(sc: Scenario, only: list[str] | None) -> list[str]:
    """The launch units this host starts: all of them, or those of ``--only`` (services by name;
    a composed group ``a+b`` as a whole). ConfigError (one line) for a name the scenario lacks."""
    from hilsim.core.config import ConfigError

    units = sc.launch_units()
    if not only:
        return units
    procs = sc.processes()
    unknown = [n for n in only if n not in procs and n not in units]
    if unknown:
        raise ConfigError(f"--only {','.join(only)}: {', '.join(unknown)} not among this scenario's services "
                          f"({', '.join(procs)})")
    out = []
    for u in units:
        members = u.split("+")
        picked = [m for m in members if m in only or u in only]
        if picked and len(picked) != len(members):
            raise ConfigError(f"--only {','.join(only)}: {u} runs as one process (compose); name all of "
                              f"{', '.join(members)} or none")
        if picked:
            out.append(u)
    return out
