"""The viewer's side of a run's live stream (:mod:`hilsim.record.live`): find it (:func:`read_live`,
:func:`wait_live`), join it (:func:`join`, as loading the page does), tell whether a viewer is connected to it
(:func:`viewer_connected`: ``hilsim up --view`` starts its task only then), ``hilsim view --live``, and a
headless Rerun viewer for benchmarks and tests (:class:`HeadlessViewer`).

Zenoh keys: none. Files: reads ``<run dir>/live.json``.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import re
import subprocess
import time
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hilsim.core.recording import has_display, rerun_env, rerun_executable
from hilsim.record.live import LIVE_NAME


def read_live(run_dir: str | Path) -> dict[str, Any] | None:
    """The live viewer's addresses of a run that is up with ``--view`` (``viewer``, ``grpc``), else None."""
    p = Path(run_dir) / LIVE_NAME
    try:
        info = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and "viewer" in info else None


def join(info: dict[str, Any], timeout: float = 10.0) -> None:
    """Tell a run's live stream a viewer joins (its rows stream from now on), as loading the page does; for a
    viewer that connects to the gRPC address itself (``hilsim view --live``, Rerun's native viewer).
    Raises OSError if the page server does not answer."""
    if not info.get("watch"):
        return  # no page server's address: nothing to tell
    u = urllib.parse.urlsplit(str(info["watch"]))
    conn = http.client.HTTPConnection(u.hostname or "127.0.0.1", u.port or 80, timeout=timeout)  # no proxy: loopback
    try:
        conn.request("GET", f"{u.path}?{u.query}" if u.query else u.path)
        r = conn.getresponse()
        r.read()
        if r.status != 204:
            raise OSError(f"{info['watch']} answered {r.status} {r.reason}")
    finally:
        conn.close()


def idle_priority() -> None:
    """In a viewer's process (``preexec_fn``): it runs only on what the simulation leaves of the cores
    (``SCHED_IDLE``), so a viewer on the machine of a run that fills its cores falls behind (what it has not
    drawn yet waits in the stream's server) instead of slowing the run (``hilsim bench loop --live``: a viewer
    drawing by software at the default priority cost the arm 11 % of its speed on 2 cores)."""
    with contextlib.suppress(OSError, AttributeError):  # AttributeError: not Linux
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


class HeadlessViewer:
    """Rerun's native viewer without a window, connected to a run's stream (``info``: :func:`read_live`), taking
    in and drawing every frame as one on this host does, started as ``hilsim view --live`` starts its viewer
    (:func:`idle_priority`): the viewer of benchmarks and tests. Its output goes to ``log``. It draws with Vulkan:
    where only OpenGL is there (llvmpipe without Mesa's lavapipe, Debian's ``mesa-vulkan-drivers``), Rerun
    0.41's headless viewer stops at its first frame ("Failed to get render context"), so :meth:`failure` is
    asked after use: a viewer that died measured nothing."""

    def __init__(self, info: dict[str, Any], log: Path, *, idle: bool = True) -> None:
        """``idle``: at :func:`idle_priority`, as ``hilsim view --live`` starts a viewer; False at the default
        priority (a test that needs the viewer connected soon on a machine other tests keep busy)."""
        self.log = log
        with open(log, "wb") as out:
            self.proc = subprocess.Popen([rerun_executable(), "--headless", "--bind", "127.0.0.1", "--new", "--connect",
                                          str(info["grpc"])], stdout=out, stderr=subprocess.STDOUT,
                                         env={**os.environ, **rerun_env()}, preexec_fn=idle_priority if idle else None)

    def failure(self) -> str | None:
        """None while the viewer runs, else how it ended: its exit code and the first line of its output that
        says why (a panic, an error)."""
        code = self.proc.poll()
        if code is None:
            return None
        text = re.sub(r"\x1b\[[0-9;]*m", "", self.log.read_text(errors="replace"))
        why = next((ln.strip() for ln in text.splitlines() if "panicked" in ln or " ERROR " in ln), "")
        return f"Rerun's headless viewer exited with code {code}" + (f": {why}" if why else "") + f" ({self.log})"

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


def viewer_connected(info: dict[str, Any]) -> bool:
    """Whether a viewer is connected to the live stream's server (a TCP connection to its gRPC port): a browser
    loads the page and joins seconds before its viewer (compiled then) connects. True where it cannot be told
    (the server's process is not this host's, e.g. a container's)."""
    import psutil

    try:
        port = urllib.parse.urlsplit(str(info["grpc"]).removeprefix("rerun+")).port
        server = psutil.Process(int(info["server"]))
        if "rerun" not in server.name():  # a pid of another PID namespace (a container's), not ours
            return True
        conns = server.net_connections(kind="tcp")
    except (KeyError, ValueError, TypeError, psutil.Error):
        return True
    return any(c.status == psutil.CONN_ESTABLISHED and c.laddr and c.laddr.port == port for c in conns)


def wait_live(run_dir: str | Path, timeout: float, alive: Callable[[], bool] = lambda: True,
              watched: bool = False) -> dict[str, Any] | None:
    """:func:`read_live`, waiting up to ``timeout`` seconds while ``alive()``; ``watched``: until it also says a
    viewer joined and one is connected to the stream (``hilsim up`` waits for that with ``logger.live.wait``),
    else None."""
    end = time.monotonic() + timeout
    while True:
        info = read_live(run_dir)
        if info is not None and (not watched or (info.get("watched") and viewer_connected(info))):
            return info
        if time.monotonic() >= end or not alive():
            return None
        time.sleep(0.1)


# ---------------------------------------------------------------------- hilsim view --live
def cmd_view_live(args: Any) -> int:
    """``hilsim view --live [--run DIR]``: the live viewer of a run that is up with ``--view``: its address
    (``viewer: URL``), and with a display Rerun's native viewer connected to the run's stream."""
    import sys

    from hilsim.core import run_finder
    from hilsim.core.config import ConfigError

    try:
        if args.run:
            run_dir = Path(args.run)
        else:
            up = run_finder.live_runs()
            if not up:
                raise ConfigError("no run of yours is up (start one with `hilsim up arm --view`)")
            run_dir = (up[0] if len(up) == 1 else run_finder.choose_run(up, "hilsim view --live")).run_dir
    except ConfigError as e:
        print(f"hilsim view --live: {e}", file=sys.stderr)
        return 1
    info = read_live(run_dir)
    if info is None:
        print(f"hilsim view --live: {run_dir} streams nothing live (is it up? it must be started with "
              "`hilsim up … --view`)", file=sys.stderr)
        return 1
    try:
        join(info)
    except OSError as e:
        print(f"hilsim view --live: {run_dir}'s viewer does not answer ({e})", file=sys.stderr)
        return 1
    print(f"viewer: {info['viewer']}", flush=True)
    if not has_display():
        return 0
    try:  # the native viewer, connected to the run's stream (it ends when its window is closed); on what the
        # simulation leaves of the cores
        return subprocess.call([rerun_executable(), "--connect", str(info["grpc"])], env={**os.environ, **rerun_env()},
                               preexec_fn=idle_priority)
    except KeyboardInterrupt:
        return 130
