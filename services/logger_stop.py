"""The recorder's stop: at a size limit while the run goes on, or at the run's end (a part of the logger service).

A part of :class:`hilsim.services.logger.LoggerService` (one of its bases, not a service of its own).
``logger.max_size`` / ``logger.min_free`` reached (checked by the worker after each flush): the
subscriptions go, what was taken in is written, both files are closed whole, and the recording stops
while the run goes on. At the run's end: keep receiving until nothing arrived for ``QUIET_S`` (at most
``DRAIN_LIMIT_S``), undeclare the subscriptions (the recorder's own notices are no longer published
from then on: ``_intake_closed``), drain the queue, close the files, and report. Reads no key; writes
``record_summary.json`` (``hilsim.record.report``, the losses judged by ``hilsim.record.loss``), one line
per key on stdout, and a fault or warning on the recorder's log and health keys
(``<prefix>/<robot>/log/logger``, ``<prefix>/<robot>/health/logger``) when counts disagree or samples were lost.
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import transport
from hilsim.record import foxglove_live, live, loss, report
from hilsim.record.accounting import LossAccounts
from hilsim.record.limits import human_bytes, stop_reason
from hilsim.record.routes import KeyRoutes
from hilsim.services.logger_worker import LoggerWorker

# At exit: wait for what is still in flight until nothing arrived for QUIET_S, at most DRAIN_LIMIT_S.
QUIET_S = 0.25
DRAIN_LIMIT_S = 5.0


class LoggerStop(LoggerWorker):
    """Stopping the recording: at a limit (``_stop_recording``) or at the end (``_finish``)."""

    realtime: bool
    batching: bool
    summary_path: Path
    routes: KeyRoutes
    accounts: LossAccounts
    gaps: Counter[str]
    dropped: Counter[str]
    rejected: Counter[str]
    before_first: Counter[str]
    unannounced: Counter[str]
    duplicates: Counter[str]
    suspect: Counter[str]
    after_stop: Counter[str]
    batch_refused: Counter[str]
    stopped: str | None
    stopped_at: dict[str, Any]
    _queue: deque[tuple[str, Any, transport.Attachment | None, int]]
    _subs: list[Any]
    _worker: threading.Thread | None
    _finished: bool
    _closed: bool
    _intake_closed: bool
    _last_arrival: float

    # ------------------------------------------------------------------ limits (logger.max_size, min_free)
    def _limit_reached(self) -> bool:
        """In the worker, after a flush: if the recording reached ``logger.max_size`` or the disk's free
        space ``logger.min_free``, stop recording (:meth:`_stop_recording`) and return True (the worker ends)."""
        lc = self.sc.logger
        if not (lc.max_size or lc.min_free):
            return False
        why = stop_reason(self.run_dir, self.recording_bytes(), lc.max_size, lc.min_free)
        if why is None:
            return False
        self._stop_recording(why)
        return True

    def _stop_recording(self, why: str) -> None:
        """Stop recording, cleanly, while the run goes on: no sample is taken in from here (the
        subscriptions go; samples still queued are counted as ``after_stop``, not received), what was
        taken in is written, and both files are closed whole (the bag's summary, footer and
        ``metadata.yaml``; the ``.rrd``'s footer). Said in one line (log and health) and in
        ``record_summary.json``."""
        self._begin_stop()
        with self.lock:  # _take checks it under the lock: nothing is queued after this
            self.stopped = why
            while self._queue:  # taken in, not written: no longer counted as received
                k = self._queue.popleft()[0]
                self.counts_in[k] -= 1
                self.after_stop[k] += 1
        subs = [*self._subs, *self.routes.close()]
        for sub in subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        self._subs.clear()
        self._close_files()
        live.stop(self.live)
        foxglove_live.stop(self.fox)
        self.fox = None
        used = self.recording_bytes()
        self.stopped_at = {"reason": why, "sim_time": round(self.sim_ns / 1e9, 3), "bytes": used,
                           "wall_time": time.strftime("%Y-%m-%dT%H:%M:%S")}
        self.warn(f"recording stopped at sim time {self.sim_ns / 1e9:.3f} s: {why}; the files hold the run up to "
                  f"here ({human_bytes(used)}, closed whole), the run goes on")

    def _close_files(self) -> None:
        """Write what was taken in, then close the ``.rrd`` (its footer) and the bag whole."""
        assert self.rec is not None
        self._flush()
        self.rec.flush()
        self.rec.disconnect()
        self._close_bag()

    # ------------------------------------------------------------------ stopping
    def _finish(self) -> None:
        """Stop receiving, record everything queued, close the file, report the counts."""
        if self._finished:
            return
        self._finished = True
        self._begin_stop()
        self._await_quiet()
        key_subs = self.routes.close()  # no key subscription declared after this
        with self._codec_lock:  # a notice being put now reaches the subscription; none after (_publish_log)
            self._intake_closed = True
        for sub in [*self._subs, *key_subs]:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass  # already gone with the session
        with self.lock:  # a callback still running now counts its sample as dropped
            self._closed = True
        self._worker_stop.set()
        if self._worker is not None:
            self._worker.join()
        if self.rec is None:
            return
        if self.stopped is None:
            while self._queue:  # anything that arrived while the worker was stopping
                self._handle(*self._queue.popleft())
            self._close_files()
        live.stop(self.live)
        foxglove_live.stop(self.fox)
        self._report()

    def _await_quiet(self) -> None:
        """Before closing: keep receiving what is still in flight (samples a realtime publisher's
        link holds for a slow logger, up to the kernel's socket buffers) until nothing arrived
        for ``QUIET_S``, at most ``DRAIN_LIMIT_S``. What is still in flight then is not seen."""
        t0 = time.monotonic()
        with self.lock:
            n0 = sum(self.counts_in.values()) + sum(self.dropped.values())
        while time.monotonic() - t0 < DRAIN_LIMIT_S and time.monotonic() - self._last_arrival < QUIET_S:
            time.sleep(0.02)
        with self.lock:
            n = sum(self.counts_in.values()) + sum(self.dropped.values()) - n0
        self.log.info("stopping: %d samples still arrived in %.2f s", n, time.monotonic() - t0)

    def _report(self) -> None:
        with self.lock:
            c = report.Counts(
                received=Counter(self.counts_in), recorded=Counter(self.recorded), bagged=Counter(self.bagged),
                rejected=Counter(self.rejected), lost=Counter(), dropped=Counter(self.dropped),
                before_first=Counter(self.before_first), unannounced=Counter(self.unannounced),
                duplicates=Counter(self.duplicates), after_stop=Counter(self.after_stop),
                suspect=Counter(self.suspect), contested=Counter(), batch_refused=Counter(self.batch_refused))
        c.plain = self.routes.plain_keys()
        c.expected = loss.expected_keys(self.sc, self.keys, self.routes.covers) if self.stopped is None else set()
        with self.lock:
            gaps = Counter(self.gaps)
        c.lost = self.accounts.judged_lost(gaps, c.dropped, c.received)
        c.contested = self.accounts.contested()
        for k in gaps:  # gaps its writers' own counts say are not losses: said apart, as contested ones
            c.contested[k] += gaps[k] - (c.lost[k] - c.dropped[k])
        bag = self.sc.logger.bag
        stopped_at = self.stopped_at if self.stopped is not None else None
        tmp = self.summary_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(report.summary(c, bag=bag, batching=self.batching, stopped_at=stopped_at),
                                  indent=1, sort_keys=True) + "\n")
        tmp.replace(self.summary_path)
        lines = report.lines(c, rrd=self.rrd_path, bag_dir=self.bag_dir if bag else None, clock=self.sc.clock.mode,
                             stopped_at=stopped_at)
        total_in, total_rec, total_lost = sum(c.received.values()), sum(c.recorded.values()), sum(c.lost.values())
        try:
            print("\n".join(lines), flush=True)
        except BrokenPipeError:
            # whoever read our stdout is gone (a killed launcher); the summary file is written
            self.log.warning("stdout closed; per-key counts are in %s", self.summary_path)
        if total_in != total_rec:
            self.fault(f"received {total_in} messages but recorded {total_rec}")
        if bag and sum(c.bagged.values()) != total_rec:
            self.fault(f"recorded {total_rec} messages but bagged {sum(c.bagged.values())}")
        if total_lost and not self.realtime:
            self.fault(f"lost {total_lost} samples in lockstep, where nothing may be lost")
        elif total_lost:
            self.warn(f"lost {total_lost} samples: the recorder could not keep up with the realtime loop")
