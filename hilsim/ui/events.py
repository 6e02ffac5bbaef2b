"""The event stream: the panel's state pushed to the browser as server-sent events
(``GET /api/events``), one ``data:`` line of JSON every :data:`EVENT_PERIOD`, until the page goes
away or the panel closes.

No Zenoh keys of its own: the state sent is :meth:`hilsim.ui.panel.Panel.state`, what the watcher
(:mod:`hilsim.ui.watch`) keeps and the run's status.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable

from starlette.requests import Request
from starlette.responses import Response, StreamingResponse

from hilsim.ui.panel import Panel

EVENT_PERIOD = 0.25  # wall seconds between two server-sent states


def event_endpoint(panel: Panel) -> Callable[[Request], Awaitable[Response]]:
    """The ``GET /api/events`` handler: the state, 4 Hz, as ``text/event-stream``."""

    async def events(request: Request) -> Response:
        async def stream() -> AsyncIterator[str]:
            while not panel.closing.is_set():
                yield f"data: {json.dumps(panel.state())}\n\n"
                await asyncio.sleep(EVENT_PERIOD)
                if await request.is_disconnected():
                    break
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    return events
