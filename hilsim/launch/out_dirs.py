"""Where commands put what they write: one directory per invocation under ``runs/``.

``hilsim up`` writes to ``runs/<timestamp>/``; other commands that produce files (e.g.
``hilsim plan evaluate``) write to ``runs/<timestamp>-<command>/``, so nothing lands in the
working directory and the newest output is easy to find. ``runs/`` is the scenario's
``logger.out_dir``.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path


def timestamp() -> str:
    """``YYYYmmdd-HHMMSS-mmm`` of now (local time), as run directories are named."""
    return datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]


def new_run_dir(base: str | Path, label: str = "") -> Path:
    """A fresh directory ``<base>/<timestamp>[-<label>]``, created."""
    name = timestamp() + (f"-{label}" if label else "")
    d = Path(base) / name
    d.mkdir(parents=True, exist_ok=False)
    return d
