"""What the bag costs the recorder, for ``hilsim bench loop``: CPU per recorded sample with
``logger.bag`` off and on.

Two figures:

- :func:`worker_us_per_sample`: the recorder's worker thread alone, no Zenoh: the arm's message mix
  of ``steps`` 1 kHz steps (truth and measured joint states, truth IMU, clock, commands, reference,
  the planner's acknowledgement every 10 steps, the IMU every 5), encoded first, then taken through
  ``LoggerService._handle`` and ``_flush`` (every 4000 samples, about the worker's 0.5 s batch at
  1x) as the worker does, into a real ``.rrd`` and bag; CPU time of this thread per sample.
- :func:`process_us_per_sample`: the whole logger process of a ``hilsim up`` run (Zenoh's receive
  included): its CPU seconds from "ready" to the end of the run (``hilsim.tools.bench.pipeline``) per
  sample it recorded (``record_summary.json``).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.recording import SUMMARY_NAME, read_counts
from hilsim.core.scenario import load_scenario

FLUSH_EVERY = 4000  # samples between the worker's batches here (about 0.5 s of the arm at 1x)


def arm_mix(steps: int, keys: Keys) -> list[tuple[str, bytes, transport.Attachment]]:
    """The arm's samples of ``steps`` steps, encoded, each with its writer's attachment."""
    joints = [f"joint_{i}" for i in range(1, 7)]
    gids: dict[str, bytes] = {}
    seqs: dict[str, int] = {}
    out: list[tuple[str, bytes, transport.Attachment]] = []

    def put(key: str, msg: Any) -> None:
        seqs[key] = seqs.get(key, 0) + 1
        gid = gids.setdefault(key, transport.new_gid())
        out.append((key, msgs.encode(msg), transport.Attachment(seqs[key], time.time_ns(), gid)))

    for k in range(steps):
        t = k * 1_000_000
        q = [0.001 * k + 0.1 * i for i in range(6)]
        js = msgs.JointState(header=msgs.header(t, "world"), name=joints, position=q, velocity=[0.2] * 6,
                             effort=[0.3] * 6)
        put(keys.truth("joint_states"), js)
        put(keys.clock, msgs.Clock(clock=msgs.stamp(t)))
        put(keys.truth("imu"), msgs.Imu(header=msgs.header(t, "tool"), orientation=msgs.Quaternion(w=1.0)))
        put(keys.topic("joint_states"), js)
        put(keys.topic("joint_commands"), msgs.JointState(header=msgs.header(t), name=joints, effort=[0.1] * 6))
        put(keys.topic("controller/reference"), msgs.JointState(header=msgs.header(t), name=joints, position=q,
                                                                velocity=[0.0] * 6))
        if k % 5 == 0:
            put(keys.topic("imu"), msgs.Imu(header=msgs.header(t, "tool"), orientation=msgs.Quaternion(w=1.0)))
        if k % 10 == 0:
            put(keys.sync("planner"), msgs.Clock(clock=msgs.stamp(t)))
    return out


def worker_us_per_sample(steps: int = 5000, bag: bool = True, mix: list[Any] | None = None) -> float:
    """CPU µs per sample of the recorder's worker on the arm mix (see the module docstring)."""
    from hilsim.record.rows import RowWriter
    from hilsim.services.logger import LoggerService, rr

    with tempfile.TemporaryDirectory(prefix="hilsim-bench-bag-") as d:
        sc = load_scenario("arm", {"logger.run_dir": str(Path(d) / "run"), "logger.bag": bag})
        mix = mix if mix is not None else arm_mix(steps, Keys.of(sc))
        svc = LoggerService(sc)
        svc.run_dir.mkdir(parents=True)
        svc.rec = rr.RecordingStream("bench", send_properties=False)
        svc.rec.save(svc.rrd_path)
        svc.rows = RowWriter(svc.rec, sc.robot, None, svc.fault, None)
        svc.bag = svc._open_bag() if bag else None
        if svc.bag is not None:
            svc._bag_append = svc.bag.append
        handle, flush = svc._handle, svc._flush
        t0 = time.thread_time()
        for i, (key, data, att) in enumerate(mix, 1):
            handle(key, data, att, time.time_ns())
            if i % FLUSH_EVERY == 0:
                flush()
        flush()
        if svc.bag is not None:
            svc.bag.close()
        cpu = time.thread_time() - t0
        svc.rec.disconnect()
        if sum(svc.recorded.values()) != len(mix) or (bag and sum(svc.bagged.values()) != len(mix)):
            raise RuntimeError(f"the bench lost samples: {len(mix)} in, {sum(svc.recorded.values())} recorded, "
                               f"{sum(svc.bagged.values())} bagged")
    return 1e6 * cpu / len(mix)


def worker_cost(steps: int = 5000, repeat: int = 3) -> dict[str, float]:
    """The worker's µs per sample without and with the bag, alternating, best of ``repeat`` each."""
    keys = Keys()
    mix = arm_mix(steps, keys)
    off, on = [], []
    for _ in range(repeat):
        off.append(worker_us_per_sample(bag=False, mix=mix))
        on.append(worker_us_per_sample(bag=True, mix=mix))
    return {"samples": float(len(mix)), "without_bag_us": min(off), "with_bag_us": min(on)}


def process_us_per_sample(run_dir: Path, logger_cpu_s: float) -> float:
    """The logger process's CPU per recorded sample of a run (its record_summary.json)."""
    counts, _ = read_counts(run_dir / SUMMARY_NAME)
    n = sum(v.get("recorded", 0) for v in counts.values())
    return 1e6 * logger_cpu_s / max(n, 1)
