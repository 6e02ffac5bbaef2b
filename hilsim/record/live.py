"""Watch a run live: the recorder's Rerun stream, teed to Rerun's bundled web viewer while it runs.

``logger.live.enabled`` (``hilsim up … --view``) gives the recorder a second recording stream beside its
file's, with the same recording id, into a :class:`rerun.BinaryStream` (no second subscriber on any key):
the same rows, each entity's dense ones thinned (:mod:`hilsim.record.live_rows`: at most 30 a second of
sim time, a plot's 10; most health values left out; logs, paths and static data whole).
:class:`LiveStream` hands what that sink holds, after each of the
recorder's flushes, to a ``rerun --serve-web`` child reading it on its standard input: Rerun's own
gRPC server (which keeps the run's history, static data always, for a viewer that joins late, within
``SERVER_MEMORY_LIMIT``) and its bundled web viewer, both bound to loopback. In front of the web viewer
:class:`PageProxy` serves the page with a Content-Security-Policy that lets it reach nothing but this
host's two ports: the viewer's own update checks, fonts, example lists and usage analytics never leave
the browser (nothing reaches the network), and Rerun's analytics are off as everywhere in hilsim.

Bounded: each flush's bytes are one *frame* (a whole RRD stream of its own: header, messages,
footer). Frames wait in a queue of at most ``QUEUE_BYTES`` for a writer thread of their own that writes
them to the child's pipe (it may block; the recorder never does); a frame that finds the queue full
pushes out the oldest ones not yet begun, counted as
``live_dropped`` in the recorder's health (``live_frames``, ``live_bytes`` what went through). The frames
of the recorder's setup (the robot's model, the world's geometry, the layout) are never dropped. So a
slow or vanished viewer never slows the recorder, nor through it the loop. The child is stopped with the
recorder: the stream stops with the run.

On demand: until a viewer joins, the live stream gets the setup's static rows only, so a run nobody watches
pays for nothing but a rerun process waiting on its pipe. A viewer joins by loading the page (a browser, the
panel's frame) or by ``hilsim view --live`` (which asks the page server's ``/hilsim/watch`` first); from then
on the rows stream (health: ``live_watched``). A viewer that joins later still sees the run from that moment
on (the server keeps it). ``hilsim up --view`` with a task starts its physics only once a viewer joined and
one is connected to the server (:func:`hilsim.record.live_viewer.viewer_connected`; :mod:`hilsim.launch.up`),
so the whole task streams. ``logger.live.from_start`` streams from the start instead, watched or not.

The viewer's address is written to ``<run dir>/live.json`` (:func:`hilsim.record.live_viewer.read_live`),
where ``hilsim up --view`` prints it as ``viewer: URL`` and ``hilsim view --live`` finds it. Zenoh keys: none
(the recorder's stream only); files: ``<run dir>/live.json``, ``<run dir>/live-viewer.log``.
"""

from __future__ import annotations

import contextlib
import fcntl
import http.client
import http.server
import json
import logging
import os
import secrets
import signal
import subprocess
import threading
import time
import urllib.parse
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hilsim.core.threads import sigterm_when_parent_dies

LIVE_NAME = "live.json"
SERVER_NICE = 10  # the viewer's server's niceness (the simulation's is 0)
LOG_NAME = "live-viewer.log"
QUEUE_BYTES = 32 * 1024**2  # frames waiting for the viewer's pipe at most (a few seconds of the arm's rows)
SERVER_MEMORY_LIMIT = "512MiB"  # the run's history Rerun's server keeps for late viewers (static data always)
FLUSH_PERIOD_S = 0.2  # the recorder's flush period while live: how often the view moves on (0.5 s without)
START_TIMEOUT_S = 60.0  # for the viewer's ports to listen (once its first frame came; a loaded machine)
LOOPBACK = ("127.0.0.1", "localhost", "::1")
WATCH_PATH = "/hilsim/watch"  # the page server's: a viewer joins (the stream starts), nothing is served


class LiveError(RuntimeError):
    """The live viewer could not be started or found (one line)."""


def _reached_at(host: str) -> str:
    """The address a browser uses for ``host``: loopback as 127.0.0.1, all interfaces by this host's name."""
    import socket

    if host in LOOPBACK:
        return "127.0.0.1"
    return socket.gethostname() if host in ("0.0.0.0", "::") else host


def _free_port(host: str) -> int:
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _wait_listening(host: str, port: int, proc: subprocess.Popen[bytes], timeout: float) -> None:
    import socket

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise LiveError(f"the live viewer (rerun) exited with code {proc.returncode} at start")
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex((host, port)) == 0:
                return
        time.sleep(0.05)
    raise LiveError(f"the live viewer (rerun) did not listen on {host}:{port} within {timeout:g} s")


def csp(grpc_origin: str) -> str:
    """The page's Content-Security-Policy: scripts, styles, fonts and wasm from this page's origin only,
    data from the run's gRPC server only; any other address (fonts, update checks, analytics) is refused
    by the browser before a request is made."""
    return ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
            f"connect-src 'self' {grpc_origin}; worker-src 'self' blob:; frame-ancestors *")


class PageProxy:
    """Rerun's bundled web viewer (served by the child on loopback) behind a page server that adds
    :func:`csp`; on a host other than loopback it also asks for ``token`` (once, in the URL; then a
    cookie)."""

    def __init__(self, host: str, port: int, upstream: tuple[str, int], grpc_origin: str, token: str = "",
                 on_visit: Callable[[], None] = lambda: None) -> None:
        self.upstream, self.policy, self.token, self.on_visit = upstream, csp(grpc_origin), token, on_visit
        proxy = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_GET(self) -> None:  # http.server's name
                proxy.get(self)

            def log_message(self, *a: Any) -> None:  # quiet: the recorder's log is not a web server's
                pass

        self.server = http.server.ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self.port = int(self.server.server_address[1])
        self.thread = threading.Thread(target=self.server.serve_forever, name="live-page", daemon=True)
        self.thread.start()

    def get(self, h: http.server.BaseHTTPRequestHandler) -> None:
        url = urllib.parse.urlsplit(h.path)
        cookie = ""
        if self.token:
            given = urllib.parse.parse_qs(url.query).get("token", [""])[0]
            has = f"hilsim_live={self.token}" in (h.headers.get("Cookie") or "")
            if not (has or secrets.compare_digest(given, self.token)):
                h.send_error(403, "the viewer's token is missing or wrong")
                return
            cookie = f"hilsim_live={self.token}; Path=/; HttpOnly; SameSite=Strict"
        self.on_visit()  # a viewer is here: the rows stream from now on
        if url.path == WATCH_PATH:
            h.send_response(204)
            h.send_header("Content-Length", "0")
            h.end_headers()
            return
        conn = http.client.HTTPConnection(*self.upstream, timeout=30)
        try:
            conn.request("GET", url.path or "/", headers={"Accept-Encoding": h.headers.get("Accept-Encoding", "")})
            r = conn.getresponse()
            body = r.read()
        except OSError as e:
            h.send_error(502, f"the live viewer is gone: {e}")
            return
        finally:
            conn.close()
        h.send_response(r.status)
        for k, v in r.getheaders():
            if k.lower() not in ("content-length", "connection", "transfer-encoding", "content-security-policy"):
                h.send_header(k, v)
        h.send_header("Content-Length", str(len(body)))
        h.send_header("Content-Security-Policy", self.policy)
        h.send_header("Cache-Control", "no-store")
        if cookie:
            h.send_header("Set-Cookie", cookie)
        h.end_headers()
        with contextlib.suppress(OSError):  # a browser that left
            h.wfile.write(body)

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


class LiveStream:
    """The recorder's second sink and the viewer it feeds (see the module's docstring)."""

    def __init__(self, run_dir: Path, host: str = "127.0.0.1", port: int = 0,
                 warn: Callable[[str], None] | None = None, from_start: bool = False) -> None:
        self.run_dir, self.host = Path(run_dir), host
        self.from_start = from_start  # the rows stream from the start, watched or not
        self.watched = threading.Event()  # a viewer joined
        self.info: dict[str, Any] = {}  # what live.json says, once the viewer listens
        self.info_lock = threading.Lock()
        self.warn = warn or (lambda _text: None)
        self.rec: Any = None  # the live recording stream (rerun.RecordingStream), once attached
        self.sink: Any = None  # its rerun.BinaryStream
        self.tee: Any = None  # the file's stream and this one, as the recorder writes to them
        self.queue: deque[tuple[bytes, bool]] = deque()  # frames not yet written: (frame, essential)
        self.queued = 0  # bytes in the queue
        self.frames = self.bytes = self.dropped = self.dropped_bytes = 0
        self.stopped = ""  # why the stream stopped early ("" while it runs)
        self.closed = False
        self.lock = threading.Lock()
        self.ready = threading.Condition(self.lock)  # a frame queued, or closed
        bind = "127.0.0.1" if host in LOOPBACK else host
        self.grpc_port = _free_port(bind)
        web = _free_port(bind)
        from hilsim.core.recording import rerun_env, rerun_executable

        env = {**os.environ, **rerun_env(), "RERUN_ANALYTICS": "0"}
        self.log_path = self.run_dir / LOG_NAME
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [rerun_executable(), "--serve-web", "--bind", bind,
                 "--port", str(self.grpc_port), "--web-viewer-port", str(web),
                 "--server-memory-limit", SERVER_MEMORY_LIMIT, "-"],
                stdin=subprocess.PIPE, stdout=log, stderr=log, env=env, preexec_fn=_child_setup)
        assert self.proc.stdin is not None
        self.fd = self.proc.stdin.fileno()
        with contextlib.suppress(OSError):  # a larger pipe: fewer wake-ups of the writer
            fcntl.fcntl(self.fd, 1031, 1024**2)  # F_SETPIPE_SZ
        self.writer = threading.Thread(target=self._write, name="live-writer", daemon=True)
        self.writer.start()
        self.page: PageProxy | None = None
        seen = _reached_at(host)  # the address the browser reaches
        self.grpc_url = f"rerun+http://{seen}:{self.grpc_port}/proxy"
        self.url = ""
        # rerun listens once the first bytes reached its standard input (the setup's frame): announced then
        threading.Thread(target=self._announce, args=(bind, web, seen, port), name="live-announce",
                         daemon=True).start()

    def _announce(self, bind: str, web: int, seen: str, port: int) -> None:
        """Once the viewer's ports listen: the page server in front of it, and ``live.json``."""
        try:
            _wait_listening(bind, self.grpc_port, self.proc, START_TIMEOUT_S)
            _wait_listening(bind, web, self.proc, START_TIMEOUT_S)
            token = "" if self.host in LOOPBACK else secrets.token_urlsafe(18)
            page = PageProxy(bind, port, (bind, web), f"http://{seen}:{self.grpc_port}", token, self._joined)
        except (LiveError, OSError) as e:
            with self.lock:
                self._stop_early(f"no live viewer: {e}")
            return
        with self.lock:
            if self.closed:
                page.close()
                return
            self.page = page
        q = urllib.parse.urlencode({"url": self.grpc_url, **({"token": token} if token else {})})
        self.url = f"http://{seen}:{page.port}/?{q}"
        watch = f"http://{seen}:{page.port}{WATCH_PATH}" + (f"?{urllib.parse.urlencode({'token': token})}"
                                                             if token else "")
        # server: the process a viewer connects to (hilsim up waits for a connection: viewer_connected)
        self.info = {"viewer": self.url, "grpc": self.grpc_url, "watch": watch, "pid": os.getpid(),
                     "server": self.proc.pid}
        self._write_info()

    def _write_info(self) -> None:
        """``live.json``: the addresses, and whether a viewer joined (``hilsim up`` waits for it with
        ``logger.live.wait``)."""
        with self.info_lock:
            if not self.info or self.closed:
                return
            tmp = self.run_dir / (LIVE_NAME + ".tmp")
            tmp.write_text(json.dumps({**self.info, "watched": self.watched.is_set()}) + "\n")
            tmp.replace(self.run_dir / LIVE_NAME)

    # ------------------------------------------------------------------ the recorder's side
    def attach(self, rec: Any, blueprint: Any) -> Any:
        """The live recording stream beside the file's ``rec`` (its recording id, the layout made active: a
        default blueprint alone is not applied by a viewer that receives the stream live); returns the
        :class:`~hilsim.record.live_rows.LiveTee` the recorder writes its rows to."""
        import rerun as rr

        from hilsim.record.live_rows import LiveTee

        self.rec = rr.RecordingStream("hilsim", recording_id=rec.get_recording_id(), send_properties=True)
        self.sink = self.rec.binary_stream()
        rr.send_blueprint(blueprint, make_active=True, make_default=True, recording=self.rec)
        self.tee = LiveTee(rec, self.rec, active=self.streaming)
        return self.tee

    def streaming(self) -> bool:
        """Whether the rows stream: from the start, or since a viewer joined."""
        return self.from_start or self.watched.is_set()

    def _joined(self) -> None:
        """A viewer came (the page, or ``hilsim view --live``): the rows stream from now on."""
        if not self.watched.is_set():
            self.watched.set()
            logging.getLogger(__name__).info("a viewer joined: the run streams live from now on")
            self._write_info()

    def pump(self, essential: bool = False) -> None:
        """After the recorder flushed: what the sink holds, as one frame, to the writer's queue; never
        waits. ``essential``: the setup's frame, never dropped."""
        if self.stopped or self.sink is None:
            return
        if self.rec is not None:
            self.rec.flush()  # the live stream's own batcher (in memory: quick)
        frame = self.sink.read(flush=False)
        if not frame:
            return
        with self.ready:
            self.queue.append((frame, essential))
            self.queued += len(frame)
            while self.queued > QUEUE_BYTES:  # the oldest frames not begun and not the setup's go
                i = next((i for i, (_, keep) in enumerate(self.queue) if not keep), None)
                if i is None or i == len(self.queue) - 1:
                    break
                dropped = self.queue[i][0]
                del self.queue[i]
                self.queued -= len(dropped)
                self.dropped += 1
                self.dropped_bytes += len(dropped)
            self.ready.notify()

    def _write(self) -> None:
        """The writer thread: frames to the viewer's pipe, one whole frame at a time (blocking here,
        never the recorder)."""
        while True:
            with self.ready:
                while not self.queue and not self.closed:
                    self.ready.wait()
                if not self.queue:
                    return
                frame, _ = self.queue.popleft()
                self.queued -= len(frame)
            view = memoryview(frame)
            try:
                while view:
                    view = view[os.write(self.fd, view):]
            except OSError as e:  # the viewer process is gone: the recording goes on without it
                with self.ready:
                    self._stop_early(f"the live viewer stopped reading ({e})")
                return
            with self.ready:
                self.frames += 1
                self.bytes += len(frame)

    def _stop_early(self, why: str) -> None:
        self.stopped = why
        self.dropped += len(self.queue)
        self.queue.clear()
        self.queued = 0
        self.warn(f"{why}; the recording goes on")

    def health(self) -> dict[str, Any]:
        """The stream's counts, for the recorder's health."""
        with self.lock:
            thin = {"live_rows": self.tee.sent, "live_rows_thinned": self.tee.thinned} if self.tee else {}
            return {**thin, "live_watched": int(self.watched.is_set()), "live_frames": self.frames,
                    "live_bytes": self.bytes, "live_queued": self.queued,
                    "live_dropped": self.dropped, "live_dropped_bytes": self.dropped_bytes,
                    **({"live_stopped": self.stopped} if self.stopped else {})}

    def close(self, linger: float = 2.0) -> None:
        """The run ended: write what is queued (at most ``linger`` seconds), then stop the viewer."""
        if self.closed:
            return
        self.closed = True
        with self.ready:
            self.ready.notify()
        self.writer.join(linger)  # what is queued, for at most `linger` seconds
        with self.lock:
            page, self.page = self.page, None
        if page is not None:
            page.close()
        self._kill()
        with self.info_lock, contextlib.suppress(OSError):  # not written again after (closed)
            (self.run_dir / LIVE_NAME).unlink()

    def _kill(self) -> None:
        p = self.proc
        if p.stdin is not None:
            with contextlib.suppress(OSError):
                p.stdin.close()
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _child_setup() -> None:
    """The viewer's server process: below the simulation's processes in the scheduler's eyes (niced, not idle: it
    must keep reading the recorder's frames, else they are dropped), gone with the recorder."""
    with contextlib.suppress(OSError):
        os.nice(SERVER_NICE)
    sigterm_when_parent_dies()


# ---------------------------------------------------------------------- the recorder's hooks (services/logger.py)
def start(cfg: Any, run_dir: Path, warn: Callable[[str], None]) -> LiveStream | None:
    """The live stream of ``logger.live`` (:class:`hilsim.core.config.LiveConfig`), None when it is off or
    cannot start (said once; the recording goes on without it)."""
    if not cfg.enabled:
        return None
    try:
        return LiveStream(run_dir, cfg.host, cfg.port, warn, cfg.from_start)
    except (LiveError, OSError) as e:
        warn(f"no live viewer: {e}; the recording goes on")
        return None


def attach(stream: LiveStream | None, rec: Any, rrd_path: Path, blueprint: Any) -> Any:
    """The recording's file sink; with a live stream, its own recording stream beside it. Returns what the
    recorder writes its rows to: ``rec``, or the tee of both (hilsim.record.live_rows)."""
    rec.save(rrd_path, default_blueprint=blueprint)
    return rec if stream is None else stream.attach(rec, blueprint)


def setup_done(stream: LiveStream | None) -> None:
    """The recorder's static rows (the model, the world, the layout) logged: sent as frames never dropped."""
    if stream is not None:
        stream.pump(essential=True)


def stop(stream: LiveStream | None) -> None:
    """The recording ended: so does the live stream (idempotent)."""
    if stream is not None and not stream.closed:
        with contextlib.suppress(Exception):  # the recording is closed: what its sink still holds
            stream.pump()
        stream.close()
        h = stream.health()
        logging.getLogger(__name__).info(
            "live viewer stopped: %d frames (%d bytes) streamed, %d dropped (%d bytes)%s", h["live_frames"],
            h["live_bytes"], h["live_dropped"], h["live_dropped_bytes"],
            f"; {stream.stopped}" if stream.stopped else "")
