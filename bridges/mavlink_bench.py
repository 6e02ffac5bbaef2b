"""``hilsim bench mavlink``: what the MAVLink bridge adds between a GPS message and its Zenoh
sample, against pymavlink alone, in the same run.

All on UDP loopback and a Zenoh router in this process:

- ``pymavlink``: the floor. A GPS_RAW_INT packed by pymavlink, sent from one UDP socket of this
  process to another and parsed there (pymavlink, MAVLink 2 common dialect): p50/p99 of send ->
  parsed (paced), and the messages per second that get through when sent flat out.
- ``bridge``: ``hilsim run bridge-mavlink`` as its own process (``config/hil/mavlink.yaml`` over
  the outdoor rover, listening on a port of its own), this process playing the GPS: a
  GPS_RAW_INT sent -> its ``gps/fix`` sample received here (the probe's number is in its
  latitude), p50/p99, paced at 200 Hz; then flat out: the samples per second that come out.

Send and receive times are taken by the same clock of the same process, so the bridge's figures
contain the baseline's path (one UDP hop, one pymavlink parse) plus a Zenoh hop, a CDR encode and
decode and the bridge's own Python: compare them with the ``pymavlink`` row.
"""

from __future__ import annotations

import argparse
import json
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from hilsim.bridges.bench_common import PACE, bridge_process, flat_out, pct, probes
from hilsim.core import msgs, transport
from hilsim.core.config import CONFIG_DIR, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario, write_scenario

LAT0, LON0 = 411778800, -85977900  # degE7: the outdoor world's datum


def _probe(k: int) -> Any:
    """A GPS_RAW_INT whose latitude carries the probe number ``k`` (1e-7 degree each)."""
    return mavlink.MAVLink_gps_raw_int_message(time.time_ns() // 1000, 3, LAT0 + k, LON0, 90_000, 100, 100, 0, 0, 12,
                                               alt_ellipsoid=90_000, h_acc=500, v_acc=800)


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


class _Sender:
    """pymavlink's encoder writing datagrams to one port."""

    def __init__(self, port: int) -> None:
        self.sock = _udp()
        self.dest = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(self, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_GPS)

    def write(self, buf: bytes) -> None:
        self.sock.sendto(buf, self.dest)

    def send(self, k: int) -> None:
        self.mav.send(_probe(k))


# ---------------------------------------------------------------------- pymavlink alone
def bench_pymavlink(n: int, seconds: float) -> dict[str, Any]:
    rx_sock = _udp()
    rx_sock.settimeout(0.05)
    tx = _Sender(rx_sock.getsockname()[1])
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    got: dict[int, float] = {}
    count = [0]
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            try:
                data = rx_sock.recv(4096)
            except TimeoutError:
                continue
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "GPS_RAW_INT":
                    got[m.lat - LAT0] = time.perf_counter()
                    count[0] += 1

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        sent = probes(tx.send, range(1, n + 1), time.perf_counter)
        time.sleep(0.2)
        lat = [got[k] - sent[k] for k in sent if k in got]
        count[0] = 0
        k = flat_out(lambda i: tx.send(i % 1000), seconds)
        time.sleep(0.3)
        mps = count[0] / seconds
    finally:
        stop.set()
        th.join(2)
        tx.sock.close()
        rx_sock.close()
    return {"latency": pct(lat), "lost": n - len(lat), "messages_per_s": round(mps), "sent_per_s": round(k / seconds)}


# ---------------------------------------------------------------------- the bridge
def bench_bridge(n: int, seconds: float, workdir: Path) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    with _udp() as s:
        port = s.getsockname()[1]
    sc = load_scenario(CONFIG_DIR / "rover-outdoor.yaml", {
        "zenoh.connect": [ep], "bridge-mavlink.connection": f"udpin:127.0.0.1:{port}",
        "bridge-mavlink.gps.jump_gate": 1e6, "bridge-mavlink.gps.timeout": 60.0,
        "bridge-mavlink.gps.startup_timeout": 60.0}, overlays=[CONFIG_DIR / "hil" / "mavlink.yaml"])
    cfg = workdir / "scenario.yaml"
    write_scenario(sc, cfg)
    keys = Keys.of(sc)
    session = transport.open_session(ZenohConfig(connect=[ep]))
    zen_rx: dict[int, float] = {}
    zcount = [0]

    def on_fix(sample: Any) -> None:
        t = time.perf_counter()
        m = msgs.decode(msgs.NavSatFix, sample.payload.to_bytes())
        zen_rx[round(m.latitude * 1e7) - LAT0] = t
        zcount[0] += 1

    sub = session.declare_subscriber(keys.topic("gps/fix"), on_fix)
    tx = _Sender(port)
    try:
        with bridge_process("bridge-mavlink", cfg, workdir, session, keys):
            deadline = time.monotonic() + 10
            while not zen_rx:  # the first fix: the bridge's publisher has reached our subscriber
                if time.monotonic() > deadline:
                    raise RuntimeError("no gps/fix from bridge-mavlink")
                tx.send(0)
                time.sleep(0.05)
            time.sleep(0.3)
            zen_rx.clear()
            sent = probes(tx.send, range(1, n + 1), time.perf_counter)
            time.sleep(0.3)
            lat = [zen_rx[k] - sent[k] for k in sent if k in zen_rx]
            zcount[0] = 0
            k = flat_out(lambda i: tx.send(i % 1000), seconds)
            time.sleep(0.5)
            sps = zcount[0] / seconds
    finally:
        tx.sock.close()
        sub.undeclare()
        session.close()
        router.close()
    return {"latency": pct(lat), "lost": n - len(lat), "samples_per_s": round(sps),
            "offered_per_s": round(k / seconds)}


def cmd_mavlink(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="hilsim-bench-mavlink-") as d:
        base = bench_pymavlink(args.samples, args.seconds)
        bridge = bench_bridge(args.samples, args.seconds, Path(d))
    res = {"link": "UDP loopback, MAVLink 2 GPS_RAW_INT", "samples": args.samples, "seconds": args.seconds,
           "pymavlink": base, "bridge": bridge,
           "added_p50_us": round(bridge["latency"]["p50_us"] - base["latency"]["p50_us"], 1),
           "added_p99_us": round(bridge["latency"]["p99_us"] - base["latency"]["p99_us"], 1)}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"hilsim bench mavlink ({res['link']}; {args.samples} paced probes at {1 / PACE:.0f} Hz, "
          f"{args.seconds:g} s flat out)")
    print(f"{'path':44s} {'p50 [µs]':>9s} {'p99 [µs]':>9s} {'lost':>5s} {'out [1/s]':>10s} {'offered [1/s]':>14s}")
    rows = [("pymavlink alone: UDP send -> parsed", base["latency"], base["lost"], base["messages_per_s"],
             base["sent_per_s"]),
            ("bridge: GPS_RAW_INT -> gps/fix on Zenoh", bridge["latency"], bridge["lost"], bridge["samples_per_s"],
             bridge["offered_per_s"])]
    for name, lat, lost, out, offered in rows:
        print(f"{name:44s} {lat['p50_us']:9.0f} {lat['p99_us']:9.0f} {lost:5d} {out:10d} {offered:14d}")
    print(f"added by the bridge over pymavlink alone: p50 {res['added_p50_us']:.0f} µs, "
          f"p99 {res['added_p99_us']:.0f} µs")
    return 0
