"""``hilsim bench loop --live N``: what watching a run live costs (docs/recording.md, "Watch it live").

The pipelined arm through the run's own router, as ``hilsim up`` runs it, without ``--view`` and with it in
its modes (nobody watching, streaming from the start, Rerun's viewer joined), and with Foxglove's server alone
and with a client, in turns (:func:`bench_live`). Zenoh keys: none of its own (the run's services').
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

from hilsim.tools.bench.runs import arm_scenario, run_arm


def bench_live(sim_seconds: float, tmp: Path, repeat: int, say: Any) -> dict[str, Any]:
    """What watching it live costs (docs/recording.md, "Watch it live"): the pipelined arm through the run's
    own router, as ``hilsim up`` runs it, without ``--view`` (off), with it and nobody watching (on: nothing
    streams until a viewer joins), the same streaming from the start (``logger.live.from_start``: what a viewer
    joining late would see, sent to Rerun's server whether or not anyone watches), and with Rerun's native
    viewer joined (watched: ``rerun --headless --connect``, ingesting and rendering on this machine's cores as
    a viewer on the same host does), in turns ``repeat`` times in one sitting (a shared machine's load
    drifts): each round's ratios against off, and their medians. Where the ``websockets`` package is (the
    test extra) also Foxglove's server (``--foxglove``) with nobody connected (*foxglove*) and with a client
    subscribed to every channel it advertises (*foxglove watched*)."""
    import threading

    from hilsim.record.foxglove_live import read_info
    from hilsim.record.live_viewer import HeadlessViewer, join, wait_live

    rtf: dict[str, list[float]] = {"off": [], "on": [], "from_start": [], "watched": []}
    taken: list[int] = []  # messages the Foxglove client took in, per round
    try:
        import websockets.sync.client  # noqa: F401  (a client to the protocol's spec, not hilsim's)

        rtf.update({"foxglove": [], "foxglove_watched": []})
    except ImportError:
        say("    (no websockets package: Foxglove's server not measured; pip install -e '.[test]')")
    for i in range(repeat):
        for mode in rtf:
            viewers: list[HeadlessViewer] = []
            stop = threading.Event()
            got = [0]

            def attach(la: Any, mode: str = mode, viewers: list[Any] = viewers, stop: threading.Event = stop,
                       got: list[int] = got) -> None:
                if mode == "foxglove_watched":
                    info = read_info(la.run_dir)
                    if info is None:
                        raise RuntimeError(f"no Foxglove server; see {la.run_dir}")
                    threading.Thread(target=_foxglove_client, args=(info["url"], stop, got), daemon=True).start()
                if mode != "watched":
                    return
                info = wait_live(la.run_dir, 120)
                if info is None:
                    raise RuntimeError(f"no live viewer; see {la.run_dir}")
                join(info)  # as `hilsim view --live` does before it connects
                viewers.append(HeadlessViewer(info, la.run_dir / "headless-viewer.log"))

            fox = mode.startswith("foxglove")
            sc = arm_scenario(sim_seconds, **{"clock.controller_lag": 1,
                                           "logger.live.enabled": mode in ("on", "from_start", "watched"),
                                           "logger.live.from_start": mode == "from_start",
                                           "logger.foxglove.enabled": fox, "logger.foxglove.port": 0})
            try:
                o = run_arm(sc, tmp / f"live-{mode}-{i}", run_router=True, after_ready=attach)
            finally:
                stop.set()
                died = [f for f in (v.failure() for v in viewers) if f]
                for v in viewers:
                    v.stop()
            if died:  # a viewer that died took nothing in: the round measured no viewer
                raise RuntimeError(f"round {i + 1}, {mode}: {died[0]}")
            rtf[mode].append(float(o.health["physics"]["real_time_factor"]))
            if mode == "foxglove_watched":
                taken.append(got[0])
        say(f"    round {i + 1}: " + ", ".join(f"{m.replace('_', ' ')} {v[-1]:.2f}x" for m, v in rtf.items())
            + (f" (the Foxglove client took in {taken[-1]} messages)" if taken else ""))
    out: dict[str, Any] = {"rtf": rtf, "foxglove_messages": taken}
    for mode in (m for m in rtf if m != "off"):
        out[f"ratio_{mode}"] = r = [a / b for a, b in zip(rtf[mode], rtf["off"], strict=True)]
        out[f"median_ratio_{mode}"] = statistics.median(r)
    return out


def _foxglove_client(url: str, stop: Any, got: list[int]) -> None:
    """A Foxglove WebSocket client (the ``websockets`` package, to the protocol's spec) subscribed to every
    channel the server advertises, taking in every message until ``stop`` (counted in ``got[0]``)."""
    import websockets.sync.client as ws_client

    with ws_client.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],  # type: ignore[list-item]
                           max_size=None, open_timeout=60) as ws:
        while not stop.is_set():
            try:
                msg = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:  # the run ended: the server went
                return
            if not isinstance(msg, str):
                got[0] += 1
            else:
                j = json.loads(msg)
                if j.get("op") == "advertise":
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in j["channels"]]}))
