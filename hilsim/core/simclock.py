"""Sim time on a process's own wall clock, estimated from the stamps of the samples it receives.

A hardware server (the CAN bridge, the motor model) lives on the wall clock, but what it measures
belongs at a sim time: the time physics was at when the measurement was taken. Physics publishes
sim time, and every command the server receives is stamped with the sim time of the step it
answers, so ``stamp − arrival`` is the offset between the two clocks minus that command's delay on
its way. The promptest sample has the least delay, so the offset is the largest ``stamp − arrival``
of the last ``window`` seconds (a sliding maximum: physics falling behind the wall clock for a
while moves it down again), and a measurement taken at wall time ``w`` is at sim time ``w + offset``.
Its error is the promptest command's delay (well under a millisecond on one machine), not each one's.
"""

from __future__ import annotations

import time
from collections import deque


class SimClock:
    """``saw(stamp, wall)`` for each stamped sample; ``sim_ns(wall)`` is the sim time at a wall time."""

    def __init__(self, window: float = 1.0) -> None:
        self.window = window
        self._max: deque[tuple[float, float]] = deque()  # (wall, offset), offsets decreasing: a sliding max

    def saw(self, stamp_ns: int, wall: float | None = None) -> None:
        """A sample stamped ``stamp_ns`` (sim) arrived at ``wall`` (``time.monotonic()``, default now)."""
        w = time.monotonic() if wall is None else wall
        off = stamp_ns * 1e-9 - w
        q = self._max
        while q and q[-1][1] <= off:
            q.pop()
        q.append((w, off))
        while q[0][0] < w - self.window and len(q) > 1:
            q.popleft()

    @property
    def known(self) -> bool:
        return bool(self._max)

    def sim_ns(self, wall: float | None = None) -> int:
        """The sim time [ns] at wall time ``wall`` (default now); 0 before any sample."""
        if not self._max:
            return 0
        w = time.monotonic() if wall is None else wall
        return max(0, round((w + self._max[0][1]) * 1e9))


def wall_of(epoch: float) -> float:
    """A ``time.time()`` timestamp (e.g. a CAN frame's, taken by the kernel on arrival) on ``time.monotonic()``;
    now if it is unset or not plausible (in the future, or older than a second)."""
    now_mono, now_epoch = time.monotonic(), time.time()
    if not epoch or not 0.0 <= now_epoch - epoch <= 1.0:
        return now_mono
    return now_mono - (now_epoch - epoch)
