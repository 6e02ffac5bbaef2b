"""The panel's ``GET /recording.rrd`` gives the whole recording of the run it shows: every part of a recording
split by size (``recording.part-<k>.rrd``) after the first, one after the other, which Rerun's own reader
(the ``rerun`` CLI, not written here) reads as one recording. Before, the first file alone was served.
Called through the panel's ASGI app, without a server or a run."""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import rerun as rr

from hilsim.core.recording import split_name
from hilsim.ui.routes import make_app


def _get(app: Any, path: str) -> tuple[int, dict[str, str], bytes]:
    """One GET through the ASGI app: status, headers, body."""
    out: dict[str, Any] = {"body": b"", "asked": 0}

    async def run() -> None:
        done = asyncio.Event()  # the whole response sent: the client then goes

        async def receive() -> dict[str, Any]:
            out["asked"] += 1
            if out["asked"] == 1:
                return {"type": "http.request", "body": b"", "more_body": False}
            await done.wait()
            return {"type": "http.disconnect"}

        async def send(message: dict[str, Any]) -> None:
            if message["type"] == "http.response.start":
                out["status"] = message["status"]
                out["headers"] = {k.decode(): v.decode() for k, v in message["headers"]}
            elif message["type"] == "http.response.body":
                out["body"] += message.get("body", b"")
                if not message.get("more_body"):
                    done.set()

        scope = {"type": "http", "method": "GET", "path": path, "raw_path": path.encode(), "query_string": b"",
                 "headers": [], "scheme": "http", "server": ("127.0.0.1", 8080), "client": ("127.0.0.1", 5000),
                 "root_path": "", "http_version": "1.1"}
        await asyncio.wait_for(app(scope, receive, send), 30)

    asyncio.run(run())
    return out["status"], out["headers"], out["body"]


def _part(path: Path, rec: rr.RecordingStream, sink: Any, values: list[float]) -> None:
    for i, v in enumerate(values):
        rec.set_time("step", sequence=i)
        rec.log("joint/position", rr.Scalars(v))
    rec.flush()
    path.write_bytes(sink.read(flush=False))


def _chunks(rerun: str, path: Path) -> int:
    p = subprocess.run([rerun, "rrd", "print", str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    return sum(line.startswith("Chunk(") for line in p.stdout.splitlines())


def test_the_recording_is_served_whole_with_every_part(tmp_path: Path) -> None:
    from hilsim.core.recording import rerun_executable

    first = tmp_path / "recording.rrd"
    rec = rr.RecordingStream("hilsim-test")
    sink = rec.binary_stream()  # each read a whole RRD stream: as a file the recorder closed and the next
    _part(first, rec, sink, [0.1, 0.2])
    _part(split_name(first, 1), rec, sink, [0.3])
    _part(split_name(first, 2), rec, sink, [0.4, 0.5, 0.6])
    panel = SimpleNamespace(run=SimpleNamespace(info={"recording": str(first)}),
                            control=SimpleNamespace(start=None), commands=SimpleNamespace(goal=None, cancel=None,
                                                                                          gains=None))
    status, headers, body = _get(make_app(panel), "/recording.rrd")  # type: ignore[arg-type]
    assert status == 200 and 'filename="recording.rrd"' in headers.get("content-disposition", ""), headers
    parts = [first, split_name(first, 1), split_name(first, 2)]
    assert body == b"".join(p.read_bytes() for p in parts)
    got = tmp_path / "got.rrd"
    got.write_bytes(body)
    rerun = rerun_executable()
    assert _chunks(rerun, got) == sum(_chunks(rerun, p) for p in parts) >= 3


def test_no_recording_yet_is_a_404_naming_the_field(tmp_path: Path) -> None:
    panel = SimpleNamespace(run=SimpleNamespace(info={"recording": str(tmp_path / "recording.rrd")}),
                            control=SimpleNamespace(start=None), commands=SimpleNamespace(goal=None, cancel=None,
                                                                                          gains=None))
    status, _, body = _get(make_app(panel), "/recording.rrd")  # type: ignore[arg-type]
    assert status == 404 and b'"field":"recording"' in body.replace(b" ", b""), body
