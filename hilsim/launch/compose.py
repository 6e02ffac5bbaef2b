"""Composition: several services in one process, like ROS 2 components in a container.

``hilsim up arm --compose physics,sensors,controller`` (or ``compose: [[physics, sensors,
controller]]`` in the scenario) runs those services as threads of one process,
``hilsim run physics+sensors+controller``. Each keeps its own code, lock, health and
liveliness; what changes is the session they share, a :class:`ComposedSession`:

- a sample published in the process is handed to the subscribers *in the process* as the
  message object itself: no CDR encoding or decoding, no Zenoh hop. One dispatcher thread
  delivers them in publication order, so a lockstep step (physics → sensors → controller →
  physics) is a plain loop and stays deterministic;
- every key is still published on Zenoh for the processes outside (recorder, planner, tools,
  bridges), encoded only while some subscriber outside exists, and what comes from outside
  arrives as before. Keys, messages, attachments and writer announcements are unchanged, so
  nothing outside can tell a composed run from a distributed one.

Local samples carry the same attachment as remote ones and go through the same provenance,
staleness and counting path (:meth:`hilsim.core.service.Service.subscribe`). A delivered message
object is shared by every local subscriber: handlers read it and must not modify it.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from hilsim.core import transport
from hilsim.core.inproc import key_matches

log = logging.getLogger("hilsim.launch.compose")

# (service name, ...): a process name joins its services' names with "+"
SEP = "+"
LocalHandler = Callable[[str, Any, transport.Attachment], None]


def process_name(group: list[str]) -> str:
    return SEP.join(group)


def members(process: str) -> list[str]:
    return process.split(SEP)


class _LocalPublisher:
    """A Zenoh publisher limited to remote subscribers, plus delivery to the local ones."""

    def __init__(self, cs: ComposedSession, key: str, pub: zenoh.Publisher) -> None:
        self.cs, self.key, self.pub = cs, key, pub
        # encode for Zenoh only while a subscriber outside the process exists (e.g. no recorder:
        # physics' truth/imu goes to the sensors in the process and nowhere else)
        self.remote = True
        try:
            self.remote = pub.matching_status.matching
            self._listener = pub.declare_matching_listener(self._on_matching)
        except (AttributeError, zenoh.ZError):  # an older binding: always send
            self._listener = None

    def _on_matching(self, status: Any) -> None:
        self.remote = bool(status.matching)

    def deliver(self, msg: Any, att: transport.Attachment) -> None:
        self.cs.deliver(self.key, msg, att)

    def put(self, payload: Any, attachment: bytes | None = None) -> None:
        self.pub.put(payload, attachment=attachment)

    def undeclare(self) -> None:
        if self._listener is not None:
            try:
                self._listener.undeclare()
            except zenoh.ZError:
                pass
        self.pub.undeclare()


class ComposedSession:
    """What :class:`hilsim.core.service.Service` needs of a session, shared by the services of one
    process: Zenoh for the outside, direct delivery inside (see the module docstring)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._subs: list[tuple[str, LocalHandler]] = []
        self._routes: dict[str, list[LocalHandler]] = {}
        self._queue: queue.SimpleQueue[tuple[str, Any, transport.Attachment] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.delivered = 0
        # the recorder is one of this process's services: the others then send it no batches
        # (logger.batch), it takes their messages as objects
        self.recorder_inside = False
        self._thread = threading.Thread(target=self._dispatch, daemon=True, name="compose-dispatch")
        self._thread.start()

    # -------------------------------------------------------------- what Service declares
    def declare_publisher(self, key: str, **kw: Any) -> _LocalPublisher:
        pub = self.session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE, **kw)
        return _LocalPublisher(self, key, pub)

    def declare_subscriber(self, key: str, handler: Any, **kw: Any) -> Any:
        """From outside only: samples published in the process come through :meth:`local_subscriber`."""
        return self.session.declare_subscriber(key, handler, allowed_origin=zenoh.Locality.REMOTE, **kw)

    def local_subscriber(self, key: str, handler: LocalHandler) -> Any:
        entry = (key, handler)
        with self._lock:
            self._subs.append(entry)
            self._routes.clear()

        class _Decl:
            def undeclare(_self) -> None:  # _self: the closure needs this session as self
                with self._lock:
                    if entry in self._subs:
                        self._subs.remove(entry)
                    self._routes.clear()

        return _Decl()

    def has_local(self, key: str) -> bool:
        """Whether a subscriber in the process receives ``key`` (what a publisher may skip on)."""
        cbs = self._routes.get(key)
        if cbs is None:
            with self._lock:
                cbs = self._routes[key] = [h for expr, h in self._subs if key_matches(expr, key)]
        return bool(cbs)

    def __getattr__(self, name: str) -> Any:
        # liveliness, queryables, get, ...: the real session's, unchanged
        return getattr(self.session, name)

    # -------------------------------------------------------------- delivery
    def deliver(self, key: str, msg: Any, att: transport.Attachment) -> None:
        self._queue.put((key, msg, att))

    def _dispatch(self) -> None:
        q = self._queue
        while True:
            item = q.get()
            if item is None:
                return
            key, msg, att = item
            cbs = self._routes.get(key)
            if cbs is None:
                with self._lock:
                    cbs = self._routes[key] = [h for expr, h in self._subs if key_matches(expr, key)]
            for cb in cbs:
                cb(key, msg, att)
                self.delivered += 1

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=5.0)
        self.session.close()


def fleet_drivers(sc: Any, names: list[str], services: list[Any]) -> list[Any]:
    """Robots as arrays (``fleet.arrays``, :mod:`hilsim.core.fleet`): for each kind this process serves
    for *every* robot (``sensors@*``, ``controller@*``) and whose class offers one, the fleet driver
    that steps them all; its robots' services leave their per-step path to it (``fleet_driven``)."""
    from hilsim.core import fleet
    from hilsim.core.scenario import fleet_arrays

    if not fleet_arrays(sc):
        return []
    out = []
    for kind in fleet.ARRAY_KINDS:
        group = [s for n, s in zip(names, services, strict=True) if fleet.split_id(n)[0] == kind]
        if len(group) != sc.robots:  # some robots' services run elsewhere: each keeps its own path
            continue
        offer = getattr(type(group[0]), "array_driver", None)
        driver = offer(sc) if offer is not None else None
        if driver is None:
            continue
        for s in group:
            s.fleet_driven = True
            s.fleet_acked = getattr(driver, "acks_for_robots", True)
        out.append(driver(sc, group))
    return out


def run(names: list[str], sc: Any) -> int:
    """``hilsim run a+b+c``: the services ``names`` in this process; returns the exit code."""
    from hilsim.core.service import instantiate, on_stop_signals

    # names: services, or with robots > 1 robots' services (controller@arm3: hilsim.core.fleet)
    services = [instantiate(n, sc) for n in names]
    services += fleet_drivers(sc, names, services)
    # start as the launcher does (the reverse of stop_rank: physics last, once the others listen)
    order = sorted(services, key=lambda s: -s.stop_rank)
    stop = threading.Event()
    on_stop_signals(stop.set)  # not stop.set in a signal handler: it may deadlock (see there)
    try:
        real = transport.open_session(sc.zenoh)
    except ConnectionError as e:
        log.error("%s", e)
        return 2
    cs = ComposedSession(real)
    cs.recorder_inside = any(getattr(s, "records", False) for s in services)
    rcs: dict[str, int] = {}
    threads: list[threading.Thread] = []
    for s in order:
        def serve(s: Any = s) -> None:
            rcs[s.name] = s.serve(cs)
            stop.set()  # one service ending (done, or an error) ends the process, as it would alone

        t = threading.Thread(target=serve, name=s.name, daemon=True)
        t.start()
        threads.append(t)
        # the next one starts once this one has declared its inputs (or has already ended)
        while s.state == "starting" and t.is_alive() and not stop.is_set():
            t.join(0.01)
    while not stop.wait(0.2):
        pass
    # the recorder last, once the others have ended: their final health and last samples are handed to it
    # before it drains (asked together, it stopped before the controller's final health, which the bag lacked)
    by_name = {s.name: t for s, t in zip(order, threads, strict=True)}
    ranked = sorted(services, key=lambda s: s.stop_rank)
    recorders = [s for s in ranked if getattr(s, "records", False)]
    for group in ([s for s in ranked if s not in recorders], recorders):
        for s in group:
            s.request_stop()
        for s in group:
            by_name[s.name].join(timeout=10.0)
    cs.close()
    return max(rcs.values(), default=0)
