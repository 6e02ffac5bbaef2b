"""The transport floor for ``hilsim bench loop``: a bare zenoh-python ring of three processes.

Three processes pass one payload around a ring (bench process → relay 1 → relay 2 → bench
process), each on its own key, with the same session setup as the services (peers on loopback
through a router, callbacks, reliable, ``transport.publisher``) and payloads the size of the arm's per-step
messages. No encoding, no checks, no service code: one round is the least a distributed
lockstep step (physics → sensors → controller → physics, three hops) can cost on this machine.

``python -m hilsim.tools.bench.ring ENDPOINT IN_KEY OUT_KEY``: a relay (what the benchmark starts twice).

The recording floor (:func:`sample_cost_us`): what one sample costs a subscriber in another process,
CPU time of its whole process (Zenoh's threads included) per received sample, with the Python
callback the services use and with a Zenoh FIFO channel read by a Python thread, and what a
``put`` to that subscriber costs the publisher; the arm's per-step mix (six keys) at a steady
pace. ``python -m hilsim.tools.bench.ring publish ENDPOINT SAMPLES PER_TICK TICK_US``: the publisher.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable

import zenoh

from hilsim.core import transport
from hilsim.core.config import ZenohConfig

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
        subprocess.Popen([sys.executable, "-m", "hilsim.tools.bench.ring", ep, keys[i], keys[i + 1]],
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


KEYS_PER_STEP = 6  # the arm's per-step keys: clock, truth joint states and IMU, joint states, commands, reference


def publish(endpoint: str, samples: int, per_tick: int, tick_us: float) -> None:
    """Publish ``samples`` payloads round-robin on ``per_tick`` keys, ``per_tick`` every
    ``tick_us``, once a line arrives on stdin; print this process's CPU seconds for it."""
    s = _session(endpoint)
    pubs = [transport.publisher(s, f"bench/rec/{i}") for i in range(per_tick)]
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    sys.stdin.readline()
    payload = bytes(PAYLOAD_BYTES)
    c0, nxt = time.process_time(), time.perf_counter()
    for j in range(samples):
        pubs[j % per_tick].put(payload)
        if j % per_tick == per_tick - 1:
            nxt += tick_us * 1e-6
            time.sleep(max(0.0, nxt - time.perf_counter()))
    sys.stdout.write(f"{time.process_time() - c0}\n")
    sys.stdout.flush()
    sys.stdin.read()  # until the benchmark closes our stdin
    s.close()


def _publisher_cpu_s(ep: str, samples: int, tick_us: float,
                     received: Callable[[], int] | None) -> tuple[float, float]:
    """Run the publisher once against this process's session; wait for every sample if someone here
    receives them; return the CPU seconds of the publisher and of this process meanwhile."""
    p = subprocess.Popen([sys.executable, "-m", "hilsim.tools.bench.ring", "publish", ep, str(samples),
                          str(KEYS_PER_STEP), str(tick_us)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdin is not None and p.stdout is not None
    try:
        if p.stdout.readline().strip() != "ready":
            raise RuntimeError("the sample-cost publisher did not start")
        time.sleep(0.5)  # its subscriptions' routes settle
        c0 = time.process_time()
        p.stdin.write("go\n")
        p.stdin.flush()
        cpu = float(p.stdout.readline())
        deadline = time.monotonic() + 30.0
        while received is not None and received() < samples:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{samples - received()} of {samples} samples never arrived")
            time.sleep(0.01)
        return cpu, time.process_time() - c0
    finally:
        p.stdin.close()
        try:
            p.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def sample_cost_us(samples: int = 35_000, tick_us: float = 300.0) -> dict[str, float]:
    """CPU µs per sample: ``callback`` and ``channel`` (the receiving process, per sample received),
    ``put`` (the publisher, per sample, over its cost with nobody subscribed)."""
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    # the subscriber listens and the publisher connects to it: no router's CPU in either figure
    s = transport.open_session(ZenohConfig(connect=[], listen=[ep]))
    out: dict[str, float] = {}
    try:
        idle, _ = _publisher_cpu_s(ep, samples, tick_us, None)
        got = [0]

        def count(_sample: zenoh.Sample) -> None:
            got[0] += 1

        sub = s.declare_subscriber("bench/rec/*", count)
        busy, here = _publisher_cpu_s(ep, samples, tick_us, lambda: got[0])
        out["callback"] = here / samples * 1e6
        out["put"] = max(busy - idle, 0.0) / samples * 1e6
        sub.undeclare()
        chan = s.declare_subscriber("bench/rec/*", zenoh.handlers.FifoChannel(samples + 1))
        taken = [0]

        def drain() -> None:
            while taken[0] < samples:
                try:
                    chan.recv()
                except zenoh.ZError:  # closed
                    return
                taken[0] += 1

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        _, here = _publisher_cpu_s(ep, samples, tick_us, lambda: taken[0])
        out["channel"] = here / samples * 1e6
        chan.undeclare()
        reader.join(timeout=5.0)
        return out
    finally:
        s.close()


if __name__ == "__main__":
    if sys.argv[1] == "publish":
        publish(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5]))
    else:
        relay(*sys.argv[1:4])
