"""The recorder's intake: what arrives, taken into the queue once (a part of the logger service).

A part of :class:`hilsim.services.logger.LoggerService` (one of its bases, not a service of its own).
Reads every data key of the domain (``logger.record`` under ``<domain>/``) with each sample's attachment
(sequence number, writer id: ``hilsim.core.transport``), a composed service's message objects
(``_on_local``), and with ``logger.batch`` > 0 the services' batches
(``<prefix>/batch/<domain>/<service>/<zid>/<node id>``, ``hilsim.core.batch``), a batch's samples checked
against the key table (``hilsim.core.rights``: what its service may write). Writes no key.

The Zenoh callbacks only queue: :meth:`LoggerIntake._take` takes a sample once per (key, writer,
sequence number, payload) (``hilsim.record.accounting``), counts it (received, unannounced, duplicates,
dropped at a full queue or after the subscriptions closed, after a stop) and appends it to the worker's
queue (:mod:`hilsim.services.logger_worker`); a Foxglove live server gets it as it arrives.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from typing import Any

import zenoh

from hilsim.core import batch, rights, transport
from hilsim.core.keys import Keys
from hilsim.core.service import Service
from hilsim.record import foxglove_live
from hilsim.record.accounting import LossAccounts
from hilsim.record.routes import KeyRoutes


class LoggerIntake(Service):
    """The recorder's subscriptions' callbacks and the queue's intake."""

    delay_s: float
    batching: bool
    accounts: LossAccounts
    routes: KeyRoutes
    fox: foxglove_live.FoxgloveLive | None
    gaps: Counter[str]
    dropped: Counter[str]
    duplicates: Counter[str]
    unannounced: Counter[str]
    after_stop: Counter[str]
    batch_refused: Counter[str]
    stopped: str | None
    queue_limit: int | None
    _queue: deque[tuple[str, Any, transport.Attachment | None, int]]
    _key_names: dict[str, str]
    _last_arrival: float
    _closed: bool
    _malformed_warned: bool
    _batch_rights: dict[tuple[str, str], bool]
    _service_rights: dict[str, rights.Rights | None]
    lock: threading.Lock

    # ------------------------------------------------------------------ batches (logger.batch)
    def _on_batch(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        try:
            records = batch.decode(raw)
        except batch.BatchError as e:
            # recorded as a rejected sample of the batch key (bag and rows), and the recording goes on
            if not self._malformed_warned:
                self._malformed_warned = True
                self.warn(f"malformed batch on {sample.key_expr}: {e} (further ones are only counted)")
            self._take(str(sample.key_expr), None, raw)
            return
        service = Keys.batch_service(str(sample.key_expr)) or ""
        for r in records:
            if not self.routes.covers(r.key):
                continue
            if not self._batch_may_hold(service, r.key):
                # the router lets a service put only its own batches; what one holds is checked against the key
                # table as a sample on the key itself would be at the router: not the run's, not recorded
                with self.lock:
                    self.batch_refused[r.key] += 1
                    first = self.batch_refused[r.key] == 1
                if first:
                    self.warn(f"a batch of {service or '?'} holds a sample of {r.key}, which the key table does not "
                              f"let {service or 'it'} write: not recorded (further ones are only counted)")
                continue
            self._take(r.key, transport.Attachment(r.seq, r.source_ns, r.gid), r.payload)

    def _batch_may_hold(self, service: str, key: str) -> bool:
        """Whether ``service`` may write ``key`` (hilsim.core.rights, as its identity at the router), cached."""
        got = self._batch_rights.get((service, key))
        if got is None:
            if service not in self._service_rights:  # derived once per service (the type hashes are not free)
                try:
                    self._service_rights[service] = rights.service_rights(self.sc, service) if service else None
                except Exception:  # a service name the scenario does not know: nobody's batch
                    self._service_rights[service] = None
            r = self._service_rights[service]
            got = r is not None and r.may_put(key)
            self._batch_rights[(service, key)] = got
        return got

    # ------------------------------------------------------------------ receiving (Zenoh thread)
    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Only queue: decoding here would slow Zenoh's delivery to every other subscriber.
        self._take(str(sample.key_expr), transport.read_attachment(sample), sample.payload.to_bytes())

    def _on_local(self, key: str, msg: Any, att: transport.Attachment) -> None:
        # composed (hilsim.launch.compose): a message object from a service of this process; encoded by
        # the worker, so it is recorded from the same bytes (and rows) as one that came over Zenoh
        self._take(key, att, msg)

    def _take(self, k: str, att: transport.Attachment | None, payload: Any) -> None:
        if self.delay_s and not self.stop_event.is_set():
            time.sleep(self.delay_s)
        k = self._key_names.setdefault(k, k)  # one string per key, not one per queued sample
        self._last_arrival = time.monotonic()
        if self.stopped is not None:  # the recording stopped (logger.max_size, min_free): not taken in
            with self.lock:
                self.after_stop[k] += 1
            return
        # The base's health thread iterates these counters under self.lock.
        with self.lock:
            prov = self.provenance
            if att is not None and (k not in prov.restricted or att.gid in prov.writers.get(k, ())):
                # a writer announced for another key, on this open one: not that writer (an insider's forgery,
                # hilsim.core.provenance); recorded, counted as unannounced, its gaps no loss of ours
                elsewhere = prov.announced_elsewhere(k, att.gid)
                if not self.accounts.sequence(k, att, payload, counted=not elsewhere):
                    # it came both ways (in a batch, or from a latched writer's cache, and on its key): once
                    self.duplicates[k] += 1
                    return
                if elsewhere:
                    self.unannounced[k] += 1
            elif k in prov.restricted:
                # Batching: a writer whose token is not known yet (a race at its start) can send a sample
                # both ways too; taken once all the same, its gaps not counted (not announced yet)
                if att is not None and self.batching and not self.accounts.sequence(k, att, payload, counted=False):
                    self.duplicates[k] += 1
                    return
                # recorded like everything received, but a stranger's gaps are no loss of ours
                self.unannounced[k] += 1
            if self.stopped is not None:
                self.after_stop[k] += 1
                return
            t_ns = time.time_ns()
            queued = not (self._closed or (self.queue_limit is not None and len(self._queue) >= self.queue_limit))
            if queued:
                self.counts_in[k] += 1
                self._queue.append((k, payload, att, t_ns))
            else:
                self.dropped[k] += 1
        fox = self.fox
        if fox is not None and isinstance(payload, bytes):
            # Foxglove's clients get it as it arrives, not once the worker wrote it: a live view stays live
            # when the files fall behind (seen: minutes behind, the queue full, in a realtime run); the
            # server never waits for a client (its backlog drops a slow one's oldest)
            fox.add(k, payload, t_ns)
        if not queued:
            return
        if k in self.routes.latched:
            self.routes.got(k)  # its publisher's cache need not be asked again
        if self.accounts.say_suspect:
            said, self.accounts.say_suspect = self.accounts.say_suspect, ""
            self.warn(said)

    def lost(self) -> Counter[str]:
        """Samples lost per key: gaps in the sequence numbers plus drops at the full queue."""
        with self.lock:
            return self.gaps + self.dropped
