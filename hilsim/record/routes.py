"""The recorder's routes: which keys it subscribes to one by one, for which writers.

With ``logger.batch`` the run's services send the recorder their samples in batches (hilsim.core.batch)
and it subscribes key by key only for the writers no batch covers (ROS 2 nodes, tools, bridges of other
runs) and for transient-local writers (a late-joiner subscription asks the publisher's cache). Without
batches ``**`` takes every key and only the transient-local writers get a subscription of their own.

A transient-local key keeps its subscription even once a batch covers its writer (a latched sample is put
once, at its writer's start: a batch sent before the recorder listened is gone, the cache is not; a
batching token seen after the writer's own once dropped it, and the bag had no ``/tf_static``), and its
cache is asked again until its sample came (:meth:`KeyRoutes.ask_again`): after ``LATCHED_RETRY_S``, then
twice as long each time, at most ``LATCHED_RETRY_MAX_S`` (an action's status is put only once a goal comes;
each ask declares a subscription, which cost the realtime recorder a tenth of its time at 1 s), unless
every writer of the key sends batches: its sample then comes in the batch as well, whenever it is put
(an action's status of hilsim's own services, asked every 30 s for a whole interactive run without goals).

Reads (liveliness): the batching services' tokens (``Keys.batch``: which nodes batch) and the ROS 2
graph's publisher tokens (``@ros2_lv/<domain>/…/MP/…``: who writes what, hilsim.core.provenance).
Writes: nothing; declares the key subscriptions and hands their samples to the recorder's callback.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext as zenoh_ext

from hilsim.core.keys import Keys
from hilsim.core.ros2 import wire

LATCHED_RETRY_S = 1.0  # wall seconds before the first ask again of a transient-local cache that gave nothing yet
LATCHED_RETRY_MAX_S = 30.0  # …doubling up to this
Node = tuple[str, str]  # (zid, node id) of a ROS 2 node (hilsim's services are nodes too)


class KeyRoutes:
    """The key subscriptions of one recorder (see the module docstring); thread-safe."""

    def __init__(self, keys: Keys, record: list[str], *, batching: bool) -> None:
        self.keys = keys
        self.batching = batching
        self.lock = threading.Lock()
        self.batching_nodes: set[Node] = set()  # the nodes that send batches
        self.plain: dict[str, dict[bytes, Node]] = {}  # key -> the nodes of its writers no batch covers
        self.key_subs: dict[str, list[Any]] = {}  # key -> its own subscription
        self.closed = False  # no subscription is declared once the recorder stops
        self._exprs = [zenoh.KeyExpr(keys.scoped(e)) for e in record]
        self._covers: dict[str, bool] = {}  # key -> whether logger.record covers it
        self._session: Any = None
        self._real: zenoh.Session | None = None
        self._zid = ""
        self._composed = False
        self._on_sample: Callable[[zenoh.Sample], None] = lambda sample: None
        self._on_twice: Callable[[str], None] = lambda key: None
        # transient-local keys: their subscription stays whoever else covers them (a batch sent before this
        # recorder listened is gone; the publisher's cache is not), asked again until a sample came
        self.latched: dict[str, float] = {}  # key -> when (monotonic) its cache was last asked
        self._wait: dict[str, float] = {}  # key -> seconds until its next ask (doubling)
        self.latched_got: set[str] = set()

    def start(self, session: Any, real: zenoh.Session | None, zid: str, *, composed: bool,
              on_sample: Callable[[zenoh.Sample], None], on_twice: Callable[[str], None]) -> list[Any]:
        """Follow the tokens on ``session`` (``real``: the Zenoh session behind it, for transient-local
        subscriptions; ``zid``: the recorder's own; ``composed``: this process's own services hand it
        their messages as objects). ``on_sample`` takes a key subscription's samples; ``on_twice(key)``
        says a key's samples may come two ways (without batches: ``**`` and a latched writer's cache).
        The liveliness subscribers, for the caller to undeclare; with batches the batching tokens
        first, with their history, so that at start-up the writers of those nodes are known as covered."""
        self._session, self._real, self._zid, self._composed = session, real, zid, composed
        self._on_sample, self._on_twice = on_sample, on_twice
        live = session.liveliness()
        subs = []
        if self.batching:
            subs.append(live.declare_subscriber(self.keys.all_batches, self._on_batch_token, history=True))
        subs.append(live.declare_subscriber(self.keys.all_writers, self._on_writer_token, history=True))
        return subs

    def covers(self, key: str) -> bool:
        """Whether ``logger.record`` covers ``key``."""
        got = self._covers.get(key)
        if got is None:
            try:
                ke = zenoh.KeyExpr(key)
                got = any(e.intersects(ke) for e in self._exprs)
            except zenoh.ZError:
                got = False
            self._covers[key] = got
        return got

    def close(self) -> list[Any]:
        """No subscription from here on; the key subscriptions, for the caller to undeclare."""
        with self.lock:
            self.closed = True
            subs = [d for ds in self.key_subs.values() for d in ds]
            self.key_subs.clear()
        return subs

    def plain_keys(self) -> set[str]:
        """The keys subscribed one by one for a writer no batch covers (with batches)."""
        with self.lock:
            return set(self.plain) if self.batching else set()

    def _on_batch_token(self, sample: zenoh.Sample) -> None:
        node = Keys.batch_node(str(sample.key_expr))
        if node is None:
            return
        with self.lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self.batching_nodes.discard(node)
                return
            self.batching_nodes.add(node)
            # its publishers seen before its token (a race): their keys need no subscription of ours
            # unless another writer does (the batch brings what the subscription did, duplicates dropped)
            for key, writers in list(self.plain.items()):
                if key in self.latched:
                    continue  # its batch may have gone out before we listened: the cache still has it
                for gid in [g for g, n in writers.items() if n == node]:
                    del writers[gid]
                if not writers:
                    del self.plain[key]
                    for d in self.key_subs.pop(key, []):
                        try:
                            d.undeclare()
                        except zenoh.ZError:
                            pass

    def _on_writer_token(self, sample: zenoh.Sample) -> None:
        key_expr = str(sample.key_expr)
        if "/MP/" not in key_expr:
            return
        try:
            tok = wire.parse_token(key_expr)
        except ValueError:
            return
        if tok.topic is None or tok.dds_type is None or tok.type_hash is None:
            return
        key = wire.topic_key(tok.domain, tok.topic, tok.dds_type, tok.type_hash)
        if sample.kind != zenoh.SampleKind.PUT or not self.covers(key):
            return  # a writer gone: its key's subscription stays (its last samples may be in flight)
        latched = tok.qos is not None and tok.qos.durability == wire.Durability.TRANSIENT_LOCAL
        if not self.batching and not latched:
            return  # `**` takes it
        node = (tok.zid, tok.node_id)
        if self._composed and tok.zid == self._zid and not latched:
            # composed: this process's own services, taken as message objects; but a latched sample is
            # Zenoh's (an advanced publisher, put in setup, maybe before this recorder existed): its cache
            return
        with self.lock:
            if self.closed or (node in self.batching_nodes and not latched):
                return
            self.plain.setdefault(key, {})[tok.gid] = node
            if latched:
                self.latched.setdefault(key, time.monotonic())
            if key not in self.key_subs:
                if not self.batching:
                    self._on_twice(key)
                self.key_subs[key] = [self._subscribe_key(key, latched)]

    def got(self, key: str) -> None:
        """A sample of ``key`` was taken in (any way): a transient-local key's cache need not be asked again."""
        if key in self.latched and key not in self.latched_got:
            with self.lock:
                self.latched_got.add(key)

    def missing_latched(self) -> list[str]:
        """Transient-local keys whose writer announced itself and whose sample has not come (yet)."""
        with self.lock:
            return sorted(k for k in self.latched if k not in self.latched_got)

    def ask_again(self, period: float = LATCHED_RETRY_S) -> list[str]:
        """Ask the cache of each transient-local key without a sample again (a new late-joiner subscription,
        the old one undeclared), first after ``period``, then twice as long each time; the keys asked. A
        late joiner's one query can cross the publisher's put (the put before our subscription reached it,
        the query before the put)."""
        now = time.monotonic()
        asked, old = [], []
        with self.lock:
            if self.closed:
                return []
            for key, at in self.latched.items():
                wait = self._wait.get(key, period)
                if key in self.latched_got or now - at < wait:
                    continue
                writers = self.plain.get(key, {})
                if writers and all(n in self.batching_nodes for n in writers.values()):
                    # every writer batches: a sample it puts comes in its batch too, whenever that is (one
                    # put before this recorder listened, its cache gave at the first subscription)
                    continue
                self.latched[key] = now
                self._wait[key] = min(2 * wait, max(period, LATCHED_RETRY_MAX_S))
                old.extend(self.key_subs.get(key, []))
                self.key_subs[key] = [self._subscribe_key(key, True)]
                asked.append(key)
        for d in old:
            try:
                d.undeclare()
            except zenoh.ZError:
                pass
        return asked

    def _subscribe_key(self, key: str, latched: bool) -> Any:
        if latched and self._real is not None:
            # transient-local, as rmw_zenoh subscribes: the publisher's cache gives what it sent before
            return zenoh_ext.declare_advanced_subscriber(
                self._real, key, self._on_sample, history=zenoh_ext.HistoryConfig(detect_late_publishers=True))
        return self._session.declare_subscriber(key, self._on_sample)
