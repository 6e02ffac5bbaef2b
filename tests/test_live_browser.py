"""Watch it live (``hilsim up … --view``, hilsim.record.live), from the outside: one run started by the panel
(``hilsim up … --ui``, whose runs stream live), joined by headless Chromium (Playwright driving the system's
chromium) and by Rerun's own client (the ``rerun`` CLI, ``--connect … --save``), neither written here.

- The browser: the panel's page embeds the live view (``#live-view``) on the address ``GET /api/live`` gives,
  that of the run the panel shows, and Rerun's web viewer page loads in it from the run's page server; nothing
  the page asks for leaves this host.
- Rerun's client: what the run streams holds the world and the robot's model, and the arm's
  transforms move with the arm: sent to a target, the client's last transform of the first joint is the
  physics truth's.
- The stream stops with the run.

- The pictures: screenshots of the embedded viewer while the arm goes from its start to two targets either side
  of the obstacle. In its 3D view (found by the table, the one large brown thing) two pictures of the arm at rest
  are the same, and each move changes the pixels around the arm; the pixels both moves changed are where the arm
  stood between them. The test prints how many pixels changed where.

Without chromium or Playwright the test is skipped with the reason, except under CI=true, where it fails.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from util import LEAN, Observer, chromium, wait_until

from hilsim.core.recording import rerun_env, rerun_executable
from hilsim.core.scenario import load_scenario
from hilsim.record import live

# what the run records (and so streams): the robot's transforms (/tf, 50 Hz) and the planned path; the model,
# the world and the layout are the recorder's own setup, always sent. Every key at 1 kHz is not needed here.
LIVE_KEYS = '["tf/**", "arm/planner/path/**"]'


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _client(grpc: str, path: Path) -> subprocess.Popen[bytes]:
    """Rerun's own client joined to the run's stream, saving what it receives to ``path``."""
    return subprocess.Popen([rerun_executable(), "--connect", grpc, "--save", str(path)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, **rerun_env()})


def _received(client: subprocess.Popen[bytes], path: Path) -> tuple[set[str], list[list[float]]]:
    """Stop Rerun's client and read what it saved: the entity paths, and the quaternions of the first joint's
    transforms (``tf/shoulder_link``) in the order received."""
    import warnings

    from rerun.chunk import RrdReader  # rerun 0.41's reader (hilsim.core.recording reads files with it too)

    client.terminate()
    client.wait(30)
    entities: set[str] = set()
    quats: list[list[float]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer": the client was stopped
        for chunk in RrdReader(path).stream().to_chunks():
            entities.add(chunk.entity_path)
            if chunk.entity_path == "/tf/shoulder_link":
                quats += [q[0] for q in chunk.to_record_batch().column("Transform3D:quaternion").to_pylist()]
    return entities, quats


# the arm world's table as Rerun's viewer shades it (config/worlds: its box's colour): the largest thing of that
# colour in a picture of the viewer is the table, and the 3D view is around it
TABLE_RGB = (158, 120, 77)
CHANGED = 40  # a pixel changed: its R+G+B moved by more than this (software rendering is exact frame to frame)


def _picture(png: bytes) -> np.ndarray:
    from PIL import Image  # pillow: a dependency of rerun-sdk

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def _table(img: np.ndarray) -> tuple[int, int, int, int] | None:
    """The table's box in a picture (x0, y0, x1, y1): the largest region of its colour, None before it is drawn."""
    from scipy import ndimage

    labels, n = ndimage.label(np.abs(img - np.array(TABLE_RGB)).max(axis=2) < 40)
    if n == 0:
        return None
    sizes = ndimage.sum_labels(np.ones(labels.shape), labels, range(1, n + 1))
    if sizes.max() < 2000:  # a line of a plot or a legend's dot is not the table
        return None
    ys, xs = np.nonzero(labels == 1 + int(sizes.argmax()))
    return int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())


def _around_the_arm(table: tuple[int, int, int, int]) -> tuple[slice, slice]:
    """Where the arm is drawn: above the table it stands on (as high again as the table is drawn), across it."""
    x0, y0, x1, y1 = table
    return slice(max(0, y0 - (y1 - y0)), y1 + 1), slice(x0, x1 + 1)


def _changed(a: np.ndarray, b: np.ndarray, where: tuple[slice, slice]) -> np.ndarray:
    return np.abs(a[where] - b[where]).sum(axis=2) > CHANGED


def _path(img: np.ndarray, where: tuple[slice, slice]) -> np.ndarray:
    """The planned tool path's pixels (drawn in yellow, COLOURS["plan"], with its anti-aliased edges)."""
    from scipy import ndimage

    r, g, b = (img[where][..., i] for i in range(3))
    return ndimage.binary_dilation((r > 180) & (g > 140) & (b < 120) & (r - b > 100), iterations=3)


def _box(mask: np.ndarray) -> str:
    ys, xs = np.nonzero(mask)
    return f"x {xs.min()}-{xs.max()}, y {ys.min()}-{ys.max()}" if len(xs) else "none"


@pytest.mark.e2e
@pytest.mark.timeout(900)
def test_the_panel_and_rerun_see_the_arm_live(tmp_path: Path) -> None:
    """The panel's run streams live: its page embeds the viewer of that run, and Rerun's client, joined to the
    same stream, sees the world, the robot and the arm's first joint turn to a target as the truth says."""
    from test_live import live_wait
    from test_panel import PanelProc, _http

    sync_playwright, exe = chromium()
    run = tmp_path / "run"
    panel = PanelProc(up=[LEAN, "--interactive", "--out", str(run), "--set", f"logger.record={LIVE_KEYS}"])
    saved = tmp_path / "client.rrd"
    client: subprocess.Popen[bytes] | None = None
    obs: Observer | None = None
    outside: list[str] = []  # requests the page made to anything but this host
    try:
        got: dict[str, str] = {}

        def viewer() -> bool:
            got.update(_http(panel.url + "/api/live")[1])
            return bool(got.get("viewer"))

        assert live_wait(viewer, 300), panel.out()
        url = got["viewer"]
        info = json.loads((run / live.LIVE_NAME).read_text())  # the run the panel started and shows
        assert url == info["viewer"] and url.startswith("http://127.0.0.1:") and "url=rerun%2Bhttp" in url, url
        grpc_port = int(re.search(r":(\d+)/proxy", info["grpc"]).group(1))  # type: ignore[union-attr]
        client = _client(info["grpc"], saved)

        target, other = load_scenario("arm").task.targets[:2]  # left, then right of the obstacle
        obs = Observer(panel.endpoint)  # the physics truth, on the panel's router (closed below)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=exe, headless=True, args=[
                "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.set_default_timeout(180_000)  # the viewer's wasm in the frame holds a busy machine's cores a while
            # a request elsewhere that got an answer left this host (the viewer's page asks Google's fonts, which
            # its policy refuses in the browser: failed as "csp", not counted)
            page.on("requestfinished", lambda r: outside.append(r.url) if not r.url.startswith(
                ("http://127.0.0.1", "data:", "blob:", "about:")) else None)
            page.on("requestfailed", lambda r: outside.append(f"{r.url}: {r.failure}") if not r.url.startswith(
                ("http://127.0.0.1", "data:", "blob:", "about:")) and "csp" not in (r.failure or "").lower() else None)
            page.goto(panel.page_url, timeout=300_000, wait_until="domcontentloaded")
            frame = page.locator("#live-view")
            # offered, not loaded until asked (its wasm would hold a small machine's cores)
            page.locator("#live-show").wait_for(state="visible", timeout=120_000)
            assert not frame.is_visible() and frame.get_attribute("src") in (None, "about:blank")
            page.click("#live-show")
            frame.wait_for(state="visible", timeout=120_000)
            assert frame.get_attribute("src") == url
            box, plot = frame.bounding_box(), page.locator("#plot").bounding_box()
            assert box and plot and box["width"] > 200 and box["height"] > 150, box
            assert box["x"] + box["width"] <= plot["x"] + 1, (box, plot)  # beside the joint plots
            # Rerun's viewer page loaded in the frame, from the run's page server: its canvas is there
            assert live_wait(lambda: any(f.url == url for f in page.frames), 120), [f.url for f in page.frames]
            inner = next(f for f in page.frames if f.url == url)
            inner.wait_for_selector("canvas", state="attached", timeout=120_000)

            shots: dict[str, np.ndarray] = {}

            def shoot(name: str) -> np.ndarray:
                png = frame.screenshot()
                (tmp_path / f"{name}.png").write_bytes(png)
                shots[name] = _picture(png)
                return shots[name]

            # the viewer draws the world: the table appears in its 3D view
            t0 = time.monotonic()
            table: tuple[int, int, int, int] | None = None
            while table is None and time.monotonic() - t0 < 300:
                table = _table(shoot("start"))
                time.sleep(1)
            assert table is not None, f"no table drawn in 300 s: see {tmp_path / 'start.png'}"
            drawn_s = time.monotonic() - t0
            where = _around_the_arm(table)

            def settled(name: str) -> np.ndarray:
                """A picture once two taken a second apart are the same where the arm is (the view caught up)."""
                last = shoot(name)
                for _ in range(60):
                    time.sleep(1)
                    now = shoot(name)
                    if not _changed(last, now, where).any():
                        return now
                    last = now
                return last

            rest = settled("start")
            time.sleep(2)
            rest2 = shoot("start-again")

            # the client saw the arm's start (the first joint at 0); it is stopped to read what it saved
            entities, quats = _received(client, saved)
            client = None
            assert quats, f"Rerun's client received no transform of the arm: {sorted(entities)[:20]}"
            assert abs(quats[0][2]) < 0.01, quats[:5]

            truth: list[float] = []
            for name, goal_q in (("left", target), ("right", other)):  # the arm to a target, then to the other
                status, data = _http(panel.url + "/api/goal", {"kind": "joints", "positions": list(goal_q)})
                assert status == 200, data
                gid = data["goal_id"]
                done = lambda gid=gid: any(g["id"] == gid and g["done"] for g in panel.state()["goals"])  # noqa: E731
                assert wait_until(done, 300)
                goal = next(g for g in panel.state()["goals"] if g["id"] == gid)
                assert goal["success"], goal
                done_ns = round(goal["sim"] * 1e9)
                assert wait_until(lambda t=done_ns: bool(obs.truth) and obs.truth[-1][0] >= t, 60)
                truth.append(float(obs.truth_at(done_ns)[0]))
                assert abs(truth[-1] - goal_q[0]) < 0.02, (truth[-1], goal_q)
                settled(name)
            browser.close()
        obs.close()
        obs = None

        # the pictures: the same at rest, changed around the arm by each move, and both moves changed the pixels
        # where the arm stood between them
        # (the planned path, yellow, is told apart: it changes with each plan whether or not the arm moves)
        path = {name: _path(shots[name], where) for name in ("start", "left", "right")}
        still = _changed(rest, rest2, where)
        moved = _changed(rest, shots["left"], where) & ~path["start"] & ~path["left"]
        moved_back = _changed(shots["left"], shots["right"], where) & ~path["left"] & ~path["right"]
        both = moved & moved_back
        area = still.size
        print(f"the viewer drew the table in {drawn_s:.0f} s; around the arm ({area} px, {_box(np.ones_like(still))} "
              f"of the {shots['left'].shape[1]}x{shots['left'].shape[0]} frame, above the table at {table}): at rest "
              f"{int(still.sum())} px changed in 2 s; start -> left target {int(moved.sum())} px ({_box(moved)}); "
              f"left -> right target {int(moved_back.sum())} px ({_box(moved_back)}); changed by both moves (the "
              f"arm at the left target) {int(both.sum())} px ({_box(both)}); the planned path "
              f"{int(path['left'].sum())} px ({_box(path['left'])}) at the left target, "
              f"{int(path['right'].sum())} px at the right; pictures in {tmp_path}")
        assert not path["start"].any(), f"yellow before any plan: {_box(path['start'])}"
        assert path["left"].sum() >= 30 and path["right"].sum() >= 30, "the planned path is not drawn"
        assert still.sum() <= 0.001 * area, f"the 3D view changed with the arm at rest: {_box(still)}"
        for name, mask in (("start -> left", moved), ("left -> right", moved_back)):
            assert mask.sum() >= max(100, 20 * still.sum()), f"{name}: the arm did not move in the picture"
            assert mask.sum() <= 0.5 * area, f"{name}: more changed than the arm ({_box(mask)}): the view moved?"
        assert both.sum() >= 20, "no pixel changed on both moves: the arm at the left target is nowhere drawn"
        q1 = truth[-1]

        def turned() -> bool:
            """A client joining now gets the stream's history (the server keeps it): up to the arm at its target?"""
            nonlocal entities, quats
            c = _client(info["grpc"], saved)
            wait_until(lambda: c.poll() is not None, 5)
            entities, quats = _received(c, saved)
            return bool(quats) and abs(2 * math.atan2(quats[-1][2], quats[-1][3]) - q1) < 0.02

        assert wait_until(turned, 120), f"the client's last shoulder transform {quats[-1:]}, the truth's joint {q1}"
        print(f"Rerun's client: {len(entities)} entities, {len(quats)} transforms of the first joint; its last "
              f"{2 * math.atan2(quats[-1][2], quats[-1][3]):.4f} rad, the truth {q1:.4f} rad")
        # the world and the robot's model came with it (the recorder's setup), to a late client too
        assert any(e.startswith("/world/") for e in entities), sorted(entities)[:20]
        assert any(e.startswith("/robot/") for e in entities), sorted(entities)[:20]
    finally:
        if obs is not None:
            obs.close()
        if client is not None:
            client.kill()
            client.wait(30)
        panel.close(timeout=120)
    assert not outside, outside  # nothing left this host
    # the stream stopped with the run: the viewer process is gone, its address file removed
    assert not (run / live.LIVE_NAME).exists()
    assert not _listening(grpc_port)
    log = (run / "logger.log").read_text()
    m = re.search(r"live viewer stopped: (\d+) frames \((\d+) bytes\) streamed, (\d+) dropped", log)
    assert m and int(m.group(1)) > 10, log

