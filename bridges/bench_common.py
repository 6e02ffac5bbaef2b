"""What ``hilsim bench can`` (:mod:`.can_bench`) and ``hilsim bench mavlink`` (:mod:`.mavlink_bench`)
share: latency percentiles, paced probes and sending flat out, and the bridge under test run as its
own process the way ``hilsim up`` runs it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.core import transport
from hilsim.core.keys import Keys

PACE = 0.005  # s between latency probes (200 Hz)


def pct(xs: list[float]) -> dict[str, float]:
    """How many latencies (s), and their p50 and p99 in µs."""
    if not xs:
        return {"n": 0, "p50_us": float("nan"), "p99_us": float("nan")}
    a = np.asarray(xs) * 1e6
    return {"n": len(xs), "p50_us": round(float(np.percentile(a, 50)), 1),
            "p99_us": round(float(np.percentile(a, 99)), 1)}


def probes(send: Callable[[int], Any], numbers: Iterable[int], clock: Callable[[], float]) -> dict[int, float]:
    """``send(k)`` for each probe number, :data:`PACE` apart; each one's send time by ``clock``."""
    sent: dict[int, float] = {}
    for k in numbers:
        sent[k] = clock()
        send(k)
        time.sleep(PACE)
    return sent


def flat_out(send: Callable[[int], Any], seconds: float, first: int = 1, times: list[float] | None = None) -> int:
    """``send(k)`` for k = first, first + 1, … as fast as it goes for ``seconds``; how many were sent.
    With ``times``, each send's wall-clock time (``time.time()``) is appended to it just before."""
    t0 = time.perf_counter()
    k = first
    while time.perf_counter() - t0 < seconds:
        if times is not None:
            times.append(time.time())
        send(k)
        k += 1
    return k - first


@contextmanager
def bridge_process(service: str, config: Path, workdir: Path, session: Any, keys: Keys) -> Iterator[Path]:
    """``hilsim run SERVICE --config CONFIG`` as its own process (output in ``WORKDIR/SERVICE.log``,
    which it yields), until its liveliness token is seen (60 s at most); at the end stopped as
    ``hilsim up`` stops it (SIGINT, then SIGKILL after 15 s)."""
    log_path = workdir / f"{service}.log"
    log = open(log_path, "wb")  # closed in the finally below
    proc = subprocess.Popen([sys.executable, "-m", "hilsim.cli", "run", service, "--config", str(config)],
                            stdout=log, stderr=log, start_new_session=True)
    try:
        if not transport.wait_for_service(session, keys, service, 60):
            raise RuntimeError(f"{service} did not start (log: {log_path})")
        yield log_path
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()
