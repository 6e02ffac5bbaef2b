"""The robot, live, in the panel: the address of Rerun's web viewer that the run the panel shows streams to
(``hilsim up … --view``, :mod:`hilsim.record.live`), for the page's embedded 3D view (``GET /api/live``).

The panel's own runs stream live on demand (``logger.live.enabled``: from when the page shows the view, whose
loading joins the stream); a run it joined shows its view if that run was started with ``--view``. No Zenoh
keys: it reads ``<run dir>/live.json``.
"""

from __future__ import annotations

from typing import Any

from hilsim.core import run_finder
from hilsim.record.live_viewer import read_live


def live_address(panel: Any) -> str:
    """The live viewer's address of the run the panel shows ("" when it streams nothing live)."""
    run_dir = panel.run.info.get("run_dir") if panel.run.busy() else None
    if not run_dir:
        joined = run_finder.run_at([panel.endpoint])
        run_dir = joined.run_dir if joined is not None else None
    info = read_live(run_dir) if run_dir else None
    return str(info["viewer"]) if info else ""
