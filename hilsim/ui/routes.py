"""The panel's HTTP interface: the Starlette app, its routes and handlers, and how errors are answered.

HTTP (JSON; bad input is a 4xx with ``{"error", "field"}``, never a server error):
``GET /api/options``, ``GET /api/state``, ``GET /api/events`` (server-sent events: the state, 4 Hz;
:mod:`hilsim.ui.events`), ``POST /api/run``, ``POST /api/stop`` (:mod:`hilsim.ui.run_control`),
``POST /api/goal``, ``POST /api/cancel``, ``POST /api/gains`` (:mod:`hilsim.ui.commands`),
``POST /api/viewer`` (Rerun's bundled web viewer on the recording, served on loopback;
:mod:`hilsim.ui.viewer`), ``GET /recording.rrd`` (the current run's recording, every part of it), ``/`` and
``/static/…`` (the page).

No Zenoh keys of its own: the handlers call the panel (:mod:`hilsim.ui.panel`), whose parts read
and query them.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from hilsim.core.recording import recording_files
from hilsim.ui.events import event_endpoint
from hilsim.ui.jsonio import BadInput, finite
from hilsim.ui.panel import Panel

log = logging.getLogger("hilsim.ui")

STATIC = Path(__file__).resolve().parent / "static"
GAINS_SHOWN = ("kp", "ki", "kd", "i_limit")


async def _body(request: Request) -> dict[str, Any]:
    try:
        data = json.loads(await request.body() or b"{}")
    except ValueError:  # not JSON, not UTF-8, or a number too long to convert
        raise BadInput("request", "the request body is not JSON") from None
    if not isinstance(data, dict):
        raise BadInput("request", "the request body must be a JSON object")
    return data


def _concatenated(files: list[Path], chunk: int = 1 << 20) -> Iterator[bytes]:
    """The bytes of ``files``, one after the other (a part still being written: what it holds now)."""
    for f in files:
        with f.open("rb") as fh:
            while block := fh.read(chunk):
                yield block


def make_app(panel: Panel) -> Starlette:
    def bad(e: BadInput) -> JSONResponse:
        return JSONResponse({"error": str(e), "field": e.field}, status_code=e.status)

    def action(fn: Any, *, blocking: bool) -> Any:
        async def endpoint(request: Request) -> Response:
            try:
                body = await _body(request)
                if body.get("extra"):
                    raise BadInput("request", "extra: not accepted over HTTP")
                # queries wait for a service's answer: in a worker thread; a run is started from the
                # event loop's own (long-lived) thread, whose death alone should stop the run
                out = await run_in_threadpool(fn, body) if blocking else fn(body)
            except BadInput as e:
                return bad(e)
            return JSONResponse(finite(out))
        return endpoint

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def options(request: Request) -> Response:
        return JSONResponse({"scenarios": [o.as_json() for o in panel.options.values()],
                             "planners": panel.planners, "gain_fields": list(GAINS_SHOWN),
                             "endpoint": panel.endpoint})

    async def state(request: Request) -> Response:
        return JSONResponse(panel.state())

    async def stop(request: Request) -> Response:
        try:
            return JSONResponse(panel.control.stop())
        except BadInput as e:
            return bad(e)

    async def viewer(request: Request) -> Response:
        try:
            return JSONResponse(await run_in_threadpool(panel.open_viewer))
        except BadInput as e:
            return bad(e)

    async def live(request: Request) -> Response:
        from hilsim.ui.live_view import live_address

        return JSONResponse({"viewer": await run_in_threadpool(live_address, panel)})

    async def recording(request: Request) -> Response:
        rec = str(panel.run.info.get("recording") or "")
        if not rec or not Path(rec).is_file():
            return JSONResponse({"error": "no recording yet", "field": "recording"}, status_code=404)
        # every part of it (a recording split by size or duration, a restarted recorder's), one after the
        # other: Rerun reads RRD streams laid end to end as one recording, and the first part alone was
        # all this gave of a long run
        files = recording_files(rec)
        return StreamingResponse(_concatenated(files), media_type="application/octet-stream",
                                 headers={"Content-Disposition": 'attachment; filename="recording.rrd"'})

    async def not_found(request: Request, exc: Exception) -> Response:
        return JSONResponse({"error": f"no such page: {request.url.path}", "field": "request"}, status_code=404)

    async def not_allowed(request: Request, exc: Exception) -> Response:
        return JSONResponse({"error": f"{request.method} is not allowed on {request.url.path}", "field": "request"},
                            status_code=405)

    async def server_error(request: Request, exc: Exception) -> Response:
        log.exception("request %s %s failed", request.method, request.url.path)
        return JSONResponse({"error": f"internal error: {type(exc).__name__}: {exc}"[:300], "field": "request"},
                            status_code=500)

    routes = [
        Route("/", index),
        Route("/api/options", options),
        Route("/api/state", state),
        Route("/api/events", event_endpoint(panel)),
        Route("/api/run", action(panel.control.start, blocking=False), methods=["POST"]),
        Route("/api/stop", stop, methods=["POST"]),
        Route("/api/goal", action(panel.commands.goal, blocking=True), methods=["POST"]),
        Route("/api/cancel", action(panel.commands.cancel, blocking=True), methods=["POST"]),
        Route("/api/gains", action(panel.commands.gains, blocking=True), methods=["POST"]),
        Route("/api/viewer", viewer, methods=["POST"]),
        Route("/api/live", live),
        Route("/recording.rrd", recording),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes, exception_handlers={404: not_found, 405: not_allowed, 500: server_error})
