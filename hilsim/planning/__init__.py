"""Motion planning for hilsim: planner library (OMPL + the paper's improved RRT*), MuJoCo collision
checking, ruckig trajectories, IK, the move action client, Table III evaluation and the benchmark.

See docs/planning.md. Modules import OMPL lazily, only where a planner is built.
"""

from __future__ import annotations

import atexit
import os
import sys

_quiet = False


def _to_devnull() -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 2)


def quiet_ompl_at_exit() -> None:
    """For a process's own exit path (a service's main or a CLI command), never library code:
    the OMPL binding (nanobind) prints 'leaked …' lines during interpreter shutdown, after all
    our output; stderr is pointed at /dev/null for that final phase only."""
    global _quiet
    if not _quiet:
        _quiet = True
        atexit.register(_to_devnull)
