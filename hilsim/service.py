"""Base of every hilsim service process: session, liveliness, health, checked I/O, lifecycle.

A service subclasses :class:`Service`, declares its inputs and outputs in :meth:`setup`
through :meth:`subscribe`, :meth:`publisher` and :meth:`queryable`, and either reacts to
messages (the default :meth:`loop` just waits) or overrides :meth:`loop`.

What the base does once for all:
- every payload is decoded and validated (:func:`hilsim.msgs.decode`); a bad one is
  rejected, counted per key, logged with its key, and the service keeps running;
- an exception in a handler is counted as an error and logged, never silently dropped;
- handlers run under one lock, so a service's state needs no further locking;
- health (``<prefix>/<robot>/health/<service>``, diagnostic_msgs/DiagnosticArray) is published
  once a second and at exit; warnings and errors also go to ``<prefix>/<robot>/log/<service>``;
- a liveliness token ``<prefix>/<robot>/alive/<service>`` is declared once inputs exist,
  which is how ``hilsim up`` knows the service is ready;
- SIGINT / SIGTERM end :meth:`loop`; everything declared is undeclared and the session closed.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import zenoh

from hilsim import msgs, transport
from hilsim.config import ConfigError, Scenario
from hilsim.keys import Keys

T = TypeVar("T")
LEVEL_OK, LEVEL_WARN, LEVEL_ERROR = 0, 1, 2


class Publisher:
    """Encodes, sends and counts messages on one key."""

    def __init__(self, service: Service, key: str) -> None:
        self.key = key
        self._svc = service
        # realtime: a subscriber that cannot keep up loses samples rather than delaying us
        self._pub = transport.publisher(service.session, key, drop_when_congested=service.sc.clock.mode == "realtime")
        self.gid = transport.new_gid()
        self.seq = 0

    def put(self, msg: Any) -> None:
        self.seq += 1
        self._pub.put(msgs.encode(msg), attachment=transport.attachment_bytes(self.seq, self.gid))
        self._svc.counts_out[self.key] += 1

    def undeclare(self) -> None:
        self._pub.undeclare()


class Service:
    """One hilsim service process. Subclasses set ``name`` and implement :meth:`setup`."""

    name: ClassVar[str] = "service"

    def __init__(self, scenario: Scenario) -> None:
        self.sc = scenario
        self.keys = Keys(scenario.prefix, scenario.robot)
        self.log = logging.getLogger(f"hilsim.{self.name}")
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.state = "starting"
        self.counts_in: Counter[str] = Counter()
        self.counts_out: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.errors = 0
        self.overruns = 0
        self.last_error = ""
        self.sim_ns = 0  # latest sim time this service knows of
        self.session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._health_pub: Publisher | None = None
        self._log_pub: Publisher | None = None
        self._sync_pub: Publisher | None = None

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

    # ------------------------------------------------------------------ declarations
    def publisher(self, key: str) -> Publisher:
        assert self.session is not None
        p = Publisher(self, key)
        self._declared.append(p)
        return p

    def subscribe(
        self,
        key: str,
        cls: type[T],
        handler: Callable[[T, str], None],
        *,
        n_joints: int | None = None,
    ) -> None:
        """Call ``handler(msg, key)`` for every valid message on ``key`` (may be a key expression)."""
        assert self.session is not None

        def on_sample(sample: zenoh.Sample) -> None:
            k = str(sample.key_expr)
            self.counts_in[k] += 1
            try:
                msg = msgs.decode(cls, sample.payload.to_bytes(), n_joints=n_joints)
            except msgs.BadMessage as e:
                self.rejected[k] += 1
                self.warn(f"rejected payload on {k}: {e}")
                return
            try:
                with self.lock:
                    handler(msg, k)
            except Exception as e:  # a bug or bad value must not kill the subscriber thread
                self.fault(f"error handling {k}: {type(e).__name__}: {e}", exc=e)

        self._declared.append(self.session.declare_subscriber(key, on_sample))

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
                self.counts_out[k] += 1
            except Exception as e:
                self.fault(f"error answering {k}: {type(e).__name__}: {e}", exc=e)
                query.reply_err(f"{type(e).__name__}: {e}")

        self._declared.append(self.session.declare_queryable(key, on_query))

    # ------------------------------------------------------------------ lockstep
    @property
    def lockstep(self) -> bool:
        """True when physics waits for this service at every step."""
        return self.sc.clock.mode == "lockstep" and self.name in self.sc.lockstep_participants()

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

    def _publish_log(self, level: int, text: str) -> None:
        if self._log_pub is not None:
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
            "last_error": self.last_error,
        }
        values.update(self.health_values())
        values.update({f"rejected:{k}": v for k, v in self.rejected.items()})
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
            with self.lock:
                h = self.health()
            self._health_pub.put(h)

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
        :class:`hilsim.inproc.Bus` session (benchmarks, tests). The liveliness token comes last,
        so whoever sees it knows the inputs exist."""
        self.session = session
        self._health_pub = self.publisher(self.keys.health(self.name))
        self._log_pub = self.publisher(self.keys.log(self.name))
        if self.lockstep:
            self._sync_pub = self.publisher(self.keys.sync(self.name))
        self.setup()
        self._declared.append(session.liveliness().declare_token(self.keys.alive(self.name)))
        self.state = "running"

    def run(self) -> int:
        """Run the service until stopped; returns the process exit code."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self.request_stop)
            signal.signal(signal.SIGTERM, self.request_stop)
        try:
            self.session = transport.open_session(self.sc.zenoh)
        except ConnectionError as e:
            self.log.error(str(e))
            return 2
        rc = 0
        try:
            self.attach(self.session)
            self.log.info("ready")
            threading.Thread(target=self._health_thread, daemon=True, name="health").start()
            self.loop()
            if self.state == "running":
                self.state = "stopped"
        except ConfigError as e:
            # a bad scenario or model: one line, as everywhere else, not a traceback
            self.state = "fault"
            self.log.error("%s", e)
            rc = 2
        except Exception as e:
            self.state = "fault"
            self.log.exception("stopped by an error: %s", e)
            rc = 1
        finally:
            self.stop_event.set()
            try:
                self.publish_health()
            except Exception:
                pass
            try:
                self.teardown()
            finally:
                for d in reversed(self._declared):
                    try:
                        d.undeclare()
                    except Exception:
                        pass
                self.session.close()
        return rc


def setup_logging(name: str, level: int = logging.INFO) -> None:
    logging.basicConfig(
        level=level,
        stream=sys.stderr,
        format=f"%(asctime)s {name:<10} %(levelname)-7s %(message)s",
        datefmt="%H:%M:%S",
    )
