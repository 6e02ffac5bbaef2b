"""The Zenoh watcher: what the panel subscribes to and the state it keeps of each robot
(:class:`Monitor`, one :class:`RobotView` per robot), made into the page's snapshot.

Reads (``<prefix>/<robot>/…``, any robot): the writers' liveliness tokens (who may write what,
:mod:`hilsim.core.provenance`), ``alive/*`` (liveliness), ``health/*``, ``log/*`` (faults: level
ERROR and above), ``<prefix>/clock``, ``controller/reference`` (setpoints), ``truth/odom`` (a rover's
pose), ``truth/joint_states`` (positions; the latest about 20 times a second, for the plot),
``planner/feedback``, ``planner/result``, ``navigator/feedback``, ``navigator/result``.
Samples are believed as every service believes them (on a key with an announced writer, only that
writer's; the others and the undecodable are counted in ``ignored``). Writes nothing.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import zenoh

from hilsim.core import msgs, run_finder, transport
from hilsim.core.geometry import yaw_of
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance
from hilsim.ui.jsonio import finite

PLOT_PERIOD = 0.05  # wall seconds between plot samples (the truth comes at 500-1000 Hz)
PLOT_POINTS = 240  # samples kept for the plot: 12 s at 20 Hz
RING = 64  # samples of a high-rate key Zenoh keeps between two reads (the latest of each robot among them)
# wall seconds a departed service's last words (its final health, physics' "done") have to arrive
# before its departure is judged: a service stopped at the run's end says "stopped" as it leaves
DEPARTURE_GRACE = 1.0
ENDED_STATES = ("stopped", "done")  # a service's last health state when it left because it was stopped


def _robot_of(key: str, prefix: str) -> str:
    """The robot of a data key ``<domain>/<robot>/…`` or of a liveliness token ``<prefix>/<robot>/…``
    (the default namespaces ``/<robot>``: hilsim.core.keys)."""
    return key.split("/", 2)[1]


@dataclass
class RobotView:
    """What the panel knows of one robot of the simulation."""

    alive: dict[str, bool] = field(default_factory=dict)
    health: dict[str, dict[str, Any]] = field(default_factory=dict)
    joints: list[str] = field(default_factory=list)
    position: list[float] = field(default_factory=list)
    ref_names: list[str] = field(default_factory=list)
    setpoint: list[float] = field(default_factory=list)
    history: deque[tuple[float, list[float], list[float]]] = field(default_factory=lambda: deque(maxlen=PLOT_POINTS))
    pose: tuple[float, float, float] | None = None  # a rover's truth: x, y, yaw
    goals: dict[str, dict[str, Any]] = field(default_factory=dict)


class Monitor:
    """Subscribes to the simulation's keys and keeps the latest of each (Zenoh callbacks; the
    high-rate keys through rings read by one thread)."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.session = session
        self.prefix = prefix
        k = Keys(prefix, "*", run_finder.tool_domain())
        self.lock = threading.Lock()
        self.robots: dict[str, RobotView] = {}
        self.sim_time: float | None = None
        self.clock_wall = 0.0
        self.faults: deque[dict[str, Any]] = deque(maxlen=50)
        self.expected: set[str] = set()  # the services of the panel's run while it runs (a departure is a fault)
        self.watch_departures = False
        self.prov = Provenance()
        self._prov_lock = threading.Lock()
        self.ignored = 0  # samples from writers other than the keys' announced ones, or undecodable
        self._subs: list[Any] = [
            # first: who writes what, so that only the services' own samples are believed
            session.liveliness().declare_subscriber(k.all_writers, self._on_writer, history=True),
            session.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True),
            session.declare_subscriber(k.health("*"), self._on_health),
            session.declare_subscriber(k.log("*"), self._on_log),
        ]
        # The keys written every step (up to 1 kHz) go into bounded rings inside Zenoh, read 20 times
        # a second by one thread: no Python call per sample (the panel would cost a busy loop a core's
        # tenth otherwise), and the plot gets the latest of each. The setpoint before the truth, so
        # each plot sample pairs a position with the setpoint in force.
        self._rings: list[tuple[Any, Any]] = [
            (session.declare_subscriber(key, zenoh.handlers.RingChannel(RING)), handle)
            for key, handle in ((k.clock, self._on_clock), (k.topic("controller/reference"), self._on_reference),
                                (k.truth("odom"), self._on_odom), (k.truth("joint_states"), self._on_truth))
        ]
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll, name="panel-poll", daemon=True)
        self._poller.start()
        for svc in ("planner", "navigator"):
            self._subs += [
                session.declare_subscriber(k.topic(f"{svc}/feedback"), self._feedback_cb(svc)),
                session.declare_subscriber(k.topic(f"{svc}/result"), self._result_cb(svc)),
            ]

    def robot(self, name: str) -> RobotView:
        """Under self.lock."""
        return self.robots.setdefault(name, RobotView())

    def fault(self, source: str, text: str) -> None:
        with self.lock:
            self.faults.append({"wall": time.time(), "source": source, "text": text})

    def _on_writer(self, sample: zenoh.Sample) -> None:
        with self._prov_lock:
            self.prov.on_token(sample)

    def _decode(self, sample: zenoh.Sample, cls: type) -> Any:
        """The message, if it comes from the key's announced writer (as every service judges it:
        :mod:`hilsim.core.provenance`) and decodes; else None, counted in ``ignored``."""
        with self._prov_lock:
            why, _ = self.prov.check(str(sample.key_expr), transport.read_attachment(sample))
            if why is not None:
                self.ignored += 1
                return None
        try:
            return msgs.decode(cls, sample.payload.to_bytes())
        except msgs.BadMessage:
            with self._prov_lock:
                self.ignored += 1
            return None  # a stranger's garbage on a key must not reach the page

    def _on_alive(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        svc = key.rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            rv = self.robot(_robot_of(key, self.prefix))
            was = rv.alive.get(svc, False)
            rv.alive[svc] = up
            departed = was and not up and self.watch_departures and svc in self.expected
        if departed:  # a service of the running run left: judged once its last health had time to come
            t = threading.Timer(DEPARTURE_GRACE, self._judge_departure, args=(_robot_of(key, self.prefix), svc))
            t.daemon = True
            t.start()

    def _judge_departure(self, robot: str, svc: str) -> None:
        """A fault if the service died: not back, the run not ending (the launcher's report clears
        ``watch_departures``; physics said ``done``), and its last health not ``stopped`` or ``done``
        (what a service says as it leaves when it is stopped)."""
        with self.lock:
            rv = self.robots.get(robot)
            if rv is None or rv.alive.get(svc, False) or not self.watch_departures:
                return
            last = rv.health.get(svc, {}).get("values", {}).get("state")
            done = any(r.health.get("physics", {}).get("values", {}).get("state") == "done"
                       for r in self.robots.values())
        if last in ENDED_STATES or done:
            return
        self.fault(svc, f"service {svc} is gone (its liveliness token disappeared)")

    def _on_health(self, sample: zenoh.Sample) -> None:
        h = self._decode(sample, msgs.DiagnosticArray)
        if h is None:
            return
        robot = _robot_of(str(sample.key_expr), self.prefix)
        new_faults = []
        with self.lock:
            rv = self.robot(robot)
            for st in h.status:
                vals = {kv.key: kv.value for kv in st.values}
                old = rv.health.get(st.name, {})
                if st.level >= 2 and old.get("level", 0) < 2:
                    new_faults.append((st.name, st.message or vals.get("last_error", "error")))
                rv.health[st.name] = {"level": int(st.level), "message": st.message, "values": vals,
                                      "wall": time.time()}
        for name, text in new_faults:
            self.fault(name, f"health: {text}")

    def _on_log(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.Log)
        if m is not None and m.level >= 40:
            self.fault(m.name, m.msg)

    def _poll(self) -> None:
        while not self._stop.wait(PLOT_PERIOD):
            for sub, handle in self._rings:
                latest: dict[str, zenoh.Sample] = {}  # per key: one robot's latest each
                try:
                    while (sample := sub.try_recv()) is not None:
                        latest[str(sample.key_expr)] = sample
                except zenoh.ZError:  # undeclared while closing
                    return
                for sample in latest.values():
                    handle(sample)

    def _on_clock(self, sample: zenoh.Sample) -> None:
        c = self._decode(sample, msgs.Clock)
        if c is not None:
            with self.lock:
                self.sim_time = msgs.seconds(c.clock)
                self.clock_wall = time.monotonic()

    def _on_truth(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is None:
            return
        with self.lock:
            rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
            rv.joints, rv.position = list(m.name), list(m.position)
            ref = dict(zip(rv.ref_names, rv.setpoint, strict=False))
            sp = [ref.get(n, math.nan) for n in rv.joints]
            rv.history.append((msgs.seconds(m.header.stamp), rv.position, sp))

    def _on_reference(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample, msgs.JointState)
        if m is not None:
            with self.lock:
                rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
                rv.ref_names, rv.setpoint = list(m.name), list(m.position)

    def _on_odom(self, sample: zenoh.Sample) -> None:
        o = self._decode(sample, msgs.Odometry)
        if o is not None:
            p, yaw = o.pose.pose.position, yaw_of(o.pose.pose.orientation)
            with self.lock:
                rv = self.robot(_robot_of(str(sample.key_expr), self.prefix))
                rv.pose = (p.x, p.y, yaw)

    def _goal(self, rv: RobotView, gid: str, service: str) -> dict[str, Any]:
        g = rv.goals.get(gid)
        if g is None:
            g = rv.goals[gid] = {"id": gid, "service": service, "state": "sent", "progress": 0.0,
                                 "done": False, "success": None, "message": "", "error": [], "wall": time.time(),
                                 "planner": "", "choice": ""}
            while len(rv.goals) > 12:  # the oldest go first (dicts keep insertion order)
                rv.goals.pop(next(iter(rv.goals)))
        return g

    def _feedback_cb(self, service: str) -> Any:
        def on(sample: zenoh.Sample) -> None:
            fb = self._decode(sample, msgs.MoveFeedback)
            if fb is None:
                return
            with self.lock:
                g = self._goal(self.robot(_robot_of(str(sample.key_expr), self.prefix)), fb.goal_id, service)
                if not g["done"]:
                    g.update(state=fb.state, progress=fb.progress, sim=msgs.seconds(fb.header.stamp))
                    if fb.planner:  # planner: auto says what it picked and why once it has chosen
                        g.update(planner=fb.planner, choice=fb.choice or g["choice"])
        return on

    def _result_cb(self, service: str) -> Any:
        def on(sample: zenoh.Sample) -> None:
            r = self._decode(sample, msgs.MoveResult)
            if r is None:
                return
            with self.lock:
                g = self._goal(self.robot(_robot_of(str(sample.key_expr), self.prefix)), r.goal_id, service)
                state = "reached" if r.success else "canceled" if "cancel" in r.message.lower() else "failed"
                g.update(planner=r.planner or g["planner"], choice=r.choice or g["choice"])
                g.update(state=state, done=True, success=r.success, message=r.message,
                         error=list(r.execution_error), progress=1.0 if r.success else g["progress"],
                         sim=msgs.seconds(r.header.stamp))
        return on

    def note_goal(self, robot: str, gid: str, service: str) -> None:
        with self.lock:
            self._goal(self.robot(robot), gid, service)

    def gains(self, robot: str) -> dict[str, dict[str, float]]:
        """The gains in force, from the controller's health (``gains:<joint>`` = ``kp=… ki=…``)."""
        with self.lock:
            vals = self.robot(robot).health.get("controller", {}).get("values", {})
        out: dict[str, dict[str, float]] = {}
        for k, v in vals.items():
            if k.startswith("gains:"):
                g = {}
                for item in v.split():
                    name, _, num = item.partition("=")
                    with contextlib.suppress(ValueError):
                        g[name] = float(num)
                out[k[6:]] = g
        return out

    def snapshot(self, robot: str) -> dict[str, Any]:
        with self.lock:
            rv = self.robot(robot)
            now = time.time()
            services = []
            for name in sorted(set(rv.alive) | set(rv.health)):
                h = rv.health.get(name, {})
                vals = h.get("values", {})
                services.append({
                    "name": name, "alive": rv.alive.get(name, False), "level": h.get("level"),
                    "state": vals.get("state", ""), "message": h.get("message", ""),
                    "age": round(now - h["wall"], 1) if h else None,
                    "errors": vals.get("errors", ""), "last_error": vals.get("last_error", ""),
                })
            ph = rv.health.get("physics", {}).get("values", {})
            hist = list(rv.history)
            snap = {
                "robot": robot,
                "sim_time": self.sim_time,
                "clock_age": round(time.monotonic() - self.clock_wall, 1) if self.clock_wall else None,
                "rtf": ph.get("real_time_factor"),
                "paused_for": ph.get("paused_for", ""),
                # realtime: steps physics finished after their deadline (a loaded machine)
                "overruns": ph.get("overruns"),
                "services": services,
                "joints": {"names": rv.joints, "position": rv.position,
                           "setpoint": [dict(zip(rv.ref_names, rv.setpoint, strict=False)).get(n) for n in rv.joints]},
                "history": {"t": [h[0] for h in hist], "pos": [h[1] for h in hist], "ref": [h[2] for h in hist]},
                "pose": rv.pose,
                "goals": list(reversed(rv.goals.values())),
                "faults": list(reversed(self.faults))[:20],
                "ignored": self.ignored,
            }
        snap["gains"] = self.gains(robot)
        return finite(snap)

    def close(self) -> None:
        self._stop.set()
        self._poller.join(2)
        for s in [*self._subs, *(sub for sub, _ in self._rings)]:
            with contextlib.suppress(Exception):
                s.undeclare()
