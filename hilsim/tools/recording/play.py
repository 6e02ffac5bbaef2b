"""``hilsim play BAG``: publish a recorded bag's samples again, on their original keys, in sim time.

    hilsim play runs/<run>[/bag] [--rate R] [--keys PATTERN[,PATTERN…]] [--loop] [--clock] [--delay S]

- Keys: each channel's ``hilsim_key`` (the Zenoh key it was recorded from), else the rmw_zenoh key
  rebuilt from its topic and type (:func:`hilsim.core.ros2.wire.topic_key`, domain 0); ``--domain D``
  moves every key to ROS domain D (default: the recorded one).
- Order and pace: sim-time order, ties in the order the recorder received them, paced by the stamps
  at ``--rate`` (1: as fast as the recorded sim time went; 0: as fast as possible). A sample's sim
  time is its publish time (its stamp), except for a sample whose stamp does not say when it was
  sent: a type without a stamp (``cmd_vel``) and a ``JointTrajectory``, whose ``header.stamp`` is
  when it is to start (ROS convention; hilsim's planner stamps it ahead), take the latest stamp
  the recorder had received before them. So a trajectory reaches its controller as many steps
  before its start as it did in the run: played at its start stamp instead, it raced the joint
  states of that step (another key, another publisher: Zenoh keeps no order between them) and
  lost, by up to 10 steps, in one play of three at ``--rate 1``. A trajectory is played no later
  than ``TRAJECTORY_LEAD_NS`` before its start, the lead hilsim's planner gives it: a recorder on
  a busy machine received one after the joint states of its start step (its controller had it in
  time), and a play in that order gave other commands from that step on.
- A writer of its own, as a ROS 2 node would be: node ``hilsim_play`` in the graph (``NN`` token), one
  publisher per key with its ``MP`` token and the gid derived from it (rmw_zenoh's rule), rmw_zenoh
  attachments with its own sequence numbers from 1, so receivers' provenance checks
  (:mod:`hilsim.core.provenance`) take it for what it is; the recorded writers' gids and numbers stay in
  the bag (each message's metadata), never on the wire. It connects with the tools' identity of the run
  (docs/security.md), which may write only what a person commands and what no service of the run writes.
- Which run: the first line names the run it joined (directory, scenario, router endpoint;
  :func:`hilsim.core.run_finder.tool_target`: ``--run DIR``, ``--connect``, else the one run of yours that
  is up; several: asked, never guessed). Refused, in one line, before anything is played: a key a
  service of that run writes (named, with the way to do it on purpose: a run without that service), a
  key its tools may not write, and, unless the target was named (``--run``/``--connect``), a key other
  publishers of that run write. Nothing answering there is an error, not an empty success.
- While playing: a key nobody subscribes to is said (its samples reach nobody); the summary counts what
  was played (messages, keys, the sim time from the first played to the last played, also after an
  early stop).
- ``--clock``: the recorded ``/clock`` is not played; the player publishes its own ``/clock`` at each
  new stamp, before the samples of that stamp.
- ``--keys``: ROS 2 topic globs (``/arm/joint_states``, ``/arm/*``) or Zenoh key expressions
  (``0/arm/**``), comma-separated; a sample is played if any of them matches.
- ``--delay``: seconds between announcing the publishers and the first sample, so that subscribers'
  routes exist (a sample put before Zenoh knows a subscriber reaches nobody).

A progress line on standard error while playing; a missing or unreadable bag is one line and exit
code 1. Reads the bag whole into memory first.
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh

from hilsim.core import msgs, run_finder, transport
from hilsim.core.keys import Keys
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire
from hilsim.record.bag import BagError, offered_qos, stamp_offset
from hilsim.record.bag_read import Bag, BagMessage, open_bag

NODE = "hilsim_play"
# types whose header.stamp says when they take effect, not when they were sent
STARTS_AT_STAMP = frozenset({"trajectory_msgs/msg/JointTrajectory"})
# a trajectory is played at least this long (sim) before its start: the lead hilsim's planner sends it
# with (services/planner_worker.py, START_DELAY_NS)
TRAJECTORY_LEAD_NS = 20_000_000


@dataclass
class Item:
    sim_ns: int
    key: str
    topic: str
    data: bytes


def key_of(m: BagMessage, domain: int | None) -> str:
    """The Zenoh key to play a message on (see the module docstring)."""
    key = m.key
    if not key:
        if m.type == "unknown" or not ros2types.is_known(m.type):
            raise BagError(f"{m.topic}: no hilsim_key and an unknown type {m.type!r}: cannot build its key")
        key = wire.topic_key(0, m.topic, wire.dds_type_name(m.type), ros2types.type_hash(m.type))
    if domain is not None:
        key = f"{int(domain)}/{key.split('/', 1)[1]}"
    return key


class Selector:
    """``--keys``: ROS 2 topic globs and Zenoh key expressions."""

    def __init__(self, text: str | None) -> None:
        parts = [p.strip() for p in (text or "").split(",") if p.strip()]
        self.globs = [p for p in parts if p.startswith("/")]
        self.exprs = [zenoh.KeyExpr.autocanonize(p) for p in parts if not p.startswith("/")]
        self.all = not parts

    def __call__(self, topic: str, key: str) -> bool:
        if self.all:
            return True
        if any(fnmatch.fnmatchcase(topic, g) for g in self.globs):
            return True
        return any(e.intersects(zenoh.KeyExpr(key)) for e in self.exprs)


def schedule(bag: Bag, select: Selector, domain: int | None, skip_clock: bool) -> list[Item]:
    """The messages to play, in sim-time order (see the module docstring)."""
    out: list[tuple[int, int, Item]] = []
    latest = 0
    stamped: dict[str, bool] = {}
    for i, m in enumerate(bag.messages()):
        if m.encoding != "cdr":  # a JSON channel of hilsim export: no key to play it on
            continue
        s = stamped.get(m.type)
        if s is None:
            s = stamped[m.type] = stamp_offset(m.type) >= 0 and m.type not in STARTS_AT_STAMP
        if s:
            latest = max(latest, m.pub_ns)
            t = m.pub_ns
        else:
            t = latest
            if m.type in STARTS_AT_STAMP and m.pub_ns:  # stamp 0: "now", nothing to go by
                t = min(t, max(m.pub_ns - TRAJECTORY_LEAD_NS, 0))
        if skip_clock and m.topic == "/clock":
            continue
        key = key_of(m, domain)
        if select(m.topic, key):
            out.append((t, i, Item(t, key, m.topic, m.data)))
    out.sort(key=lambda x: (x[0], x[1]))
    return [x[2] for x in out]


class Player:
    """The publishers of one play: a ROS 2 node with a publisher per key (graph tokens, gids, attachments)."""

    def __init__(self, session: zenoh.Session, domain: int) -> None:
        self.session = session
        self.domain = domain
        self.zid = str(session.info.zid())
        self._ids = iter(range(1, 1 << 30))
        self.node_id = next(self._ids)
        self._declared: list[Any] = [session.liveliness().declare_token(
            wire.node_token(domain, self.zid, self.node_id, "/", "/", NODE))]
        self.pubs: dict[str, tuple[Any, bytes, list[int]]] = {}  # key -> (publisher, gid, [seq])

    def publisher(self, key: str) -> tuple[Any, bytes, list[int]]:
        p = self.pubs.get(key)
        if p is None:
            parts = key.split("/")
            topic = "/" + "/".join(parts[1:-2])
            token = wire.entity_token("MP", int(parts[0]), self.zid, self.node_id, next(self._ids), "/", "/", NODE,
                                      topic, parts[-2], parts[-1], offered_qos(topic))
            self._declared.append(self.session.liveliness().declare_token(token))
            pub = transport.publisher(self.session, key)
            self._declared.append(pub)
            p = self.pubs[key] = (pub, wire.entity_gid(token), [0])
        return p

    def put(self, key: str, data: bytes) -> None:
        pub, gid, seq = self.publisher(key)
        seq[0] += 1
        pub.put(data, attachment=wire.encode_attachment(seq[0], time.time_ns(), gid))

    def close(self) -> None:
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except zenoh.ZError:
                pass


class Progress:
    def __init__(self, total: int, span: tuple[int, int], quiet: bool = False) -> None:
        self.total, self.span, self.quiet = total, span, quiet
        self.tty = sys.stderr.isatty()
        self.last = 0.0

    def show(self, n: int, sim_ns: int, loop: int, force: bool = False) -> None:
        now = time.monotonic()
        if self.quiet or (not force and now - self.last < (0.25 if self.tty else 1.0)):
            return
        self.last = now
        t0, t1 = self.span
        again = f" (loop {loop + 1})" if loop else ""
        text = (f"playing: sim {(sim_ns - t0) / 1e9:8.3f} / {(t1 - t0) / 1e9:.3f} s, "
                f"{n}/{self.total} messages{again}")
        sys.stderr.write(("\r" + text + "\033[K") if self.tty else text + "\n")
        sys.stderr.flush()

    def done(self) -> None:
        if self.tty and not self.quiet:
            sys.stderr.write("\n")


def play(session: zenoh.Session, items: list[Item], *, domain: int, rate: float = 1.0, loop: bool = False,
         clock: bool = False, delay: float = 0.5, quiet: bool = False,
         stop: threading.Event | None = None) -> dict[str, Any]:
    """Publish ``items`` (see :func:`schedule`); returns what was played. ``stop``: an Event that
    ends the play early (Ctrl-C, SIGTERM: :func:`cmd_play`; tests)."""
    stop = stop if stop is not None else threading.Event()  # never set: played to the end
    player = Player(session, domain)
    clock_key = Keys(domain=domain).clock if clock else ""
    keys = sorted({it.key for it in items})
    for k in keys:  # every publisher announced before the first sample
        player.publisher(k)
    if clock:
        player.publisher(clock_key)
    if delay > 0:
        stop.wait(delay)
    span = (items[0].sim_ns, items[-1].sim_ns) if items else (0, 0)
    deaf = sorted(k for k in keys if not _has_subscriber(player.pubs[k][0]))
    if deaf and not quiet:
        names = ", ".join(wire_topic(k) for k in deaf)
        print(f"hilsim play: warning: nobody subscribes to {names}: its samples reach nobody", file=sys.stderr,
              flush=True)
    prog = Progress(len(items), span, quiet)
    played = 0
    loops = 0
    played_keys: set[str] = set()
    first_ns = last_ns = None
    wall0 = time.monotonic()
    try:
        while True:
            t_start = time.monotonic()
            last_clock = -1
            for n, it in enumerate(items):
                if stop.is_set():
                    break
                if rate > 0:
                    wait = t_start + (it.sim_ns - span[0]) / 1e9 / rate - time.monotonic()
                    if wait > 0.0005:
                        stop.wait(wait)  # a stop ends the wait too
                if clock and it.sim_ns > last_clock:
                    player.put(clock_key, msgs.encode(msgs.Clock(clock=msgs.stamp(it.sim_ns))))
                    last_clock = it.sim_ns
                player.put(it.key, it.data)
                played += 1
                played_keys.add(it.key)
                if first_ns is None:
                    first_ns = it.sim_ns
                last_ns = it.sim_ns if loops == 0 else span[1]
                prog.show(n + 1, it.sim_ns, loops)
            else:
                prog.show(len(items), span[1], loops, force=True)
                loops += 1
                if loop and items and not stop.is_set():
                    continue
            break
    finally:
        prog.done()
        player.close()
    sim_s = ((last_ns - first_ns) / 1e9 if first_ns is not None and last_ns is not None else 0.0)
    return {"messages": played, "keys": len(played_keys), "loops": loops, "sim_s": sim_s,
            "wall_s": time.monotonic() - wall0, "deaf": deaf}


def _has_subscriber(pub: Any) -> bool:
    try:
        return bool(pub.matching_status.matching)
    except (AttributeError, zenoh.ZError):  # an in-process bus: no matching status to ask
        return True


def wire_topic(key: str) -> str:
    """A key as a person names it: its ROS 2 topic (``/arm/joint_states``), else the key."""
    parts = key.split("/")
    return "/" + "/".join(parts[1:-2]) if len(parts) >= 4 and parts[-1].startswith("RIHS") else key


def cmd_play(args: argparse.Namespace) -> int:
    if args.rate < 0:
        print("hilsim play: --rate must be 0 (as fast as possible) or more", file=sys.stderr)
        return 2
    try:
        bag = open_bag(args.bag)
        items = schedule(bag, Selector(args.keys), args.domain, skip_clock=args.clock)
    except BagError as e:
        print(f"hilsim play: {str(e).splitlines()[0]}", file=sys.stderr)
        return 1
    if not bag.complete:
        print(f"hilsim play: {args.bag}: incomplete (its recorder was killed?): playing the {bag.message_count} "
              f"messages that are whole; `hilsim bag recover {args.bag}` makes it whole", file=sys.stderr)
    if not items:
        print(f"hilsim play: {args.bag}: no message matches --keys {args.keys!r}", file=sys.stderr)
        return 1
    domain = args.domain if args.domain is not None else int(items[0].key.split("/", 1)[0])
    run = getattr(args, "run", None)
    target = run_finder.tool_target(args.connect, run, "hilsim play")
    if target.run is not None:
        print(f"hilsim play: {target.describe()}", file=sys.stderr, flush=True)
    where = ", ".join(target.zenoh.connect)
    try:
        session = transport.open_session(target.zenoh)
    except ConnectionError as e:
        print(run_finder.no_run_up("hilsim play", where) if target.run is None else f"hilsim play: {e}",
              file=sys.stderr)
        return 2
    try:
        if not transport.connected(session, 2.0):
            if target.run is None:
                print(run_finder.no_run_up("hilsim play", where) + ": nothing played", file=sys.stderr)
            else:
                print(f"hilsim play: nothing answers at {where} (the run's router is gone?): nothing played",
                      file=sys.stderr)
            return 2
        if target.run is None:
            print(f"hilsim play: {target.describe()}", file=sys.stderr, flush=True)
        keys = sorted({i.key for i in items} | ({Keys(domain=domain).clock} if args.clock else set()))
        explicit = bool(run or args.connect or os.environ.get("HILSIM_ZENOH_CONNECT"))
        refused = refusal(session, keys, domain, target.run, explicit)
        if refused:
            print(f"hilsim play: {refused}", file=sys.stderr)
            return 1
        pace = "as fast as possible" if args.rate == 0 else f"at {args.rate:g}x"
        print(f"hilsim play: {len(items)} messages on {len({i.key for i in items})} keys, {pace}"
              + (", publishing /clock" if args.clock else ""), file=sys.stderr)
        # Ctrl-C or SIGTERM ends the play between two messages: taken by a watcher thread, not as a
        # KeyboardInterrupt, which a put blocked by a slow subscriber would hold back (seen: a --loop
        # play that went on for 20 s after Ctrl-C), and which a script's background job never gets
        from hilsim.core.service import watch_signals

        signals: list[int] = []
        stop = threading.Event()

        def on_signal(signum: int) -> None:
            signals.append(signum)
            stop.set()

        restore = watch_signals(on_signal, (signal.SIGINT, signal.SIGTERM))
        try:
            res = play(session, items, domain=domain, rate=args.rate, loop=args.loop, clock=args.clock,
                       delay=args.delay, stop=stop)
        finally:
            restore()
    finally:
        session.close()
    of = f" of {len(items)}" if not args.loop and res["messages"] < len(items) else ""
    print(f"hilsim play: played {res['messages']}{of} messages on {res['keys']} keys, {res['sim_s']:.3f} s of sim "
          f"time in {res['wall_s']:.3f} s" + (f" (stopped by {signal.Signals(signals[0]).name})" if signals else ""),
          file=sys.stderr)
    return 128 + signals[0] if signals else 0


def live_publishers(session: zenoh.Session, domain: int) -> dict[str, set[str]]:
    """Who publishes what now, from the ROS 2 graph: data key -> the nodes (``/arm/sensors``) with a publisher."""
    out: dict[str, set[str]] = {}
    for reply in session.liveliness().get(wire.graph_key(domain), timeout=2.0):
        if reply.ok is None:
            continue
        try:
            tok = wire.parse_token(str(reply.ok.key_expr))
        except ValueError:
            continue
        if tok.kind == "MP" and tok.topic is not None and tok.dds_type is not None and tok.type_hash is not None:
            key = wire.topic_key(tok.domain, tok.topic, tok.dds_type, tok.type_hash)
            out.setdefault(key, set()).add(tok.fq_node_name)
    return out


def _run_scenario(ptr: run_finder.RunPointer | None) -> Any:
    """The resolved scenario of the run joined (its ``scenario.yaml``), or None if it cannot be read."""
    if ptr is None:
        return None
    from hilsim.core.config import ConfigError
    from hilsim.core.scenario import load_scenario

    try:
        return load_scenario(str(ptr.run_dir / "scenario.yaml"))
    except (ConfigError, OSError, ValueError):
        return None


def refusal(session: zenoh.Session, keys: list[str], domain: int, ptr: run_finder.RunPointer | None,
            explicit: bool) -> str | None:
    """Why these keys are not to be played into the run joined (one line), or None (module docstring)."""
    from hilsim.core import rights
    from hilsim.core.keys import relative_topic

    sc = _run_scenario(ptr)
    where = ptr.describe() if ptr is not None else "the run joined"
    live = live_publishers(session, domain)
    services = {s.replace("-", "_"): s for s in rights.running(sc)} if sc is not None else {}
    for key in keys:
        topic = wire_topic(key)
        nodes = sorted(live.get(key, ()))
        owned = [n for n in nodes if n.rsplit("/", 1)[-1] in services]
        if owned:
            svc = services.get(owned[0].rsplit("/", 1)[-1], owned[0].rsplit("/", 1)[-1])
            how = ""
            if sc is not None:
                rest = [s for s in sc.services if s != svc]
                how = f", e.g. hilsim up {sc.name} --set services=[{','.join(rest)}]"
            return (f"{topic} is written by {svc} ({owned[0]}) in {where}: a second writer would fight it; to play "
                    f"it on purpose, play it into a run without {svc}{how}")
        if sc is not None and not rights.tools_rights(sc).may_put(key):
            writers = rights.owners(sc, relative_topic(key, sc.ros2.namespace)) or ["a service"]
            return (f"{topic}: the tools of {where} may not write it (written by {', '.join(writers)}; "
                    "docs/security.md); play it into a run without that service")
        if nodes and not explicit:
            return (f"{where} has its own publishers on {topic} ({', '.join(nodes)}); to play into it all the same, "
                    "name it: --run DIR or --connect ENDPOINT")
    return None
