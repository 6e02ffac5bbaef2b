"""Watch it live (``hilsim up … --view``, hilsim.record.live): the stream's bounds (a viewer that reads
nothing never holds the recorder; its frames are dropped and counted, the setup's never), a viewer process
that went away, the page server's policy and token, and a run that streams only once a viewer joins (read by
Rerun's own client, not written here).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from hilsim.core import transport
from hilsim.record import live, live_viewer


class _Frames:
    """A stand-in for the recording's binary sink: one frame of ``size`` bytes per read."""

    def __init__(self, size: int) -> None:
        self.size, self.n = size, 0

    def read(self, flush: bool = False) -> bytes:
        self.n += 1
        return bytes([self.n % 256]) * self.size


def test_a_viewer_that_reads_nothing_never_holds_the_recorder(tmp_path: Path) -> None:
    """The viewer process stopped (SIGSTOP): its pipe fills, the writer thread waits, and the recorder's
    pump keeps returning; the oldest frames not begun are dropped and counted, the setup's frame never."""
    stream = live.LiveStream(tmp_path)
    mb = 1024**2
    try:
        os.kill(stream.proc.pid, signal.SIGSTOP)
        stream.sink = _Frames(4 * mb)
        stream.pump()  # the writer takes it, and waits on the full pipe
        assert live_wait(lambda: stream.health()["live_queued"] == 0)
        stream.pump(essential=True)  # as the setup's frame: kept whatever comes after it
        for _ in range(30):  # 120 MB more against a 32 MB queue
            stream.pump()
        h = stream.health()
        assert h["live_frames"] == 0, h  # nothing reached the stopped viewer whole
        assert h["live_dropped"] >= 20 and h["live_dropped_bytes"] == h["live_dropped"] * 4 * mb, h
        assert h["live_queued"] <= live.QUEUE_BYTES + 4 * mb, h
        with stream.lock:
            kept = [keep for _, keep in stream.queue]
        assert kept[0] and kept.count(True) == 1, kept  # the setup's frame is next, not dropped
        assert len(kept) + h["live_dropped"] == 31, (len(kept), h)
    finally:
        os.kill(stream.proc.pid, signal.SIGCONT)
        stream.close(linger=0.5)
    assert stream.proc.poll() is not None  # the viewer process is stopped with the stream
    assert not (tmp_path / live.LIVE_NAME).exists()
    # a broken subprocess pipe is said once, and the recording goes on
    said: list[str] = []
    stream = live.LiveStream(tmp_path, warn=said.append)
    try:
        stream.proc.kill()
        stream.proc.wait()
        stream.sink = _Frames(1024)
        for _ in range(5):
            stream.pump()
            time.sleep(0.05)
        assert live_wait(lambda: bool(stream.stopped)), stream.health()
        assert said and "stopped reading" in said[0], said
    finally:
        stream.close(linger=0.1)


def live_wait(cond: Any, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def test_the_page_refuses_other_hosts_and_a_missing_token(tmp_path: Path) -> None:
    """The page server's policy lets the page reach its own origin and the run's gRPC server only; off
    loopback it asks the URL's token (then a cookie)."""
    import http.client
    import http.server

    class Upstream(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # http.server's name
            body = b"<html>viewer</html>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *a: Any) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Upstream)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    visits = 0

    def visited() -> None:
        nonlocal visits
        visits += 1

    page = live.PageProxy("127.0.0.1", 0, ("127.0.0.1", srv.server_address[1]), "http://127.0.0.1:9", token="s3cret",
                          on_visit=visited)
    try:
        def get(path: str, cookie: str = "") -> http.client.HTTPResponse:
            c = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
            c.request("GET", path, headers={"Cookie": cookie} if cookie else {})
            return c.getresponse()

        assert get("/").status == 403
        assert get("/?token=wrong").status == 403
        r = get("/?token=s3cret")
        assert r.status == 200 and r.read() == b"<html>viewer</html>"
        policy = r.getheader("Content-Security-Policy") or ""
        assert "connect-src 'self' http://127.0.0.1:9;" in policy and "default-src 'self'" in policy, policy
        cookie = (r.getheader("Set-Cookie") or "").split(";")[0]
        assert get("/index.js", cookie).status == 200
        assert visits == 2  # the page and its script: a viewer is here
        assert get(live.WATCH_PATH).status == 403 and visits == 2  # joining asks the token too
        w = get(f"{live.WATCH_PATH}?token=s3cret")
        assert w.status == 204 and w.read() == b"" and visits == 3  # answered here, not by the viewer's server
    finally:
        page.close()
        srv.shutdown()
        srv.server_close()


def _lines_until(p: subprocess.Popen[str], start: str) -> list[str]:
    """What ``hilsim up`` printed, up to the first line that starts with ``start`` (or its end)."""
    assert p.stdout is not None
    lines: list[str] = []
    for line in p.stdout:
        lines.append(line)
        if line.startswith(start):
            break
    return lines


@pytest.mark.e2e
@pytest.mark.timeout(300)
def test_a_run_streams_only_once_a_viewer_joins(tmp_path: Path) -> None:
    """``logger.live.enabled`` (as the panel's runs): ``hilsim up`` prints ``viewer: URL``; until a viewer joins,
    Rerun's own client connected to the run's stream gets the world and the robot's model but no row of the arm's
    motion; once ``hilsim view --live`` joined, the transforms stream (and the recorder's log says so)."""
    from test_live_browser import LIVE_KEYS, _client, _received
    from util import LEAN, finish, up

    run = tmp_path / "run"
    p = up(LEAN, "--interactive", "--out", str(run), "--set", "logger.live.enabled=true", "--set",
           f"logger.record={LIVE_KEYS}")
    try:
        lines = _lines_until(p, "viewer: ")
        assert lines and lines[-1].startswith("viewer: http://127.0.0.1:"), "".join(lines)
        info = live_viewer.read_live(run)
        assert info is not None and lines[-1].split()[1] == info["viewer"], (lines[-1], info)
        time.sleep(3)  # the arm runs 3 s with nobody watching
        before = tmp_path / "before.rrd"
        c = _client(info["grpc"], before)
        time.sleep(3)
        entities, quats = _received(c, before)
        assert any(e.startswith("/world/") for e in entities) and any(e.startswith("/robot/") for e in entities), \
            sorted(entities)[:20]  # the setup's static rows: a viewer that joins sees the world and the robot
        assert not quats, f"{len(quats)} transforms streamed with nobody watching"
        joined = subprocess.run([sys.executable, "-m", "hilsim.cli", "view", "--live", "--run", str(run)],
                                capture_output=True, text=True, timeout=60, env={**os.environ, "DISPLAY": ""})
        assert joined.returncode == 0 and f"viewer: {info['viewer']}" in joined.stdout, joined
        after = tmp_path / "after.rrd"
        c = _client(info["grpc"], after)
        time.sleep(3)
        _, quats = _received(c, after)
        assert len(quats) > 10, f"{len(quats)} transforms of the first joint in 3 s after a viewer joined"
        assert "a viewer joined" in (run / "logger.log").read_text()
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
        out = finish(p, 120)
    assert "result: OK" in out, out[-2000:]


def test_view_on_the_command_line_waits_for_its_viewer() -> None:
    """``hilsim up --view`` with a task waits for its viewer before it starts (120 s, ``--view-wait``'s); an
    interactive run does not (it waits for goals), nor one with ``logger.live.enabled`` alone (the panel's)."""
    from hilsim.cli import build_parser
    from hilsim.launch.up import up_overrides

    def overrides(*argv: str) -> dict[str, Any]:
        return up_overrides(build_parser().parse_args(["up", "arm", *argv]))[0]

    assert "logger.live.wait" not in overrides("--set", "logger.live.enabled=true")
    assert overrides("--view")["logger.live.wait"] == 120
    assert overrides("--view", "--view-wait", "0")["logger.live.wait"] == 0
    assert "logger.live.wait" not in overrides("--view", "--interactive")


def _physics_of(run: Path) -> list[int]:
    """The pids of the physics processes of the run in ``run``."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                args = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"physics" in args and any(str(run).encode() in a for a in args):
                pids.append(int(d.name))
    return pids


@pytest.mark.e2e
@pytest.mark.timeout(400)
def test_view_with_a_task_starts_once_a_viewer_joins(tmp_path: Path) -> None:
    """``hilsim up … --view`` with a task: the viewer's address, then the run waits with physics not started
    until a viewer joins (here ``hilsim view --live``), then runs its task; with nobody coming it starts after
    ``--view-wait`` seconds all the same."""
    from util import LEAN, finish, up

    run = tmp_path / "run"
    p = up(LEAN, "--view", "--view-wait", "120", "--clock", "lockstep", "--out", str(run), "--set",
           'logger.record=["tf/**"]')
    lines: list[str] = []
    viewer: live_viewer.HeadlessViewer | None = None
    died: str | None = None
    try:
        lines = _lines_until(p, "waiting for a viewer")
        text = "".join(lines)
        assert "viewer: http://127.0.0.1:" in text and "waiting for a viewer" in lines[-1], text
        time.sleep(2)
        assert "physics" not in next(x for x in lines if x.startswith("ready: ")), text
        assert not _physics_of(run), "physics started before a viewer joined"  # nothing moves yet
        # joined (as a browser loading the page does) but no viewer connected to the stream yet (a browser's
        # compiles first): still nothing moves
        joined = subprocess.run([sys.executable, "-m", "hilsim.cli", "view", "--live", "--run", str(run)],
                                capture_output=True, text=True, timeout=60, env={**os.environ, "DISPLAY": ""})
        assert joined.returncode == 0, joined
        time.sleep(3)
        assert not _physics_of(run), "physics started before a viewer connected"
        # a viewer connects (Rerun's own, headless): the run starts
        # (at the default priority: at idle priority it could wait minutes on a CI machine kept busy by other tests)
        viewer = live_viewer.HeadlessViewer(json.loads((run / "live.json").read_text()), tmp_path / "viewer.log",
                                            idle=False)
    finally:
        out = "".join(lines) + finish(p, 300)
        if viewer is not None:
            died = viewer.failure()  # one that died at once may still have connected for a moment
            viewer.stop()
    assert died is None, died
    assert "a viewer joined: starting" in out and "result: OK" in out, out[-3000:]

    run2 = tmp_path / "run2"
    p = up(LEAN, "--view", "--view-wait", "2", "--clock", "lockstep", "--out", str(run2), "--set",
           'logger.record=["tf/**"]')
    out = finish(p, 300)
    assert "no viewer joined in 2 s: starting without one" in out and "result: OK" in out, out[-3000:]


def test_a_viewer_hilsim_starts_runs_at_idle_priority_and_says_how_it_ended(tmp_path: Path) -> None:
    """The viewer as ``hilsim view --live`` starts it runs on what the simulation leaves of the cores
    (SCHED_IDLE); a headless one draws here (Vulkan by software), and one that ended says how."""
    info = {"grpc": f"rerun+http://127.0.0.1:{transport.free_port()}/proxy"}  # nobody there: it keeps trying
    v = live_viewer.HeadlessViewer(info, tmp_path / "idle.log")
    try:
        assert os.sched_getscheduler(v.proc.pid) == os.SCHED_IDLE
        time.sleep(3)  # past its first frame (where it stops without a Vulkan device)
        assert v.failure() is None, v.failure()
    finally:
        v.stop()
    assert "exited with code" in (v.failure() or "")
    normal = live_viewer.HeadlessViewer(info, tmp_path / "normal.log", idle=False)
    try:
        assert os.sched_getscheduler(normal.proc.pid) == os.SCHED_OTHER
    finally:
        normal.stop()
