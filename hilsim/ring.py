"""The transport floor for ``hilsim bench loop``: a bare zenoh-python ring of three processes.

Three processes pass one payload around a ring (bench process → relay 1 → relay 2 → bench
process), each on its own key, with the same session setup as the services (peers on loopback
through a router, callbacks, express, reliable) and payloads the size of the arm's per-step
messages. No encoding, no checks, no service code: one round is the least a distributed
lockstep step (physics → sensors → controller → physics, three hops) can cost on this machine.

``python -m hilsim.ring ENDPOINT IN_KEY OUT_KEY``: a relay (what the benchmark starts twice).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import zenoh

from hilsim import transport
from hilsim.config import ZenohConfig

PAYLOAD_BYTES = 240  # a 6-joint JointState with positions, velocities and efforts is ~230 bytes


def _session(endpoint: str) -> zenoh.Session:
    return transport.open_session(ZenohConfig(connect=[endpoint]))


def relay(endpoint: str, key_in: str, key_out: str) -> None:
    s = _session(endpoint)
    pub = transport.publisher(s, key_out)
    s.declare_subscriber(key_in, lambda sample: pub.put(sample.payload.to_bytes()))
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    sys.stdin.read()  # until the benchmark closes our stdin
    s.close()


def round_trip_us(rounds: int = 3000, warmup: int = 300) -> float:
    """Median wall time of one round of the ring, in microseconds."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    keys = ["bench/ring/0", "bench/ring/1", "bench/ring/2"]
    relays = [
        subprocess.Popen([sys.executable, "-m", "hilsim.ring", ep, keys[i], keys[i + 1]],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for i in range(2)
    ]
    s = _session(ep)
    try:
        for r in relays:
            assert r.stdout is not None
            if r.stdout.readline().strip() != "ready":
                raise RuntimeError("a ring relay did not start")
        back = threading.Event()
        s.declare_subscriber(keys[2], lambda _sample: back.set())
        pub = transport.publisher(s, keys[0])
        payload = bytes(PAYLOAD_BYTES)
        # routes between peers settle after the first samples: wait until a round completes
        deadline = time.monotonic() + 10.0
        while True:
            back.clear()
            pub.put(payload)
            if back.wait(0.2):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("the ring did not close within 10 s")
        times: list[float] = []
        for i in range(warmup + rounds):
            back.clear()
            t0 = time.perf_counter()
            pub.put(payload)
            if not back.wait(5.0):
                raise RuntimeError("a ring round was lost")
            if i >= warmup:
                times.append(time.perf_counter() - t0)
        times.sort()
        return times[len(times) // 2] * 1e6
    finally:
        for r in relays:
            if r.stdin is not None:
                r.stdin.close()
        for r in relays:
            try:
                r.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                r.kill()
        s.close()
        router.close()


if __name__ == "__main__":
    relay(*sys.argv[1:4])
