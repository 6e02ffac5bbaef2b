"""``hilsim topic list|echo|hz``: look at a running simulation the way ``ros2 topic`` does.

Connects to ``--connect`` (default: ``HILSIM_ZENOH_CONNECT`` or the launcher's well-known
``tcp/127.0.0.1:7447``, see :func:`hilsim.core.run_finder.tool_endpoints`), with the credentials of the
run whose router that is (:func:`hilsim.core.run_finder.tool_zenoh`), and never publishes anything.
Topics are ROS 2 names (``/arm/joint_states``) in the domain
``--domain`` (``ROS_DOMAIN_ID``); ``list`` reads the ROS 2 graph (rmw_zenoh's liveliness tokens) as
``ros2 topic list`` does, so a ROS 2 node's topics show up beside hilsim's. ``echo``/``hz`` take a
topic name (its key is ``<domain>/<name>/*/*``: any type) or a Zenoh key expression, and decode
each sample by the type in its key (:func:`hilsim.core.keys.message_type`). ``echo`` on a topic
that has no publisher in the graph (no ``MP`` token) and no sample says so after a second.

``hz`` believes only the key's rightful writer: once a publisher has announced itself for the key
(its ``MP`` graph token, :mod:`hilsim.core.provenance`), a sample without an attachment, from another
writer, or a duplicate or reordered one is not counted (it says how many it ignored), so an
impostor on ``/clock`` cannot change the figures; ``--any-writer`` counts every sample.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from collections import defaultdict, deque
from typing import Any

import yaml
import zenoh

from hilsim.core import msgs, run_finder, transport
from hilsim.core.keys import UnknownKey, message_type, topic_name
from hilsim.core.provenance import Provenance
from hilsim.core.ros2 import wire

WRITERS_SETTLE_S = 0.5  # hz: time for the announced writers (liveliness history) to arrive
NO_PUBLISHER_AFTER_S = 1.0  # echo: a topic without publisher nor sample is said to be so after this


def _session(args: argparse.Namespace) -> zenoh.Session:
    """The tool's session; its first line names the run it joined (ConnectionError: nothing there)."""
    return run_finder.open_tool_session(args.connect, run=getattr(args, "run", None),
                                       tool=f"hilsim topic {args.topic_cmd}")


def _stamp_of(msg: Any) -> float | None:
    h = getattr(msg, "header", None)
    if h is not None:
        return msgs.seconds(h.stamp)
    for attr in ("clock", "stamp"):
        t = getattr(msg, attr, None)
        if isinstance(t, msgs.Time):
            return msgs.seconds(t)
    return None


INTERNAL = ("health", "sync", "log", "hw")  # hilsim's own topics under a robot's namespace: `list --all`


def key_expr(name: str, domain: int) -> str:
    """A topic name (``/arm/joint_states``) as the key expression of every type on it; a key expression as is."""
    return f"{domain}/{name.strip('/')}/*/*" if name.startswith("/") else name


def _internal(topic: str) -> bool:
    parts = topic.strip("/").split("/")
    return len(parts) > 1 and parts[1] in INTERNAL


def cmd_list(args: argparse.Namespace) -> int:
    domain = run_finder.tool_domain(getattr(args, "domain", None))
    counts: dict[str, int] = defaultdict(int)
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        with lock:
            counts[str(s.key_expr)] += 1

    listen = args.duration or 1.0
    tokens: set[str] = set()

    def on_token(s: zenoh.Sample) -> None:
        with lock:
            if s.kind == zenoh.SampleKind.PUT:
                tokens.add(str(s.key_expr))
            else:
                tokens.discard(str(s.key_expr))

    with _session(args) as ses:
        # a subscriber with history, not a one-shot get: right after connecting, a get can
        # run before the router has told this session about the other peers
        live = ses.liveliness().declare_subscriber(wire.graph_key(domain), on_token, history=True)
        sub = ses.declare_subscriber(wire.domain_key(domain), on_sample)
        time.sleep(listen)
        sub.undeclare()
        live.undeclare()
    graph = []
    for k in tokens:
        try:
            graph.append(wire.parse_token(k))
        except ValueError:
            continue
    topics: dict[str, set[str]] = defaultdict(set)
    for name, types in wire.list_topics(graph).items():
        topics[name].update(types)
    rates: dict[str, float] = defaultdict(float)
    for key, n in counts.items():  # traffic without a graph token (a tool publishing by hand) shows too
        try:
            name = topic_name(key)
        except UnknownKey:
            continue
        topics[name].add(wire.ros_type_name(key.split("/")[-2]))
        rates[name] += n / listen
    if not topics:
        print(f"no topics in ROS 2 domain {domain} (is a simulation running? try --connect, --domain)")
        return 1
    hidden = 0
    for name in sorted(topics):
        if _internal(name) and not getattr(args, "all", False):
            hidden += 1
            continue
        line = name
        if getattr(args, "show_types", False):
            line += f" [{', '.join(sorted(topics[name]))}]"
        if rates.get(name):
            line += f"  {rates[name]:.1f} msg/s"
        print(line)
    if hidden:
        print(f"({hidden} internal topics hidden: health, sync, log, hw; --all shows them)")
    return 0


def _resolve(args: argparse.Namespace) -> str:
    return key_expr(args.key, run_finder.tool_domain(getattr(args, "domain", None)))


def _class_of(key: str) -> type | None:
    try:
        return message_type(key)
    except UnknownKey:
        return None


def cmd_echo(args: argparse.Namespace) -> int:
    expr = _resolve(args)
    done = threading.Event()
    n = 0
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        nonlocal n
        with lock:
            if done.is_set():
                return
            cls = _class_of(str(s.key_expr))
            if cls is None:
                return
            try:
                m = msgs.decode(cls, s.payload.to_bytes())
                out = msgs.to_dict(m)
                text = json.dumps(out) if args.json else yaml.safe_dump(out, sort_keys=False) + "---"
            except msgs.BadMessage as e:
                text = json.dumps({"error": str(e)}) if args.json else f"# bad payload on {s.key_expr}: {e}\n---"
            print(text, flush=True)
            n += 1
            if args.count is not None and n >= args.count:
                done.set()

    publishers: set[str] = set()  # the MP graph tokens of publishers on the topic (expression)

    def on_token(s: zenoh.Sample) -> None:
        key = publisher_key(str(s.key_expr))
        if key is None or not zenoh.KeyExpr(expr).intersects(zenoh.KeyExpr(key)):
            return
        with lock:
            (publishers.add if s.kind == zenoh.SampleKind.PUT else publishers.discard)(str(s.key_expr))

    domain = int(expr.split("/", 1)[0]) if expr.split("/", 1)[0].isdigit() else run_finder.tool_domain(
        getattr(args, "domain", None))
    with _session(args) as ses:
        graph = ses.liveliness().declare_subscriber(wire.graph_key(domain), on_token, history=True)
        sub = ses.declare_subscriber(expr, on_sample)
        try:
            # a topic nobody publishes: say so after a second, instead of waiting in silence
            quiet = args.duration is None or args.duration > NO_PUBLISHER_AFTER_S
            if quiet and not done.wait(NO_PUBLISHER_AFTER_S):
                with lock:
                    silent = n == 0 and not publishers
                if silent:
                    print(f"no publisher on {args.key} yet (waiting; Ctrl-C to stop)", file=sys.stderr, flush=True)
            done.wait(None if args.duration is None else max(0.0, args.duration - NO_PUBLISHER_AFTER_S * quiet))
        except KeyboardInterrupt:
            pass
        sub.undeclare()
        graph.undeclare()
    return 0 if (args.count is None or n >= args.count) else 1


def publisher_key(token: str) -> str | None:
    """The data key a publisher's graph token (``MP``) announces; None for any other token."""
    try:
        t = wire.parse_token(token)
    except ValueError:
        return None
    if t.kind != "MP" or not t.topic or not t.dds_type or not t.type_hash:
        return None
    try:
        return wire.topic_key(t.domain, t.topic, t.dds_type, t.type_hash)
    except ValueError:
        return None


def cmd_hz(args: argparse.Namespace) -> int:
    expr = _resolve(args)
    arrivals: deque[float] = deque(maxlen=args.window)
    stamps: deque[float] = deque(maxlen=args.window)
    lock = threading.Lock()
    prov = Provenance()
    check = not getattr(args, "any_writer", False)
    ignored = 0

    def on_sample(s: zenoh.Sample) -> None:
        nonlocal ignored
        now = time.perf_counter()
        if check:
            why, _ = prov.check(str(s.key_expr), transport.read_attachment(s))
            if why is not None:  # not from the key's announced writer: not part of its rate
                with lock:
                    ignored += 1
                return
        st = None
        cls = _class_of(str(s.key_expr))
        if cls is not None:
            try:
                st = _stamp_of(msgs.decode(cls, s.payload.to_bytes()))
            except msgs.BadMessage:
                pass
        with lock:
            arrivals.append(now)
            if st is not None:
                stamps.append(st)

    stop = threading.Event()
    t_end = time.monotonic() + args.duration if args.duration else math.inf
    printed = 0
    with _session(args) as ses:
        writers = None
        if check:
            domain = expr.split("/", 1)[0]
            writers = ses.liveliness().declare_subscriber(f"{wire.ADMIN_SPACE}/{domain}/**", prov.on_token,
                                                          history=True)
            time.sleep(WRITERS_SETTLE_S)
        sub = ses.declare_subscriber(expr, on_sample)
        try:
            while not stop.wait(1.0):
                with lock:
                    a, s, n_ignored = list(arrivals), list(stamps), ignored
                if len(a) >= 2:
                    d = [b - c for b, c in zip(a[1:], a, strict=False)]
                    mean = sum(d) / len(d)
                    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / len(d))
                    line = (f"average rate: {1 / mean:.2f} Hz (wall)  min {min(d) * 1e3:.3f} ms  "
                            f"max {max(d) * 1e3:.3f} ms  std {sd * 1e3:.3f} ms  window {len(a)}")
                    if len(s) >= 2 and s[-1] > s[0]:
                        line += f"  |  {(len(s) - 1) / (s[-1] - s[0]):.2f} Hz (sim time)"
                    if n_ignored:
                        line += f"  |  ignored {n_ignored} samples not from the announced writer"
                    print(line, flush=True)
                    printed += 1
                else:
                    print("no new messages", flush=True)
                if time.monotonic() >= t_end:
                    break
        except KeyboardInterrupt:
            pass
        sub.undeclare()
        if writers is not None:
            writers.undeclare()
    return 0 if printed else 1
