"""Watch it live (``hilsim up … --view``, hilsim.record.live): the recorder's Rerun stream in Rerun's bundled
web viewer while the run goes on, opened in headless Chromium (Playwright driving the system's chromium),
and the stream's bounds: a viewer that reads nothing never holds the recorder, its frames are dropped and
counted.

Without chromium or Playwright the browser test is skipped with the reason, except under CI=true, where it
fails.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.core.scenario import load_scenario
from hilsim.record import live
from tests.util import REPO, finish, up

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


def _table_shown(shot: np.ndarray) -> float:
    """The fraction of the 3D view that is the table's brown: the world's geometry has reached the viewer."""
    v = shot[WORLD_VIEW]
    r, g, b = v[..., 0], v[..., 1], v[..., 2]
    return float(((r > g + 15) & (g > b + 15) & (r > 90) & (r < 220)).mean())


def _hilsim(*args: str, timeout: float = 120) -> str:
    r = subprocess.run([sys.executable, "-m", "hilsim.cli", *args], capture_output=True, text=True, timeout=timeout,
                       cwd=REPO)
    assert r.returncode == 0, (args, r.stdout, r.stderr)
    return r.stdout


def _truth(run: Path) -> list[float]:
    """The arm's joint positions now, from the physics truth."""
    out = _hilsim("topic", "echo", "/arm/truth/joint_states", "--count", "1", "--json", "--run", str(run))
    return [float(v) for v in json.loads(out.strip().splitlines()[-1])["position"]]


@pytest.mark.e2e
@pytest.mark.timeout(1200)
def test_live_web_viewer_shows_the_arm_moving(tmp_path: Path) -> None:
    """``hilsim up arm --interactive --view``: the browser opens the printed address; once the viewer shows
    the world, the arm is sent to two of the scenario's targets, and after each (reached, by the physics
    truth) the 3D view is photographed once it is still: the pictures differ where the arm is."""
    sync_playwright, exe = _browser()
    run = tmp_path / "run"
    p = up("arm", "--interactive", "--view", "--out", str(run), "--wait", "600", "--set", f"logger.record={LIVE_KEYS}")
    lines: list[str] = []
    url = ""
    assert p.stdout is not None
    for line in p.stdout:
        lines.append(line)
        if line.startswith("viewer: "):
            url = line.split(" ", 1)[1].strip()
            break
    assert url.startswith("http://127.0.0.1:"), "".join(lines)  # loopback by default
    info = json.loads((run / live.LIVE_NAME).read_text())
    assert info["viewer"] == url
    grpc_port = int(re.search(r":(\d+)/proxy", info["grpc"]).group(1))  # type: ignore[union-attr]
    rest: list[str] = []
    reader = threading.Thread(target=lambda: rest.extend(p.stdout), daemon=True)  # type: ignore[arg-type]
    reader.start()
    targets = load_scenario("arm").task.targets

    shots: list[np.ndarray] = []
    outside: list[str] = []  # requests the page made to anything but this host
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=exe, headless=True, args=[
                "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]})
            page.on("request", lambda r: outside.append(r.url) if not r.url.startswith(
                ("http://127.0.0.1", "data:", "blob:")) else None)
            page.goto(url + "&renderer=webgl", timeout=300_000, wait_until="domcontentloaded")

            def still() -> np.ndarray:
                """A screenshot once the 3D view shows the world and stopped changing (the viewer caught up)."""
                last = None
                for _ in range(40):
                    time.sleep(5)
                    shot = _pixels(page.screenshot(timeout=300_000))
                    if last is not None and _table_shown(shot) > 0.05 and not _changed(last, shot, WORLD_VIEW).any():
                        return shot
                    last = shot
                from PIL import Image

                Image.fromarray(last.astype(np.uint8)).save(tmp_path / "live-last.png")  # type: ignore[union-attr]
                raise AssertionError(f"the live view did not show the world and come to rest (table "
                                     f"{_table_shown(last):.3f} of the view)")  # type: ignore[arg-type]

            shots.append(still())  # the arm where it starts
            for target in targets[:2]:
                _hilsim("goal", "arm", "--joints", *map(str, target), "--run", str(run), timeout=300)
                assert np.allclose(_truth(run), target, atol=0.02), (_truth(run), target)
                shots.append(still())
            browser.close()
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
        out = finish(p, 300)
        reader.join(5)
    text = "".join(lines + rest) + out
    assert "result: OK" in text, text
    for i, s in enumerate(shots):  # for a person to look at
        from PIL import Image

        Image.fromarray(s.astype(np.uint8)).save(tmp_path / f"live-{i}.png")

    # the arm moved in the 3D view between targets, and only where it is
    area = (WORLD_VIEW[0].stop - WORLD_VIEW[0].start) * (WORLD_VIEW[1].stop - WORLD_VIEW[1].start)
    for i in (1, 2):
        mask = _changed(shots[i - 1], shots[i], WORLD_VIEW)
        moved = int(mask.sum())
        rows, cols = np.nonzero(mask)
        print(f"3D view, before and after target {i}: {moved} of {area} pixels differ ({100 * moved / area:.1f} %), "
              f"rows {rows.min() if moved else '-'}…{rows.max() if moved else '-'}, "
              f"columns {cols.min() if moved else '-'}…{cols.max() if moved else '-'} of the view")
        assert moved > 0.003 * area, f"the arm did not move in the live view: {moved} pixels changed (of {area})"
        # the camera, the table and the floor stay: what changed is the arm's part of the picture
        assert moved < 0.25 * area, f"{moved} of {area} pixels changed: more than the arm"
        assert abs(_table_shown(shots[i]) - _table_shown(shots[0])) < 0.1
    # nothing left this host: the viewer's update checks, fonts and analytics were refused by the page's policy
    assert not outside, outside
    # the stream stopped with the run: the viewer process is gone, its address file removed
    assert not (run / live.LIVE_NAME).exists()
    assert not _listening(grpc_port)
    log = (run / "logger.log").read_text()
    m = re.search(r"live viewer stopped: (\d+) frames \((\d+) bytes\) streamed, (\d+) dropped", log)
    assert m and int(m.group(1)) > 10, log


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


@pytest.mark.e2e
@pytest.mark.timeout(900)
def test_the_panel_shows_the_robot_live(tmp_path: Path) -> None:
    """``hilsim up arm --ui``: the panel starts its run with ``--view``; ``GET /api/live`` gives the viewer's
    address, and the page embeds it beside the joint plots (an iframe on that address, shown)."""
    from tests.test_panel import PanelProc, _http

    sync_playwright, exe = _browser()
    panel = PanelProc(up=["arm", "--interactive", "--set", f"logger.record={LIVE_KEYS}"])
    outside: list[str] = []
    try:
        got: dict[str, str] = {}

        def viewer() -> bool:
            got.update(_http(panel.url + "/api/live")[1])
            return bool(got.get("viewer"))

        assert live_wait(viewer, 300), panel.out()
        url = got["viewer"]
        assert url.startswith("http://127.0.0.1:") and "url=rerun%2Bhttp" in url, url
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=exe, headless=True, args=[
                "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.on("request", lambda r: outside.append(r.url) if not r.url.startswith(
                ("http://127.0.0.1", "data:", "blob:", "about:")) else None)
            page.goto(panel.page_url, timeout=300_000, wait_until="domcontentloaded")
            frame = page.locator("#live-view")
            frame.wait_for(state="visible", timeout=120_000)
            assert frame.get_attribute("src") == url
            # the viewer's page loaded in it (its own origin: the run's page server)
            assert live_wait(lambda: any(f.url.startswith(url.split("?")[0]) for f in page.frames), 120)
            box = frame.bounding_box()
            plot = page.locator("#plot").bounding_box()
            assert box and plot and box["x"] + box["width"] <= plot["x"] + 1, (box, plot)  # beside the plots
            time.sleep(20)
            page.screenshot(path=str(tmp_path / "panel-live.png"), timeout=300_000)
            browser.close()
    finally:
        panel.close(timeout=120)
    assert not outside, outside
