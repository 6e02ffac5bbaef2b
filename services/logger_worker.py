"""The recorder's worker: the queue into the files (a part of the logger service).

A part of :class:`hilsim.services.logger.LoggerService` (one of its bases, not a service of its own).
Reads and writes no key: one thread takes the samples the intake queued
(:mod:`hilsim.services.logger_intake`), hands each payload to the bag (``hilsim.record.bag``), decodes it
(``hilsim.core.msgs``; a composed service's message object is encoded first) and turns it into rows
(``hilsim.record.rows.RowWriter``; the per-step keys' fast path), a payload that does not decode or
validate counted as rejected and recorded as a text row; a health sample's published counts go to the
loss accounts. Every ``FLUSH_PERIOD_S`` or ``FLUSH_ROWS`` rows it flushes: the rows sent into the
``.rrd``, the bag's chunk written, the samples counted as recorded and bagged; then a file may split
(:mod:`hilsim.services.logger_files`) and the size limits are checked (``_limit_reached``, in
:mod:`hilsim.services.logger_stop`).
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter, deque
from typing import Any

from hilsim.core import msgs, transport
from hilsim.core.keys import UnknownKey, message_type
from hilsim.core.threads import name_os_thread
from hilsim.record import live
from hilsim.record.accounting import LossAccounts
from hilsim.record.bag import NO_ATTACHMENT
from hilsim.record.rows import RowWriter
from hilsim.services.logger_files import LoggerFiles

FLUSH_PERIOD_S = 0.5  # wall seconds between send_columns batches
FLUSH_ROWS = 20_000  # …or earlier when this many rows are buffered
FILE_FLUSH_TIMEOUT_S = 5.0  # at most this long waiting for a batch to reach the file


class LoggerWorker(LoggerFiles):
    """The recorder's worker thread: decoding, rows, the bag, flushing."""

    rows: RowWriter | None
    fox: Any
    bagged: Counter[str]
    recorded: Counter[str]
    accounts: LossAccounts
    _queue: deque[tuple[str, Any, transport.Attachment | None, int]]
    _pending: Counter[str]
    _warned: set[str]
    _worker_stop: threading.Event
    _codec_lock: threading.RLock
    _bag_append: Any

    # ------------------------------------------------------------------ the worker
    def _ordinary_class(self) -> None:
        """The worker (this thread) in the ordinary scheduling class: hilsim up gives the recorder's threads
        SCHED_FIFO in realtime for its receiving; writing the files must not take a core from the loop."""
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass

    def _flush_period(self) -> float:
        """Flushed more often while a viewer watches (the view moves on every live.FLUSH_PERIOD_S); asked after
        each flush, not per sample."""
        return live.FLUSH_PERIOD_S if self.live is not None and self.live.streaming() else FLUSH_PERIOD_S

    def _work(self) -> None:
        name_os_thread(b"logger-worker")  # as the OS sees it: hilsim up leaves it out of SCHED_FIFO
        q = self._queue
        rows = self.rows
        assert rows is not None
        last_flush = time.monotonic()
        period = self._flush_period()
        while True:
            try:
                key, payload, att, t = q.popleft()
            except IndexError:
                if self._worker_stop.is_set():
                    break
                if rows.buffered and time.monotonic() - last_flush >= period:
                    self._ordinary_class()
                    self._flush()
                    last_flush, period = time.monotonic(), self._flush_period()
                    if self._limit_reached():
                        break
                time.sleep(0.002)
                continue
            self._handle(key, payload, att, t)
            if rows.buffered >= FLUSH_ROWS or time.monotonic() - last_flush >= period:
                self._ordinary_class()
                self._flush()
                last_flush, period = time.monotonic(), self._flush_period()
                if self._limit_reached():
                    break

    def _handle(self, key: str, payload: Any, att: transport.Attachment | None = None, t_ns: int = 0) -> None:
        rows = self.rows
        assert rows is not None
        local = not isinstance(payload, bytes)
        if local:  # a message object of this process (_on_local)
            try:
                payload = msgs.encode(payload)  # pycdr2's buffer is per thread (hilsim.core.msgs.codec)
            except Exception as e:  # not encodable: still recorded, as the error and the message's text
                self.fault(f"cannot encode {key} from this process: {type(e).__name__}: {e}", exc=e)
                rows.error(key, e, payload)
                self._pending[key] += 1
                return  # no bytes: nothing for the bag (bagged < recorded for this key)
        if self.bag is not None:  # every payload as it arrived, valid or not
            self._bag_append((key, payload, NO_ATTACHMENT if att is None else att, t_ns))
        if self.fox is not None and local:  # a composed service's message: to Foxglove once encoded (_take: the rest)
            self.fox.add(key, payload, t_ns)
        if rows.raw(key, payload):  # a clock, joint state or IMU sample of a layout seen before
            self.sim_ns = rows.clock_ns
            self._pending[key] += 1
            return
        try:
            cls = message_type(key)
            with self._codec_lock:
                msg = msgs.decode(cls, payload)
        except (UnknownKey, msgs.BadMessage) as e:
            self._reject(key, e)
            rows.rejected(key, len(payload), e)
            self._pending[key] += 1
            return
        if isinstance(msg, msgs.DiagnosticArray) and "/health/" in key:
            self.accounts.note_published(key, msg)
        try:
            rows.message(key, msg)
            rows.learn(key, payload, msg)
        except Exception as e:  # a bug here must not lose the sample: record it as text
            self.fault(f"cannot turn {key} into rows: {type(e).__name__}: {e}", exc=e)
            rows.error(key, e, msg)
        self.sim_ns = rows.clock_ns
        self._pending[key] += 1

    def _reject(self, key: str, e: Exception) -> None:
        with self.lock:
            self.rejected[key] += 1
        if key not in self._warned:  # one warning per key; the rest are counted
            self._warned.add(key)
            self.warn(f"rejected payload on {key}: {e} (further ones on this key are only counted)")

    def _flush(self) -> None:
        """Send every buffered row and push it through Rerun's batcher into the file, then count
        the samples they came from as recorded. A recorder killed with SIGKILL (no footer
        written) thus leaves a file that holds everything up to its last flush, FLUSH_PERIOD_S
        ago at most; ``hilsim.core.recording.recover_rrd`` makes it a complete .rrd again."""
        assert self.rows is not None and self.rec is not None
        ok = self.rows.flush()
        for key, e in self.rows.rejections:  # found while the fast path's batches were turned into rows
            self._reject(key, e)
        self.rows.rejections.clear()
        if ok:
            try:
                self.rec.flush(timeout_sec=FILE_FLUSH_TIMEOUT_S)
            except Exception as e:  # a slow disk: the rows are still on their way to the file
                self.warn(f"the recording was not written to {self.rrd_path} within {FILE_FLUSH_TIMEOUT_S:g} s: {e}")
            if self.live is not None:
                self.live.pump()  # never waits: a slow viewer's frames are dropped, counted in health
            with self.lock:
                self.recorded.update(self._pending)
                self.written_ns = self.rows.clock_ns  # every row up to this sim time is in the file now
            self._split_rrd()
        self._pending.clear()
        if self.bag is not None:
            n_files, closed_bytes = len(self.bag.files), self.bag.closed_bytes
            try:
                wrote = self.bag.flush()  # and on in a new file, if this one is as large or long as allowed
            except Exception as e:  # a full disk, a bug: the .rrd goes on, the bag stops here (a fault)
                self.fault(f"the bag {self.bag.path} stopped: {type(e).__name__}: {e}", exc=e)
                self.bag.abandon()
                self.bag = None
                return
            self._bag_append = self.bag.append
            with self.lock:
                self.bagged.update(wrote)
            if len(self.bag.files) > n_files:  # split: the bag's file before the current one closed
                self._say_closed(self.bag.files[-2], self.bag.closed_bytes - closed_bytes, self.bag.path)
