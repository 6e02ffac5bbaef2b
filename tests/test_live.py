"""Watch it live (``hilsim up … --view``, hilsim.record.live): the recorder's Rerun stream in Rerun's bundled
web viewer while the run goes on, opened in headless Chromium (Playwright driving the system's chromium),
and the stream's bounds: a viewer that reads nothing never holds the recorder, its frames are dropped and
counted.

Without chromium or Playwright the browser test is skipped with the reason, except under CI=true, where it
fails.
"""

from __future__ import annotations

import io
import os
import shutil
import signal
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.record import live

# what the browser test records: the keys the 3D view and the joint plots draw (a software-rendering
# browser on two loaded cores keeps up with these; every key at 1 kHz it does not)
LIVE_KEYS = '["arm/truth/joint_states", "arm/joint_trajectory", "arm/planner/path", "clock"]'
VIEWPORT = (1000, 640)
WORLD_VIEW = (slice(70, 360), slice(205, 515))  # rows, columns of the 3D view ("world") in the default layout


def _browser() -> tuple[Any, str]:
    """Playwright's sync API and the system chromium; skip (fail under CI=true) without them."""
    why = ""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        why = "playwright is not installed (pip install -e '.[test]')"
        sync_playwright = None
    exe = shutil.which("chromium") or shutil.which("chromium-browser") or ""
    if not why and not exe:
        why = "no chromium on PATH (apt-get install chromium; scripts/test.sh does it as root)"
    if why:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true: the browser test must run, but {why}")
        pytest.skip(why)
    return sync_playwright, exe


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def _changed(a: np.ndarray, b: np.ndarray, region: tuple[slice, slice]) -> np.ndarray:
    """Pixels of ``region`` that differ clearly (not by anti-aliasing) between two screenshots."""
    return np.abs(a[region] - b[region]).sum(axis=2) > 60


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


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
    page = live.PageProxy("127.0.0.1", 0, ("127.0.0.1", srv.server_address[1]), "http://127.0.0.1:9", token="s3cret")
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
    finally:
        page.close()
        srv.shutdown()
        srv.server_close()
