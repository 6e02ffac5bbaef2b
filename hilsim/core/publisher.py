"""A service's publisher on one key: encodes, stamps rmw_zenoh's attachment, counts, batches.

Part of :class:`hilsim.core.service.Service` (``Service.publisher``): announces itself with the
service's ``MP`` graph token, sends each message with a sequence number, the source time and its gid,
hands it unencoded to subscribers in the same process when composed, and, when the run's recorder
takes batches, puts it in the service's batch (and on its own key only while a subscriber matches).

Writes: the key it is made for.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

import zenoh

from hilsim.core import keys, msgs, transport
from hilsim.core.ros2 import wire


class Publisher:
    """Encodes, sends and counts messages on one key."""

    def __init__(self, service: Any, key: str, *, latched: bool = False) -> None:
        # service: the hilsim.core.service.Service it belongs to (above this module in the core)
        self.key = key
        self._svc = service
        self._drops = False  # samples dropped on a congested link (realtime streams)
        if latched:  # transient-local: the last sample kept for subscribers that come later
            self._pub = transport.latched_publisher(service.session, key)
        else:  # realtime: a subscriber that cannot keep up loses a stream's samples rather than delaying
            # us; never an order given once (a trajectory: nothing would replace it, the arm would not move)
            once = keys.given_once(key, service.keys.namespace_template)
            self._drops = service.sc.clock.mode == "realtime" and not once
            self._pub = transport.publisher(service.session, key, drop_when_congested=self._drops)
        self.seq = 0
        self._lock = threading.Lock()
        # composed (hilsim.launch.compose): also handed, unencoded, to the subscribers in this process
        self._local = getattr(self._pub, "deliver", None)
        # announce as a ROS 2 publisher does (its gid is its token's hash): receivers accept this key
        # only from announced writers (hilsim.core.provenance), and `ros2 topic list` sees it
        token = service.graph_token("MP", key, wire.QOS_LATCHED if latched else None)
        self.gid = wire.entity_gid(token)
        # the recorder takes batches (logger.batch): every sample also goes to the service's batch. A
        # latched one is put as before too (always: it is kept for late subscribers); in the batch as
        # well, because the recorder's late-joiner subscription, made when it sees the publisher's
        # token, can miss it (seen: its query for the cache came before the put, the put before the
        # subscription reached us); the recorder drops the second copy
        self._batch = service.batcher
        self._bidx = self._batch.writer(key, self.gid) if self._batch is not None else 0
        # pay only for what is consumed: encoded and put only while a subscriber anywhere matches
        # (Zenoh's matching status; one that appears mid-run, e.g. a ROS 2 node, turns it on at once;
        # composed, the process's publisher for the outside keeps its own: ``remote``). A latched
        # sample is kept for later subscribers, so it is always put.
        self.matching = True
        self._matching = None
        if not latched and self._local is None and isinstance(self._pub, zenoh.Publisher):
            self.matching = self._pub.matching_status.matching
            self._matching = self._pub.declare_matching_listener(self._on_matching)
        self._token = service.session.liveliness().declare_token(token)

    def _on_matching(self, status: Any) -> None:
        self.matching = bool(status.matching)

    def put(self, msg: Any, *, never_drop: bool = False) -> None:
        """``never_drop``: this one sample waits on a congested link even where the key's samples are
        dropped (realtime): a service's last health."""
        if self._batch is not None:
            self._put_batched(msg, never_drop)
            return
        # one at a time: a key written from two threads (logs, health) must still reach receivers
        # with growing sequence numbers, or they reject one sample as a duplicate or out of order
        # Not matched: counted as published all the same (a subscriber that comes later starts at a
        # later sequence number), neither encoded nor put.
        if self._local is None:
            data = msgs.encode(msg) if self.matching else None
            with self._lock:
                self.seq += 1
                if data is not None:
                    self._put_one(data, transport.attachment_bytes(self.seq, self.gid), never_drop)
        else:
            with self._lock:
                self.seq += 1
                att = transport.Attachment(self.seq, time.time_ns(), self.gid)
                self._local(msg, att)
                if self._pub.remote:  # encoded only while a subscriber outside the process exists
                    self._pub.put(msgs.encode(msg), attachment=att.encode())
        self._svc.counts_out[self.key] += 1

    def _put_one(self, data: bytes, att: bytes, never_drop: bool) -> None:
        if never_drop and self._drops:  # this one waits on a congested link, the key's others are dropped
            self._svc.session.put(self.key, data, attachment=att, congestion_control=zenoh.CongestionControl.BLOCK)
        else:
            self._pub.put(data, attachment=att)

    def _put_batched(self, msg: Any, never_drop: bool = False) -> None:
        # Encoded once, for the batch (the recorder) and, only while some other subscriber matches
        # (the recorder does not subscribe to this key now), for the key itself: a key only the
        # recorder reads costs an append, not a put. Sequence numbers and source times are the same
        # on both ways, so the recorder drops one it gets twice (a subscriber appearing, a race).
        b = self._batch
        assert b is not None
        svc = self._svc
        with self._lock:
            self.seq += 1
            t_ns = time.time_ns()
            if self._local is None:
                data = msgs.encode(msg)
                if self.matching:
                    att = transport.Attachment(self.seq, t_ns, self.gid).encode()
                    self._put_one(data, att, never_drop)
                    svc.counts_put[self.key] += 1
            else:
                att = transport.Attachment(self.seq, t_ns, self.gid)
                self._local(msg, att)
                data = msgs.encode(msg)
                if self._pub.remote:
                    self._pub.put(data, attachment=att.encode())
                    svc.counts_put[self.key] += 1
            full = b.add(self._bidx, self.seq, t_ns, data)
        if full:  # sent outside our lock: another publisher of the service may be adding meanwhile
            b.flush()
        svc.counts_out[self.key] += 1

    def wanted(self, *, covered: bool = False) -> bool:
        """Whether a sample put now would reach anyone (a matching subscriber outside, or, composed, one
        in the process, or the recorder's batch): a caller may then skip even building the message
        (:meth:`skip`). ``covered``: the same values go out in a fleet sample too (robots as arrays),
        which the recorder records robot by robot (hilsim.record.rows), so its batch does not want
        this one."""
        if self._batch is not None and not covered:  # the recorder takes every sample in its batch
            return True
        if self._local is None:
            return self.matching
        return bool(self._pub.remote) or self._svc.session.has_local(self.key)

    def skip(self) -> None:
        """A sample nobody would receive: counted as :meth:`put` counts it, neither built nor sent."""
        with self._lock:
            self.seq += 1
        self._svc.counts_out[self.key] += 1

    def undeclare(self) -> None:
        self._token.undeclare()
        if self._matching is not None:
            with contextlib.suppress(zenoh.ZError):  # gone with its session already
                self._matching.undeclare()
        self._pub.undeclare()
