"""Base of every hilsim service process: session, liveliness, health, checked I/O, lifecycle.

A service subclasses :class:`Service`, declares its inputs and outputs in :meth:`setup`
through :meth:`subscribe`, :meth:`publisher` and :meth:`queryable`, and either reacts to
messages (the default :meth:`loop` just waits) or overrides :meth:`loop`.

What the base does once for all:
- every payload is decoded and validated (:func:`hilsim.core.msgs.decode`); a bad one is
  rejected, counted per key, logged with its key, and the service keeps running;
- an exception in a handler is counted as an error and logged, never silently dropped; one in
  :meth:`loop`, or in the handler of a ``fatal`` subscription (the service's loop), is a fault
  that stops the service with exit code 1, so ``hilsim up`` ends the run non-zero;
- handlers run under one lock, so a service's state needs no further locking;
- health (``<prefix>/<robot>/health/<service>``, diagnostic_msgs/DiagnosticArray) is published
  once a second and at exit; warnings and errors also go to ``<prefix>/<robot>/log/<service>``;
- a liveliness token ``<prefix>/<robot>/alive/<service>`` is declared once inputs exist,
  which is how ``hilsim up`` knows the service is ready;
- when the run's recorder takes batches (``logger.batch``), every sample also goes into the
  service's batch, sent on ``<prefix>/batch/<domain>/<service>/<zid>/<node id>`` (:mod:`hilsim.core.batch`; its
  liveliness token of the same name is declared before any publisher), and is put on its own key
  only while a subscriber matches it; health then says per key how many were put (``put:<key>``);
- SIGINT / SIGTERM end :meth:`loop`; everything declared is undeclared and the session closed (the
  last batch sent first).
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import zenoh
from pydantic import BaseModel, ValidationError

from hilsim.core import batch, msgs, transport
from hilsim.core.config import ConfigError, Scenario, format_error
from hilsim.core.fleet import split_id
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.core.publisher import Publisher
from hilsim.core.registry import service_class
from hilsim.core.ros2_node import Ros2Node
from hilsim.core.scenario import robot_scenario
from hilsim.core.signals import on_stop_signals, watch_signals

T = TypeVar("T")
__all__ = ["LEVEL_ERROR", "LEVEL_OK", "LEVEL_WARN", "Publisher", "Service", "instantiate", "on_stop_signals",
           "setup_logging", "watch_signals"]
LEVEL_OK, LEVEL_WARN, LEVEL_ERROR = 0, 1, 2


class Service(Ros2Node):
    """One hilsim service process. Subclasses set ``name`` and implement :meth:`setup`.

    What the launcher and physics need to know of a service is declared here, by the class:
    ``stop_rank`` (``hilsim up`` stops services in ascending rank and starts them in the reverse
    order: physics first to stop, the recorder last), :meth:`lockstep_period` (whether and how
    often physics waits for it; announced at run time with a liveliness token, so physics needs
    no list of participants) and ``ack_via``. ``Config`` validates the service's own scenario
    section (a top-level field named like the service), available as ``self.cfg``.
    """

    name: ClassVar[str] = "service"
    stop_rank: ClassVar[int] = 50
    # the recorder: it takes the others' batches and never batches itself (logger.batch)
    records: ClassVar[bool] = False
    # how a lockstep participant acknowledges a step: "sync" (a Clock on sync/<name>) or a topic
    # it publishes exactly once per step anyway (the controller: joint_commands)
    ack_via: ClassVar[str] = "sync"
    Config: ClassVar[type[BaseModel] | None] = None

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        """Physics steps between this service's lockstep acknowledgements; None: not a participant."""
        return None

    @classmethod
    def lockstep_lag(cls, sc: Scenario) -> int:
        """Steps physics may run past a step this service owes before waiting for it (0: wait at
        that step). Only for a service whose output for step k takes effect at a later step it
        stamps itself (the planner's trajectories), so that waiting later changes nothing; or a
        controller whose command physics applies ``clock.controller_lag`` steps after the
        measurement it answers."""
        return sc.clock.controller_lag if cls.ack_via == "joint_commands" else 0

    @classmethod
    def resolve(cls, sc: Scenario) -> type[Service]:
        """The class that actually runs for this scenario (e.g. the controller by ``controller.type``)."""
        return cls

    def __init__(self, scenario: Scenario) -> None:
        self.sc = scenario
        self.cfg: Any = None
        if self.Config is not None:
            try:
                self.cfg = self.Config.model_validate(scenario.section(self.name))
            except ValidationError as e:
                raise ConfigError(format_error(scenario.source or "scenario", e, prefix=self.name)) from None
        self.keys = Keys.of(scenario)
        self.log = logging.getLogger(f"hilsim.{self.name}")
        self.lock = threading.RLock()
        self._health_lock = threading.Lock()
        self.stop_event = threading.Event()
        self.state = "starting"
        self.counts_in: Counter[str] = Counter()
        self.counts_out: Counter[str] = Counter()
        self.counts_replied: Counter[str] = Counter()  # answers to queries: not samples, never recorded
        self.rejected: Counter[str] = Counter()
        self.stale: Counter[str] = Counter()  # realtime: samples dropped as older than clock.max_age
        self.counts_put: Counter[str] = Counter()  # batching: samples also put on their own key, per key
        self.batcher: batch.Batcher | None = None  # the recorder takes batches (logger.batch)
        self.seq_gaps: Counter[str] = Counter()  # samples missing from a writer's sequence, per key
        self.provenance = Provenance()
        self.provenance.on_suspect = self._on_suspect
        self.errors = 0
        self.overruns = 0
        self.last_error = ""
        self.final = False  # the health about to be published is the last (at exit)
        # set with the final health: after it no log line goes out (its counts are the service's last word)
        self._final_lock = threading.Lock()
        self.failed: str | None = None  # the error that stopped it (fail, or loop raising)
        self.sim_ns = 0  # latest sim time this service knows of
        self.session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._health_pub: Publisher | None = None
        self._log_pub: Publisher | None = None
        self._sync_pub: Publisher | None = None
        self._zid = ""
        self._node_id = 0
        # robots as arrays (hilsim.core.fleet): a fleet driver in this process hands this robot its
        # per-step joint sample (the service does not subscribe it) and, if fleet_acked, also
        # acknowledges the lockstep steps for it
        self.fleet_driven = False
        self.fleet_acked = False

    # ------------------------------------------------------------------ to override
    def setup(self) -> None:
        """Declare subscribers, publishers and queryables."""

    def loop(self) -> None:
        """Run until :attr:`stop_event` is set. Reactive services keep this default."""
        while not self.stop_event.wait(0.2):
            pass

    def teardown(self) -> None:
        """Release what :meth:`setup` acquired beyond Zenoh declarations."""

    def health_values(self) -> dict[str, Any]:
        """Service-specific figures added to the health message."""
        return {}

    def _declare_node(self, session: Any) -> None:
        self.declare_node(session)
        if self._takes_batches(session):
            # before any publisher announces itself: the recorder learns this node batches first
            # (a race would only cost it a subscription it drops again, and duplicates it drops)
            key = self.keys.batch(self._zid, self._node_id, self.name)
            realtime = self.sc.clock.mode == "realtime"
            pub = transport.publisher(session, key, drop_when_congested=realtime)
            token = session.liveliness().declare_token(key)
            lc = self.sc.logger
            real = transport.zenoh_session(session)
            last_put = None
            if realtime and real is not None:
                def last_put(data: bytes) -> None:
                    real.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)
            self.batcher = batch.Batcher(pub, token, lc.batch, lc.batch_max_age_ms / 1000.0, last_put)
            self._declared.append(self.batcher)

    def _takes_batches(self, session: Any) -> bool:
        """Whether this service sends the recorder batches: the run has a recorder with ``logger.batch``
        on, this is not it, and it is not composed with it (hilsim.launch.compose: the recorder then
        takes this process's messages as objects); never on an in-process bus (no recorder there)."""
        lc = self.sc.logger
        if self.records or not (lc.enabled and lc.batch > 0 and "logger" in self.sc.services):
            return False
        if getattr(session, "recorder_inside", False):
            return False
        return transport.zenoh_session(session) is not None

    @property
    def zenoh_session(self) -> zenoh.Session | None:
        """The process's Zenoh session, also when composed; None on an in-process bus."""
        return transport.zenoh_session(self.session)

    # ------------------------------------------------------------------ declarations
    def publisher(self, key: str, *, latched: bool = False) -> Publisher:
        """A publisher of ``key``; ``latched``: transient-local (its last sample kept for late subscribers)."""
        assert self.session is not None
        p = Publisher(self, key, latched=latched)
        self._declared.append(p)
        return p

    def subscribe(
        self,
        key: str,
        cls: type[T],
        handler: Callable[[T, str], None],
        *,
        n_joints: int | None = None,
        with_attachment: bool = False,
        stream: bool = True,
        fatal: bool = False,
        locked: bool = True,
    ) -> None:
        """Call ``handler(msg, key)`` for every valid message on ``key`` (may be a key expression);
        with ``with_attachment``, ``handler(msg, key, attachment)`` (None if the sample has none).

        An exception in ``handler`` is a fault the service survives (counted, logged, published),
        unless ``fatal``: this subscription is the service's loop (its clock, e.g. the planner's
        decision ticks on ``joint_states``), which cannot go on without it, so the service stops
        with exit code 1 (:meth:`fail`), as when :meth:`loop` raises, and ``hilsim up`` ends the run.

        ``stream``: the key carries a stream (states, commands at a rate), where in realtime a
        sample older than ``clock.max_age`` is dropped because a newer one follows. ``False`` for
        a key whose samples are each an order given once (a trajectory): never dropped as stale,
        since nothing would replace it (a task would never start).

        ``locked``: the handler runs holding the service's lock (the default). ``False``: without it,
        for a handler that only hands the message over to the loop: Zenoh calls each subscription's
        handler on a thread of its own, so samples of two keys may be handled in another order than
        they were sent, and one that waits for the lock while another key's handler holds it (physics
        stepping on acknowledgements) can wait for hundreds of them."""
        assert self.session is not None

        realtime = self.sc.clock.mode == "realtime" and stream
        max_age_ns = round(self.sc.clock.max_age * 1e9) if realtime else 0

        def admit(k: str, att: transport.Attachment | None, payload: bytes | None = None) -> bool:
            self.counts_in[k] += 1
            why, gap = self.provenance.check(k, att, payload)
            if why is not None:
                return self.reject(k, why)
            if gap:
                self.seq_gaps[k] += gap
            if max_age_ns and att is not None and time.time_ns() - att.source_ns > max_age_ns:
                # realtime: a sample that waited too long in a queue (this process fell behind)
                # is dropped, so the loop works on fresh data and catches up instead of lagging more
                self.stale[k] += 1
                return False
            return True

        def on_sample(sample: zenoh.Sample) -> None:
            k = str(sample.key_expr)
            att = transport.read_attachment(sample)
            payload = sample.payload.to_bytes()
            if not admit(k, att, payload):
                return
            try:
                msg = msgs.decode(cls, payload, n_joints=n_joints)
            except msgs.BadMessage as e:
                self.reject(k, str(e))
                return
            handle(k, msg, att)

        def on_local(k: str, msg: Any, att: transport.Attachment) -> None:
            # composed: a message object from a service of this process, validated where it was made
            if admit(k, att):
                handle(k, msg, att)

        def handle(k: str, msg: Any, att: transport.Attachment | None) -> None:
            try:
                with self.lock if locked else contextlib.nullcontext():
                    if self.stop_event.is_set():
                        return  # stopping: the publishers may be going away
                    if with_attachment:
                        handler(msg, k, att)  # type: ignore[call-arg]
                    else:
                        handler(msg, k)
            except msgs.BadMessage as e:  # well-formed, but not usable here (e.g. an unknown joint)
                self.reject(k, str(e))
            except Exception as e:  # a bug or bad value must not kill the subscriber thread
                (self.fail if fatal else self.fault)(f"error handling {k}: {type(e).__name__}: {e}", exc=e)

        self._declared.append(self.session.declare_subscriber(key, on_sample))
        if "*" not in key:  # a concrete topic: a ROS 2 subscription, seen by `ros2 topic info`
            self._declared.append(self.session.liveliness().declare_token(self.graph_token("MS", key)))
        local = getattr(self.session, "local_subscriber", None)
        if local is not None:
            self._declared.append(local(key, on_local))

    def queryable(
        self,
        key: str,
        req_cls: type[T],
        handler: Callable[[T], Any],
        *,
        n_joints: int | None = None,
        reject: Callable[[str], Any] | None = None,
    ) -> None:
        """Answer requests on ``key``: ``handler(request) -> reply message``.

        A request that fails validation is answered with ``reject(reason)`` if given.
        """
        assert self.session is not None

        def on_query(query: zenoh.Query) -> None:
            k = str(query.key_expr)
            self.counts_in[k] += 1
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                req = msgs.decode(req_cls, payload, n_joints=n_joints)
            except msgs.BadMessage as e:
                self.rejected[k] += 1
                self.warn(f"rejected request on {k}: {e}")
                if reject is not None:
                    query.reply(k, msgs.encode(reject(str(e))))
                else:
                    query.reply_err(str(e))
                return
            try:
                with self.lock:
                    rep = handler(req)
                query.reply(k, msgs.encode(rep))
                self.counts_replied[k] += 1
            except Exception as e:
                self.fault(f"error answering {k}: {type(e).__name__}: {e}", exc=e)
                query.reply_err(f"{type(e).__name__}: {e}")

        self._declared.append(self.session.declare_queryable(key, on_query))

    def _on_suspect(self, key: str, why: str) -> None:
        """A sample that does not fit its writer's sequence (hilsim.core.provenance): delivered, counted in
        health (``suspect:<key>``); the first of each key said in the log."""
        if self.provenance.suspect[key] == 1:
            self.warn(f"suspect sample on {key}: {why} (delivered; further ones are counted)")

    def reject(self, key: str, reason: str) -> bool:
        """A sample that cannot be used: counted per key, logged with the key; returns False."""
        self.rejected[key] += 1
        self.warn(f"rejected payload on {key}: {reason}")
        return False

    # ------------------------------------------------------------------ lockstep
    @property
    def lockstep(self) -> bool:
        """True when physics waits for this service (at its :meth:`lockstep_period`)."""
        return (self.sc.clock.mode == "lockstep" and self.lockstep_period(self.sc) is not None
                and not self.fleet_acked)

    def ack_publisher(self) -> Publisher | None:
        """The publisher whose samples acknowledge steps (``ack_via``); the sync one by default."""
        return self._sync_pub

    def ack(self, step_ns: int) -> None:
        """Tell physics this service has delivered its output for the step at ``step_ns``."""
        if self._sync_pub is not None:
            self._sync_pub.put(msgs.Clock(clock=msgs.stamp(step_ns)))

    # ------------------------------------------------------------------ reporting
    def warn(self, text: str) -> None:
        self.log.warning(text)
        self._publish_log(30, text)

    def fault(self, text: str, exc: BaseException | None = None) -> None:
        """An error the service survives: counted, logged, published."""
        self.errors += 1
        self.last_error = text
        self.log.error(text, exc_info=exc if self.log.isEnabledFor(logging.DEBUG) else None)
        self._publish_log(40, text)

    def fail(self, text: str, exc: BaseException | None = None) -> None:
        """An error the service does not survive: a fault (counted, logged, published), then the
        service stops and exits with code 1, which ends the run under ``hilsim up``."""
        self.fault(text, exc)
        self.state = "fault"
        self.failed = text
        self.stop_event.set()

    def _publish_log(self, level: int, text: str) -> None:
        with self._final_lock:
            if self._log_pub is None or self.final:  # after the final health: in the process log only
                return
            try:
                self._log_pub.put(msgs.Log(stamp=msgs.stamp(self.sim_ns), level=level, name=self.name, msg=text))
            except zenoh.ZError:
                pass  # session closing: the text is in the process log already

    def health(self) -> msgs.DiagnosticArray:
        if self.state == "fault":
            level = LEVEL_ERROR
        else:
            level = LEVEL_WARN if self.errors or sum(self.rejected.values()) else LEVEL_OK
        values = {
            "state": self.state,
            "msgs_in": sum(self.counts_in.values()),
            "msgs_out": sum(self.counts_out.values()),
            "rejected": sum(self.rejected.values()),
            "errors": self.errors,
            "overruns": self.overruns,
            "stale_dropped": sum(self.stale.values()),
            "seq_gaps": sum(self.seq_gaps.values()),
            "suspect": sum(self.provenance.suspect.values()),
            "last_error": self.last_error,
            **({"final": "1"} if self.final else {}),
        }
        values.update(self.health_values())
        values.update({f"rejected:{k}": v for k, v in self.rejected.items()})
        values.update({f"stale:{k}": v for k, v in self.stale.items()})
        values.update({f"seq_gaps:{k}": v for k, v in self.seq_gaps.items()})
        values.update({f"suspect:{k}": v for k, v in self.provenance.suspect.items()})
        # per key, how many samples this service has sent: what a recorder can be checked against
        values.update({f"published:{k}": v for k, v in self.counts_out.items()})
        values.update({f"replied:{k}": v for k, v in self.counts_replied.items()})
        if self.batcher is not None:  # batching: of those, how many also went out on the key itself
            values["batches"] = self.batcher.batches
            values["batched"] = self.batcher.samples
            values.update({f"put:{k}": self.counts_put[k] for k in self.counts_out})
        st = msgs.DiagnosticStatus(
            level=level,
            name=self.name,
            message=self.state,
            hardware_id=f"{self.sc.prefix}/{self.sc.robot}",
            values=[msgs.KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )
        return msgs.DiagnosticArray(header=msgs.header(self.sim_ns), status=[st])

    def publish_health(self) -> None:
        if self._health_pub is not None:
            # one at a time: the health thread and an immediate report (e.g. physics pausing) must
            # not number their samples alike or send them out of order (receivers drop those). Not
            # under self.lock: a Zenoh callback of this process may wait for it while holding what
            # the put needs (the recorder receives its own health)
            with self._health_lock:
                with self.lock:
                    h = self.health()
                    last = self.final
                # the last one is the service's last word (its end state and figures), never dropped on a
                # congested link: without it the panel saw a stopped service as dead (stop 47's CI)
                self._health_pub.put(h, never_drop=last)

    def _health_thread(self) -> None:
        while not self.stop_event.wait(1.0):
            try:
                self.publish_health()
            except zenoh.ZError:
                return

    # ------------------------------------------------------------------ lifecycle
    def request_stop(self, *_: Any) -> None:
        self.stop_event.set()

    def attach(self, session: Any) -> None:
        """Declare everything on ``session``: a Zenoh session, or an in-process
        :class:`hilsim.core.inproc.Bus` session (benchmarks, tests). The liveliness token comes last,
        so whoever sees it knows the inputs exist."""
        self.session = session
        self._declare_node(session)
        # before any input: who may write which key (history: the writers that exist already)
        self._declared.append(session.liveliness().declare_subscriber(
            self.keys.all_writers, self.provenance.on_token, history=True))
        # (DROP in realtime like every stream: a blocking put here slowed a realtime loop whose recorder
        # fell behind, test_logger_stall; the last health alone is never dropped: publish_health)
        self._health_pub = self.publisher(self.keys.health(self.name))
        self._log_pub = self.publisher(self.keys.log(self.name))
        if self.lockstep and self.ack_via == "sync":
            self._sync_pub = self.publisher(self.keys.sync(self.name))
        self.setup()
        if self.lockstep:
            # announce the role before the liveliness token: physics, which waits for every
            # service's token before step 0, then knows whom to wait for at each step
            period = self.lockstep_period(self.sc)
            ack = self.ack_publisher()
            if ack is None:
                raise RuntimeError(f"{self.name}: lockstep participant without an acknowledgement publisher")
            token = self.keys.lockstep(self.name, int(period or 1), self.lockstep_lag(self.sc), self.ack_via,
                                       ack.gid.hex())
            self._declared.append(session.liveliness().declare_token(token))
        self._declared.append(session.liveliness().declare_token(self.keys.alive(self.name)))
        if self.state == "starting":  # a fault said during setup (a bus found missing) stays said
            self.state = "running"

    def run(self) -> int:
        """Run the service until stopped; returns the process exit code."""
        if threading.current_thread() is threading.main_thread():
            on_stop_signals(self.request_stop)
        try:
            session = transport.open_session(self.sc.zenoh)
        except ConnectionError as e:
            self.log.error(str(e))
            return 2
        try:
            return self.serve(session)
        finally:
            session.close()

    def serve(self, session: Any) -> int:
        """Attach to ``session``, loop until stopped, undeclare everything; the session stays
        open (it may be shared: :mod:`hilsim.launch.compose`). Returns the exit code."""
        self.session = session
        rc = 0
        try:
            self.attach(session)
            self.log.info("ready")
            threading.Thread(target=self._health_thread, daemon=True, name="health").start()
            self.loop()
            if self.failed is not None:  # a fatal handler's error (fail): already reported
                rc = 1
            elif self.state == "running":
                self.state = "stopped"
        except ConfigError as e:
            # a bad scenario or model: one line, as everywhere else, not a traceback
            self.state = "fault"
            self.log.error("%s", e)
            rc = 2
        except ConnectionError as e:
            # a device or link it cannot do without (a CAN bus that does not open): the reason, one line
            self.state = "fault"
            self.log.error("stopped: %s", e)
            rc = 1
        except Exception as e:
            # a fault like any other (published: hilsim up shows it), and the end of the service
            self.state = "fault"
            self.log.exception("stopped by an error: %s", e)
            self.errors += 1
            self.last_error = self.failed = f"stopped by an error: {type(e).__name__}: {e}"
            self._publish_log(40, self.last_error)
            rc = 1
        finally:
            self.stop_event.set()
            with self.lock:
                pass  # a handler still running finishes; later ones see stop_event and return
            try:
                with self._final_lock:  # a log line being sent is counted in it; none is sent after
                    self.final = True  # its last word: hilsim up's summary takes its figures from it
                self.publish_health()
            except Exception:
                pass
            try:
                self.teardown()
            finally:
                if self.batcher is not None:
                    # the last batch (final health among it) before any publisher or token goes
                    try:
                        self.batcher.flush(last=True)
                    except Exception as e:
                        self.log.warning("last batch not sent: %s", e)
                for d in reversed(self._declared):
                    try:
                        d.undeclare()
                    except Exception:
                        pass
        return rc


def setup_logging(name: str, level: int = logging.INFO) -> None:
    who = f"{name:<10}"
    if "+" in name:  # composed (hilsim.launch.compose): each line says which of the services wrote it
        who = "%(service)-10s"
    logging.basicConfig(
        level=level,
        stream=sys.stderr,
        format=f"%(asctime)s {who} %(levelname)-7s %(message)s",
        datefmt="%H:%M:%S",
    )
    if "+" in name:
        def service_of(record: logging.LogRecord) -> bool:
            record.service = record.name.removeprefix("hilsim.")
            return True

        for h in logging.getLogger().handlers:
            h.addFilter(service_of)


def instantiate(name: str, sc: Scenario) -> Service:
    """The service instance ``name`` (``physics``, ``controller@arm3``) for scenario ``sc``."""
    svc, robot = split_id(name)
    rsc = robot_scenario(sc, robot) if robot else sc
    return service_class(svc, rsc)(rsc)  # type: ignore[no-any-return]
