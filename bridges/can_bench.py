"""``hilsim bench can``: what the CAN bridge costs, against python-can alone, in the same run.

All on python-can's ``udp_multicast`` bus (a port of its own) and a Zenoh router in this process:

- ``python_can``: the floor. Two bus objects of this process; one frame's way from ``send`` to
  ``recv`` (p50/p99, paced), the same at a saturated 1 Mbit/s bus's rate (:data:`BUS_RATE`),
  and the frames per second that get through when sent flat out.
- ``bridge``: ``hilsim run bridge-can`` as its own process serving joint_1 (node 0), this process
  playing the ODrive (heartbeats, closed loop on request). Latency *command on Zenoh -> frame on
  the bus* (a ``joint_commands`` sample put here -> its Set_Input_Pos received here) and *frame on
  the bus -> sample on Zenoh* (an encoder estimate sent here -> its ``hw/bridge-can/joint_states``
  sample received here), p50/p99, paced at 200 Hz; then Zenoh -> CAN flat out (frames per
  second out of the bridge), and CAN -> Zenoh at :data:`BUS_RATE` and flat out.

CAN -> Zenoh under load: the bridge publishes once per batch of frames its reader drained
together, each joint's newest estimate (``batch_window``). Every estimate sent here carries its
own number (position = number × STEP), so each Zenoh sample says which frame it reflects. The
figures: *offered* (frames sent per second), *absorbed* (estimates the bridge took in, from its
health counters ``estimates`` / ``estimates_coalesced`` / ``state_samples``), *lost* (offered
and never absorbed), *published* (samples), *coalesced* (absorbed estimates a newer one replaced
before publication); whether the last sample reflects the last frame (the newest state wins);
and the latency of the *oldest* frame each sample absorbed (the frame after the one the previous
sample reflected: its send -> this sample's arrival), p50/p99, so coalescing hides no waiting.

``--realtime-priority N`` runs the bridge with ``bridge-can.realtime_priority`` N (SCHED_FIFO, as
docs/hil.md advises for a rig), and says whether it was granted.

The send and receive times are taken by the same clock of the same process, so the figures include
python-can's own path twice (out and back in): compare them with the ``python_can`` row.
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can

from hilsim.bridges.bench_common import PACE, bridge_process, flat_out, pct, probes
from hilsim.bridges.can_bus import BusConfig, resolve_bus
from hilsim.bridges.can_profiles import DriveCommand, Estimate, FrameError, Heartbeat, make_profile
from hilsim.core import msgs, transport
from hilsim.core.config import CONFIG_DIR, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario, write_scenario

STEP = 1e-4  # rad per probe number in joint_commands, and per frame number in encoder estimates
BUS_RATE = 7000.0  # frames/s of a saturated 1 Mbit/s bus (8-byte standard frames, ~140 bits each)


def _paced(send: Any, first: int, rate: float, seconds: float) -> list[float]:
    """Call ``send(k)`` for k = first, first + 1, … at ``rate`` per second for ``seconds``, each at
    its own time (not in bursts); the send times (wall clock, as the bridge's sample timestamps), in order."""
    times: list[float] = []
    t0 = time.perf_counter()
    n = int(rate * seconds)
    for i in range(n):
        due = t0 + i / rate
        while (d := due - time.perf_counter()) > 0:
            if d > 2e-4:
                time.sleep(d - 1.5e-4)  # sleep overshoots by ~60 µs; spin the rest
        times.append(time.time())
        send(first + i)
    return times


def _group() -> str:
    """python-can's default group, or its IPv4 one where the bridge takes it (no IPv6 multicast here)."""
    return resolve_bus(BusConfig(), logging.getLogger("hilsim.bench.can")).channel


def _bus(port: int) -> can.BusABC:
    return can.Bus(interface="udp_multicast", channel=_group(), port=port)


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
                got[int.from_bytes(m.data[:4], "little")] = time.time()
                count[0] += 1

    def send(k: int) -> None:
        tx.send(can.Message(arbitration_id=0x123, data=k.to_bytes(4, "little") + bytes(4), is_extended_id=False))

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        sent = probes(send, range(n), time.time)
        time.sleep(0.2)
        lat = [got[k] - sent[k] for k in sent if k in got]
        # at the bus's rate
        count[0] = 0
        first = n + 1
        times = _paced(send, first, BUS_RATE, seconds)
        time.sleep(0.3)
        rate_lat = [got[first + i] - t for i, t in enumerate(times) if first + i in got]
        at_rate = {"offered_per_s": round(len(times) / seconds), "received_per_s": round(count[0] / seconds),
                   "lost": len(times) - count[0], "latency": pct(rate_lat)}
        # flat out
        count[0] = 0
        first += len(times)
        sent_n = flat_out(send, seconds, first)
        time.sleep(0.3)
        fps = count[0] / seconds
    finally:
        stop.set()
        th.join(2)
        tx.shutdown()
        rx.shutdown()
    return {"latency": pct(lat), "lost": n - len(lat), "at_bus_rate": at_rate, "frames_per_s": round(fps),
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
            t = time.time()
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


def _absorbed(first: int, times: list[float], seen: list[tuple[int, float, float]], before: dict[str, str],
              after: dict[str, str], seconds: float, state_key: str) -> dict[str, Any]:
    """What became of the estimates numbered ``first``… sent at ``times``: the bridge's counters
    (``before``/``after`` the run) and the samples seen here ((frame number, arrival time, the
    bridge's put time)). Latency of the oldest frame a sample absorbed: the frame after the one
    the previous sample reflected (if that frame was lost on the way, an older one: the figure
    errs high), to the sample's put by the bridge and to its arrival here.
    A bridge without the ``estimates`` counter (before batching) published one sample per
    estimate: its count of ``state_key`` samples is its count of estimates."""
    last = first + len(times) - 1
    mine = [x for x in seen if first <= x[0] <= last]
    oldest: list[float] = []
    oldest_put: list[float] = []
    newest: list[float] = []
    backwards = 0
    prev = first - 1
    for k, t, put in mine:
        if k <= prev:
            backwards += 1  # a sample older than one already seen: the newest state did not win
            continue
        oldest.append(t - times[prev + 1 - first])
        oldest_put.append(put - times[prev + 1 - first])
        newest.append(t - times[k - first])
        prev = k

    def delta(key: str) -> int:
        if key not in after:
            key = f"published:{state_key}"
        return int(after.get(key, 0)) - int(before.get(key, 0))

    absorbed, published = delta("estimates"), delta("state_samples")
    return {
        "offered": len(times), "offered_per_s": round(len(times) / seconds),
        "absorbed": absorbed, "absorbed_per_s": round(absorbed / seconds), "lost": len(times) - absorbed,
        "published": published, "published_per_s": round(published / seconds),
        "coalesced": delta("estimates_coalesced") if "estimates_coalesced" in after else 0, "received": len(mine),
        "distinct_frames_seen": len({x[0] for x in mine}), "backwards": backwards,
        "last_sample_is_last_frame": bool(mine) and mine[-1][0] == last,
        "latency_oldest": pct(oldest), "latency_oldest_to_put": pct(oldest_put), "latency_newest": pct(newest),
    }


def bench_bridge(port: int, n: int, seconds: float, workdir: Path, priority: int = 0) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    sc = load_scenario("arm", {
        "zenoh.connect": [ep], "bridge-can.bus.port": port, "bridge-can.heartbeat_misses": 50,
        "bridge-can.rejoin_velocity": 1000.0,
        "bridge-can.realtime_priority": priority}, overlays=[CONFIG_DIR / "hil" / "can.yaml"])
    cfg = workdir / "scenario.yaml"
    write_scenario(sc, cfg)
    keys = Keys.of(sc)
    session = transport.open_session(ZenohConfig(connect=[ep]))
    drive = FakeDrive(port)
    zen_rx: dict[int, float] = {}
    # (estimate number, arrival here, put by the bridge) of every joint_states sample; wall clock
    seen: list[tuple[int, float, float]] = []
    health: list[tuple[float, dict[str, str]]] = [(0.0, {})]

    def put_time(sample: Any) -> float:
        att = transport.read_attachment(sample)
        return att.source_ns * 1e-9 if att is not None else float("nan")

    def on_state(sample: Any) -> None:
        t = time.time()
        m = msgs.decode(msgs.JointState, sample.payload.to_bytes())
        k = round(m.position[0] / STEP)
        zen_rx[k] = t
        seen.append((k, t, put_time(sample)))

    def on_health(sample: Any) -> None:
        h = msgs.decode(msgs.DiagnosticArray, sample.payload.to_bytes())
        health.append((put_time(sample), {kv.key: kv.value for kv in h.status[0].values}))

    def report_after(t: float) -> tuple[float, dict[str, str]]:
        """The bridge's first health report made after ``t`` (wall clock; it reports every second,
        judged by the report's own timestamp: a loaded machine may deliver it late)."""
        while True:
            made = [h for h in health if h[0] > t]
            if made:
                return made[0]
            if time.time() - t > 5:
                raise RuntimeError("bridge-can sent no health for 5 s")
            time.sleep(0.02)

    def counters() -> dict[str, str]:
        """The bridge's counters once it has taken in all it will: two reports in a row (a second
        apart) with the same number of estimates (a bridge behind on a loaded machine is still
        reading its socket's backlog)."""
        t, last = report_after(time.time())
        for _ in range(10):
            t, now = report_after(t)
            if now.get("estimates", now.get(state_key)) == last.get("estimates", last.get(state_key)):
                return now
            last = now
        return last

    state_key = f"published:{keys.server_state('bridge-can')}"
    sub = session.declare_subscriber(keys.server_state("bridge-can"), on_state)
    hsub = session.declare_subscriber(keys.health("bridge-can"), on_health)
    pub = session.declare_publisher(keys.topic("joint_commands"))
    try:
        with bridge_process("bridge-can", cfg, workdir, session, keys):
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
            sent = probes(command, range(1, n + 1), time.time)
            time.sleep(0.3)
            out_lat = [drive.cmd_rx[k] - sent[k] for k in sent if k in drive.cmd_rx]
            # latency, frame on the bus -> sample on Zenoh
            sent = probes(drive.estimate, range(1, n + 1), time.time)
            time.sleep(0.3)
            in_lat = [zen_rx[k] - sent[k] for k in sent if k in zen_rx]
            # flat out, Zenoh -> CAN
            before = drive.setpoints
            cmd_sent = flat_out(lambda i: command(i % 1000), seconds)
            time.sleep(0.5)
            out_fps = (drive.setpoints - before) / seconds
            # CAN -> Zenoh at the bus's rate, then flat out; every estimate numbered
            first = n + 1
            before = counters()
            times = _paced(drive.estimate, first, BUS_RATE, seconds)
            time.sleep(0.5)
            after = counters()
            at_rate = _absorbed(first, times, seen, before, after, seconds, keys.server_state("bridge-can"))
            first += len(times)
            times = []
            flat_out(drive.estimate, seconds, first, times)
            time.sleep(0.5)
            flat = _absorbed(first, times, seen, after, counters(), seconds, keys.server_state("bridge-can"))
    finally:
        # whether the scheduling class asked for was granted, as the bridge's own log says
        fifo = "running with SCHED_FIFO" in (workdir / "bridge-can.log").read_text(errors="replace")
        drive.close()
        sub.undeclare()
        hsub.undeclare()
        pub.undeclare()
        session.close()
        router.close()
    return {
        "bridge_sched_fifo": fifo,
        "zenoh_to_can": {"latency": pct(out_lat), "lost": n - len(out_lat), "frames_per_s": round(out_fps),
                         "offered_per_s": round(cmd_sent / seconds)},
        "can_to_zenoh": {"latency": pct(in_lat), "lost": n - len(in_lat), "at_bus_rate": at_rate,
                         "flat_out": flat, "samples_per_s": flat["published_per_s"],
                         "absorbed_per_s": flat["absorbed_per_s"], "offered_per_s": flat["offered_per_s"]},
    }


def cmd_can(args: argparse.Namespace) -> int:
    port = args.port or random.SystemRandom().randint(20000, 60000)
    with tempfile.TemporaryDirectory(prefix="hilsim-bench-can-") as d:
        base = bench_python_can(port, args.samples, args.seconds)
        bridge = bench_bridge(port, args.samples, args.seconds, Path(d), args.realtime_priority)
    res = {"bus": f"udp_multicast {_group()} port {port}", "samples": args.samples, "seconds": args.seconds,
           "python_can": base, **bridge}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    b, o, i = base, bridge["zenoh_to_can"], bridge["can_to_zenoh"]
    print(f"hilsim bench can ({res['bus']}; {args.samples} paced probes at {1 / PACE:.0f} Hz, "
          f"{args.seconds:g} s at {BUS_RATE:.0f} frames/s and flat out)")
    if args.realtime_priority:
        got = "granted" if bridge["bridge_sched_fifo"] else "NOT granted (see the bridge's warning)"
        print(f"bridge with SCHED_FIFO priority {args.realtime_priority}: {got}")
    print(f"{'path':34s} {'p50 [µs]':>9s} {'p99 [µs]':>9s} {'lost':>5s} {'out [1/s]':>10s} {'offered [1/s]':>14s}")
    rows = [("python-can alone: send -> recv", b["latency"], b["lost"], b["frames_per_s"], b["sent_per_s"]),
            ("bridge: Zenoh command -> CAN frame", o["latency"], o["lost"], o["frames_per_s"], o["offered_per_s"]),
            ("bridge: CAN frame -> Zenoh sample", i["latency"], i["lost"], i["absorbed_per_s"], i["offered_per_s"])]
    for name, lat, lost, fps, offered in rows:
        print(f"{name:34s} {lat['p50_us']:9.0f} {lat['p99_us']:9.0f} {lost:5d} {fps:10d} {offered:14d}")
    added = [(o["latency"]["p50_us"] - b["latency"]["p50_us"]), (i["latency"]["p50_us"] - b["latency"]["p50_us"])]
    print(f"added by the bridge over python-can alone (p50): command {added[0]:.0f} µs, state {added[1]:.0f} µs")
    r = b["at_bus_rate"]
    print(f"python-can alone at {BUS_RATE:.0f} frames/s: {r['received_per_s']} received/s of {r['offered_per_s']}, "
          f"lost {r['lost']}, latency p50 {r['latency']['p50_us']:.0f} µs p99 {r['latency']['p99_us']:.0f} µs")
    print("CAN -> Zenoh under load (absorbed: estimates the bridge took in; published: joint_states samples, "
          "each the newest estimate of its batch; latency: the oldest frame a sample absorbed -> the bridge's put, "
          "-> the sample here)")
    print(f"{'run':10s} {'offered/s':>9s} {'absorbed/s':>10s} {'lost':>6s} {'published/s':>11s} {'coalesced':>9s} "
          f"{'newest last':>11s} {'backwards':>9s} {'put p50/p99 [µs]':>17s} {'here p50/p99 [µs]':>18s}")
    for name, r in (("bus rate", i["at_bus_rate"]), ("flat out", i["flat_out"])):
        put, here = r["latency_oldest_to_put"], r["latency_oldest"]
        print(f"{name:10s} {r['offered_per_s']:9d} {r['absorbed_per_s']:10d} {r['lost']:6d} {r['published_per_s']:11d} "
              f"{r['coalesced']:9d} {r['last_sample_is_last_frame']!s:>11s} {r['backwards']:9d} "
              f"{put['p50_us']:8.0f}/{put['p99_us']:<8.0f} {here['p50_us']:9.0f}/{here['p99_us']:<8.0f}")
    r = i["at_bus_rate"]
    met = r["lost"] == 0 and r["latency_oldest_to_put"]["p99_us"] <= 1000
    print(f"goal (a saturated bus, {BUS_RATE:.0f} frames/s: every frame absorbed, frame -> put p99 <= 1 ms): "
          + ("met" if met else "NOT met"))
    return 0
