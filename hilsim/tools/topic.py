"""``hilsim topic list|echo|hz``: look at a running simulation the way ``ros2 topic`` does.

Connects as a Zenoh peer to ``--connect`` (default: ``HILSIM_ZENOH_CONNECT`` or the
launcher's well-known ``tcp/127.0.0.1:7447``, see :func:`hilsim.core.transport.tool_endpoints`),
decodes payloads by key through :func:`hilsim.core.keys.message_type`, and never publishes anything.

``hz`` believes only the key's rightful writer: once a publisher has announced itself for the key
(``<prefix>/writers/…``, :mod:`hilsim.core.provenance`), a sample without an attachment, from another
writer, or a duplicate or reordered one is not counted (it says how many it ignored), so an
impostor on ``clock`` cannot change the figures; ``--any-writer`` counts every sample.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from collections import defaultdict, deque
from typing import Any

import yaml
import zenoh

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys, UnknownKey, message_type
from hilsim.core.provenance import Provenance

WRITERS_SETTLE_S = 0.5  # hz: time for the announced writers (liveliness history) to arrive


def _session(args: argparse.Namespace) -> zenoh.Session:
    return transport.open_tool_session(args.connect)


def _stamp_of(msg: Any) -> float | None:
    h = getattr(msg, "header", None)
    if h is not None:
        return msgs.seconds(h.stamp)
    for attr in ("clock", "stamp"):
        t = getattr(msg, attr, None)
        if isinstance(t, msgs.Time):
            return msgs.seconds(t)
    return None


def cmd_list(args: argparse.Namespace) -> int:
    prefix = transport.tool_prefix(args.prefix)
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
        everything = Keys(prefix).everything
        live = ses.liveliness().declare_subscriber(everything, on_token, history=True)
        sub = ses.declare_subscriber(everything, on_sample)
        time.sleep(listen)
        sub.undeclare()
        live.undeclare()
    alive = sorted(tokens)
    if not alive and not counts:
        print(f"no hilsim services or traffic under {prefix}/ (is a simulation running? try --connect)")
        return 1
    for a in alive:
        print(f"{a}  [service]")
    for key in sorted(counts):
        try:
            t = msgs.type_name(message_type(key))
        except UnknownKey:
            t = "?"
        print(f"{key}  [{t}]  {counts[key] / listen:.1f} msg/s")
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    try:
        cls = message_type(args.key)
    except UnknownKey as e:
        print(f"error: {e.args[0]}")
        return 2
    done = threading.Event()
    n = 0
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        nonlocal n
        with lock:
            if done.is_set():
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

    with _session(args) as ses:
        sub = ses.declare_subscriber(args.key, on_sample)
        try:
            done.wait(args.duration)
        except KeyboardInterrupt:
            pass
        sub.undeclare()
    return 0 if (args.count is None or n >= args.count) else 1


def cmd_hz(args: argparse.Namespace) -> int:
    try:
        cls = message_type(args.key)
    except UnknownKey:
        cls = None
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
            prefix = args.key.split("/", 1)[0]
            writers = ses.liveliness().declare_subscriber(Keys(prefix).all_writers, prov.on_token, history=True)
            time.sleep(WRITERS_SETTLE_S)
        sub = ses.declare_subscriber(args.key, on_sample)
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
