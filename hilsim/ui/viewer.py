"""The recording in a browser: Rerun's own web viewer (bundled with rerun-sdk) on the current run's
``recording.rrd``, a ``rerun --serve-web`` child served on loopback (``POST /api/viewer``),
analytics off as everywhere in hilsim; one at a time, stopped with its whole process group.

No Zenoh keys: the viewer reads the recording file the run's logger wrote.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from pathlib import Path
from typing import Any

from hilsim.core import transport
from hilsim.ui.jsonio import BadInput
from hilsim.ui.run_control import child_setup


class Viewer:
    """The web viewer the panel started, if any, and the address the page opens it at."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None
        self.url = ""

    def shown(self) -> str:
        """The viewer's address while it runs, else ""."""
        return self.url if self.proc is not None and self.proc.poll() is None else ""

    def open(self, rec: str) -> dict[str, Any]:
        """Rerun's own web viewer (bundled with rerun-sdk) on the recording ``rec``, served on
        loopback: ``rerun --serve-web``; analytics off as everywhere in hilsim."""
        from hilsim.core.recording import rerun_config_home, rerun_env, rerun_executable

        if not rec or not Path(rec).is_file():
            raise BadInput("viewer", "no recording yet: start a run (with the logger) first", 409)
        self.stop()
        web, grpc = transport.free_port(), transport.free_port()
        env = {**os.environ, **rerun_env(), "XDG_CONFIG_HOME": str(rerun_config_home())}
        self.proc = subprocess.Popen(
            [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
             "--port", str(grpc), rec], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL, env=env, preexec_fn=child_setup)
        self.url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
        return {"url": self.url}

    def stop(self) -> None:
        """The viewer's whole process group: ``rerun`` may be a wrapper that starts the real binary."""
        v = self.proc
        if v is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(v.pid, signal.SIGTERM)
        try:
            v.wait(5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(v.pid, signal.SIGKILL)
            v.wait()
        self.proc = None
