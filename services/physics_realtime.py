"""Physics' realtime loop and its timing figures: steps paced by the wall clock, tick jitter, step latency.

A part of :class:`hilsim.services.physics.PhysicsService` (one of its bases, not a service of its own).
``clock.mode: realtime``: physics asks for SCHED_FIFO (as HIL setups do; without the privilege it says so
and goes on), steps at the wall clock's deadlines (sleeping most of the way, then spinning at most
``SPIN_NS``), counts a step that finishes after its deadline as an overrun, and keeps each tick's lateness
in a histogram of 1 µs bins. Lockstep's wall time per step (the whole round) is kept the same way; both
give the percentiles of physics' health (``jitter_p50_us`` … ``step_p99_us``).

Reads and writes no key of its own: each step is :meth:`PhysicsService._advance` (truth out through
:mod:`hilsim.services.physics_truth`); external joint servers are checked every 50 ticks
(:mod:`hilsim.services.physics_servers`).
"""

from __future__ import annotations

import gc
import os
import time
from collections.abc import Callable

import numpy as np

from hilsim.services.physics_servers import PhysicsServers

SPIN_NS = 80_000  # realtime: busy-wait at most this long before a deadline
REALTIME_PRIORITY = 10  # SCHED_FIFO priority of physics in realtime mode (if permitted)
STEP_BINS = 200_000  # lockstep: wall time per step, 1 µs bins (last bin: 200 ms or more)
JITTER_BINS = 20_000  # realtime: tick lateness, 1 µs bins (last bin: 20 ms or more)


def _percentile(hist: np.ndarray, n: int, q: float) -> float:
    """The q-quantile of ``n`` samples in a histogram of 1 µs bins, in µs."""
    return float(np.searchsorted(np.cumsum(hist), q * n))


class PhysicsRealtime(PhysicsServers):
    """Physics' realtime loop (:class:`hilsim.services.physics.PhysicsService` sets these attributes)."""

    jitter_hist: np.ndarray  # realtime: tick lateness histogram, 1 µs bins
    ticks: int
    step_hist: np.ndarray  # lockstep: wall time per step histogram, 1 µs bins
    step_count: int
    done: bool
    _advance: Callable[[], None]  # one step (PhysicsService)

    # ------------------------------------------------------------------ realtime
    def _raise_priority(self) -> None:
        """Realtime: ask the kernel for a real-time scheduling class, as HIL setups do; the
        other services then cannot delay a tick. Without the privilege, say so and go on."""
        try:
            # every thread of the process: a Zenoh thread preempted while holding the GIL
            # would otherwise stall the stepping thread (priority inversion)
            for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
            self.log.info("realtime: running with SCHED_FIFO priority %d", REALTIME_PRIORITY)
        except (PermissionError, AttributeError, OSError) as e:
            self.log.warning("realtime: could not get a real-time scheduling class (%s); "
                             "tick jitter will depend on the machine's load", e)

    def _realtime_loop(self) -> None:
        self._raise_priority()
        # a full garbage collection can take milliseconds: move what exists now out of its
        # reach and make young-generation collections rarer
        gc.freeze()
        gc.set_threshold(50_000, 50, 100)
        dt_ns = self.sc.dt_ns
        t0 = time.perf_counter_ns()
        k = 0
        while not self.stop_event.is_set() and not self.done:
            k += 1
            deadline = t0 + k * dt_ns
            # sleep most of the way, then spin: time.sleep alone overshoots by ~60 µs. The spin
            # is kept short because on a small machine it takes CPU from the other services.
            while True:
                now = time.perf_counter_ns()
                remaining = deadline - now
                if remaining <= 0:
                    break
                if remaining > SPIN_NS:
                    time.sleep((remaining - SPIN_NS) / 1e9)
            with self.lock:
                self._advance()
                if self.done:
                    break
                if self.servers and k % 50 == 0:
                    self._check_servers()
            self.jitter_hist[min((now - deadline) // 1000, JITTER_BINS)] += 1
            self.ticks += 1
            if time.perf_counter_ns() > deadline + dt_ns:
                self.overruns += 1
        if self.done:
            self.stop_event.wait()

    def _jitter_figures(self) -> dict[str, str]:
        out = {}
        if self.ticks:
            out["jitter_p50_us"] = f"{_percentile(self.jitter_hist, self.ticks, 0.5):.0f}"
            out["jitter_p99_us"] = f"{_percentile(self.jitter_hist, self.ticks, 0.99):.0f}"
        if self.step_count:
            out["step_p50_us"] = f"{_percentile(self.step_hist, self.step_count, 0.5):.0f}"
            out["step_p99_us"] = f"{_percentile(self.step_hist, self.step_count, 0.99):.0f}"
        return out
