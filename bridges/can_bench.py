"""``hilsim bench can``: what the CAN bridge costs, against python-can alone, in the same run.

All on python-can's ``udp_multicast`` bus (a port of its own) and a Zenoh router in this process:

- ``python_can``: the floor. Two bus objects of this process; one frame's way from ``send`` to
  ``recv`` (p50/p99, paced), and the frames per second that get through when sent flat out.
- ``bridge``: ``hilsim run bridge-can`` as its own process serving joint_1 (node 0), this process
  playing the ODrive (heartbeats, closed loop on request). Latency *command on Zenoh -> frame on
  the bus* (a ``joint_commands`` sample put here -> its Set_Input_Pos received here) and *frame on
  the bus -> sample on Zenoh* (an encoder estimate sent here -> its ``hw/bridge-can/joint_states``
  sample received here), p50/p99, paced at 200 Hz; then each direction flat out: the frames (or
  samples) per second that come out of the bridge.

The send and receive times are taken by the same clock of the same process, so the figures include
python-can's own path twice (out and back in): compare them with the ``python_can`` row.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from hilsim import msgs, transport
from hilsim.bridges.can_bus import UDP_GROUP_IPV6
from hilsim.bridges.can_profiles import DriveCommand, Estimate, FrameError, Heartbeat, make_profile
from hilsim.config import CONFIG_DIR, ZenohConfig, load_scenario, write_scenario
from hilsim.keys import Keys

PACE = 0.005  # s between latency probes (200 Hz)
STEP = 1e-4  # rad per probe number in joint_commands


def _pct(xs: list[float]) -> dict[str, float]:
    if not xs:
        return {"n": 0, "p50_us": float("nan"), "p99_us": float("nan")}
    a = np.asarray(xs) * 1e6
    return {"n": len(xs), "p50_us": round(float(np.percentile(a, 50)), 1),
            "p99_us": round(float(np.percentile(a, 99)), 1)}


def _bus(port: int) -> can.BusABC:
    return can.Bus(interface="udp_multicast", channel=UDP_GROUP_IPV6, port=port)


# ---------------------------------------------------------------------- python-can alone
def bench_python_can(port: int, n: int, seconds: float) -> dict[str, Any]:
    tx, rx = _bus(port), _bus(port)
    got: dict[int, float] = {}
    count = [0]
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            m = rx.recv(0.05)
            if m is not None and m.arbitration_id == 0x123:
                got[int.from_bytes(m.data[:4], "little")] = time.perf_counter()
                count[0] += 1

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        sent: dict[int, float] = {}
        for k in range(n):
            sent[k] = time.perf_counter()
            tx.send(can.Message(arbitration_id=0x123, data=k.to_bytes(4, "little") + bytes(4), is_extended_id=False))
            time.sleep(PACE)
        time.sleep(0.2)
        lat = [got[k] - sent[k] for k in sent if k in got]
        count[0] = 0
        t0 = time.perf_counter()
        k = n
        while time.perf_counter() - t0 < seconds:
            k += 1
            tx.send(can.Message(arbitration_id=0x123, data=k.to_bytes(4, "little") + bytes(4), is_extended_id=False))
        sent_n = k - n
        time.sleep(0.3)
        fps = count[0] / seconds
    finally:
        stop.set()
        th.join(2)
        tx.shutdown()
        rx.shutdown()
    return {"latency": _pct(lat), "lost": n - len(lat), "frames_per_s": round(fps),
            "sent_per_s": round(sent_n / seconds)}


# ---------------------------------------------------------------------- the bridge
class FakeDrive:
    """This process as ODrive node 0: heartbeats, closed loop on request, and probes' receipt times."""

    def __init__(self, port: int) -> None:
        self.bus = _bus(port)
        self.p = make_profile("odrive")
        self.state = self.p.IDLE
        self.stop = threading.Event()
        self.cmd_rx: dict[int, float] = {}
        self.setpoints = 0
        self.threads = [threading.Thread(target=self._rx, daemon=True), threading.Thread(target=self._hb, daemon=True)]
        for t in self.threads:
            t.start()

    def _rx(self) -> None:
        while not self.stop.is_set():
            m = self.bus.recv(0.05)
            if m is None or self.p.direction(m) != "to_drive":
                continue
            t = time.perf_counter()
            try:
                ev = self.p.parse(m)
            except FrameError:
                continue
            if not isinstance(ev, DriveCommand) or ev.node != 0:
                continue
            if ev.kind == "state":
                self.state = int(ev.a)
            elif ev.kind == "position":
                self.setpoints += 1
                self.cmd_rx[round(ev.a / STEP)] = t

    def _hb(self) -> None:
        while not self.stop.wait(0.1):
            self.bus.send(self.p.heartbeat_frame(Heartbeat(0, 0, self.state)))

    def estimate(self, k: int) -> None:
        self.bus.send(self.p.estimate_frame(Estimate(0, k * STEP, 0.0)))

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2)
        self.bus.shutdown()


def bench_bridge(port: int, n: int, seconds: float, workdir: Path) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    sc = load_scenario("arm", {
        "zenoh.connect": [ep], "bridge-can.bus.port": port, "bridge-can.heartbeat_misses": 50,
        "bridge-can.rejoin_velocity": 1000.0}, overlays=[CONFIG_DIR / "hil" / "can.yaml"])
    cfg = workdir / "scenario.yaml"
    write_scenario(sc, cfg)
    keys = Keys(sc.prefix, sc.robot)
    session = transport.open_session(ZenohConfig(connect=[ep]))
    drive = FakeDrive(port)
    zen_rx: dict[int, float] = {}
    zcount = [0]

    def on_state(sample: Any) -> None:
        t = time.perf_counter()
        m = msgs.decode(msgs.JointState, sample.payload.to_bytes())
        zen_rx[round(m.position[0] / STEP)] = t
        zcount[0] += 1

    sub = session.declare_subscriber(keys.server_state("bridge-can"), on_state)
    pub = session.declare_publisher(keys.topic("joint_commands"))
    log = open(workdir / "bridge-can.log", "wb")  # closed in the finally below
    proc = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "run", "bridge-can", "--config", str(cfg)],
                            stdout=log, stderr=log, start_new_session=True)
    try:
        alive = threading.Event()
        tok = session.liveliness().declare_subscriber(keys.alive("bridge-can"), lambda s: alive.set(), history=True)
        if not alive.wait(60):
            raise RuntimeError(f"bridge-can did not start (log: {workdir / 'bridge-can.log'})")
        tok.undeclare()
        deadline = time.monotonic() + 10
        while drive.state != drive.p.CLOSED_LOOP:
            if time.monotonic() > deadline:
                raise RuntimeError("bridge-can did not put the drive into closed loop")
            time.sleep(0.01)
        time.sleep(0.3)

        def command(k: int) -> None:
            pub.put(msgs.encode(msgs.JointState(header=msgs.header(0), name=["joint_1"], position=[k * STEP],
                                                velocity=[0.0], effort=[0.0])))

        # latency, command on Zenoh -> frame on the bus
        sent: dict[int, float] = {}
        for k in range(1, n + 1):
            sent[k] = time.perf_counter()
            command(k)
            time.sleep(PACE)
        time.sleep(0.3)
        out_lat = [drive.cmd_rx[k] - sent[k] for k in sent if k in drive.cmd_rx]
        # latency, frame on the bus -> sample on Zenoh
        sent = {}
        for k in range(1, n + 1):
            sent[k] = time.perf_counter()
            drive.estimate(k)
            time.sleep(PACE)
        time.sleep(0.3)
        in_lat = [zen_rx[k] - sent[k] for k in sent if k in zen_rx]
        # flat out, Zenoh -> CAN
        before = drive.setpoints
        t0 = time.perf_counter()
        k = 0
        while time.perf_counter() - t0 < seconds:
            k += 1
            command(k % 1000)
        cmd_sent = k
        time.sleep(0.5)
        out_fps = (drive.setpoints - before) / seconds
        # flat out, CAN -> Zenoh
        zcount[0] = 0
        t0 = time.perf_counter()
        k = 0
        while time.perf_counter() - t0 < seconds:
            k += 1
            drive.estimate(k % 1000)
        est_sent = k
        time.sleep(0.5)
        in_fps = zcount[0] / seconds
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()
        drive.close()
        sub.undeclare()
        pub.undeclare()
        session.close()
        router.close()
    return {
        "zenoh_to_can": {"latency": _pct(out_lat), "lost": n - len(out_lat), "frames_per_s": round(out_fps),
                         "offered_per_s": round(cmd_sent / seconds)},
        "can_to_zenoh": {"latency": _pct(in_lat), "lost": n - len(in_lat), "samples_per_s": round(in_fps),
                         "offered_per_s": round(est_sent / seconds)},
    }


def cmd_can(args: argparse.Namespace) -> int:
    port = args.port or random.SystemRandom().randint(20000, 60000)
    with tempfile.TemporaryDirectory(prefix="hilsim-bench-can-") as d:
        base = bench_python_can(port, args.samples, args.seconds)
        bridge = bench_bridge(port, args.samples, args.seconds, Path(d))
    res = {"bus": f"udp_multicast {UDP_GROUP_IPV6} port {port}", "samples": args.samples, "seconds": args.seconds,
           "python_can": base, **bridge}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    b, o, i = base, bridge["zenoh_to_can"], bridge["can_to_zenoh"]
    print(f"hilsim bench can ({res['bus']}; {args.samples} paced probes at {1 / PACE:.0f} Hz, "
          f"{args.seconds:g} s flat out per direction)")
    print(f"{'path':34s} {'p50 [µs]':>9s} {'p99 [µs]':>9s} {'lost':>5s} {'out [1/s]':>10s} {'offered [1/s]':>14s}")
    rows = [("python-can alone: send -> recv", b["latency"], b["lost"], b["frames_per_s"], b["sent_per_s"]),
            ("bridge: Zenoh command -> CAN frame", o["latency"], o["lost"], o["frames_per_s"], o["offered_per_s"]),
            ("bridge: CAN frame -> Zenoh sample", i["latency"], i["lost"], i["samples_per_s"], i["offered_per_s"])]
    for name, lat, lost, fps, offered in rows:
        print(f"{name:34s} {lat['p50_us']:9.0f} {lat['p99_us']:9.0f} {lost:5d} {fps:10d} {offered:14d}")
    added = [(o["latency"]["p50_us"] - b["latency"]["p50_us"]), (i["latency"]["p50_us"] - b["latency"]["p50_us"])]
    print(f"added by the bridge over python-can alone (p50): command {added[0]:.0f} µs, state {added[1]:.0f} µs")
    return 0
