"""What a service restarted by ``hilsim up`` takes over from the process that died.

``hilsim up`` restarts a service under the scenario's restart policy (``restart.services``, see
:class:`hilsim.core.config.RestartConfig`) with ``HILSIM_RESTART=<attempt>`` in its environment. Most
of a service's state comes back on its own: the controller measures where the arm is from
``joint_states``, the planner re-sends the trajectory being executed when a controller
(re)appears. What only the dead process knew (live gain changes, how far the scenario task had
got) a service keeps with :func:`keep` in ``<run dir>/state/<service>.json`` (one robot of several:
``<service>@<robot>.json``) (written atomically,
so a SIGKILL leaves the previous version or the new one) and reads back with :func:`kept`, which
answers only in a restarted process: a fresh run never inherits a previous run's state
(``hilsim up`` also empties ``state/`` when it starts).
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

from hilsim.core.config import Scenario

RESTART_ENV = "HILSIM_RESTART"  # set by hilsim up in a restarted process: the attempt number
STATE_DIR = "state"


def restarted() -> int:
    """The restart attempt this process is (0: the first start)."""
    try:
        return int(os.environ.get(RESTART_ENV, "0"))
    except ValueError:
        return 0


def state_path(sc: Scenario, service: str) -> Path | None:
    """Where ``service`` keeps its state in this run (None outside ``hilsim up``: no run dir)."""
    d = sc.logger.run_dir
    # one robot of several (robots: N): its own file, <service>@<robot>.json (hilsim.core.fleet)
    name = f"{service}@{sc.robot}" if sc.fleet_member else service
    return None if d is None else Path(d) / STATE_DIR / f"{name}.json"


def keep(sc: Scenario, service: str, state: dict[str, Any]) -> None:
    """Save ``state`` (JSON) for a restarted ``service``; atomic replace, never half a file."""
    path = state_path(sc, service)
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")  # composed: services share a pid
    tmp.write_text(json.dumps(state, sort_keys=True))
    tmp.replace(path)


def kept(sc: Scenario, service: str) -> dict[str, Any]:
    """The state the previous process of ``service`` kept; empty unless this is a restart."""
    path = state_path(sc, service)
    if not restarted() or path is None:
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
