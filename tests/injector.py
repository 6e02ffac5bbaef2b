"""A bad-input injector, run as its own process against a running simulation (tests only).

It listens to every key of the simulation and, for each key it has seen, publishes bad and
mutated copies of real samples: empty, random bytes, truncated, bit-flipped, 1 MiB, a well-formed
message with a NaN in it, well-formed copies of real samples from an unannounced writer (with
no attachment, and with an attachment of its own), and forged ones: a real sample with one value
changed (or, with no value to change, the sample itself: a trajectory), sent with its writer's gid
(public: the graph token's hash, and in every sample) and the writer's next sequence number, as that
writer would (``forged_writer``), or a number far ahead
(``forged_ahead``: +10,000, which once made every later sample of the writer "out of order"); and
replays: a real sample seen seconds before, sent again exactly as it came (payload and attachment:
its writer's gid and number, as a bag replayed with its recorded ids would). ``query_garbage`` sends
malformed requests to the queryables a person may ask (goals, cancels, gains). ``--kinds`` picks some.

It is a client of the router (as every process with credentials is): with ``--auth FILE`` (a Zenoh
config with credentials of the run, e.g. the tools' ``<run dir>/zenoh-client.json5``) as an insider;
without it, against ``hilsim up``'s router, it cannot connect. It prints, as JSON, how many of each
kind it sent when stopped (SIGINT/SIGTERM) or after ``--seconds`` (``"keys"``: on how many keys), or
``{"connected": false, …}``.

    python tests/injector.py --connect tcp/127.0.0.1:7447 [--auth FILE] [--domain 0] [--rate 300]
        [--seconds 30] [--kinds forged_writer,random]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import threading
import time
from collections import Counter

import zenoh

from hilsim.core import msgs, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys, UnknownKey, message_type

KINDS = ("empty", "random", "truncated", "bitflip", "huge", "nan", "copy_no_attachment", "copy_foreign_writer",
         "forged_writer", "forged_ahead", "replay", "query_garbage")
REPLAY_AGE_S = 2.0  # a replayed sample is at least this old
AHEAD = 10_000


def poison(msg: object) -> bool:
    """Put a NaN into the first float list or float field found; False if there is none."""
    for name in getattr(msg, "__dataclass_fields__", {}):
        v = getattr(msg, name)
        if isinstance(v, float):
            setattr(msg, name, math.nan)
            return True
        if isinstance(v, list) and v and isinstance(v[0], float):
            v[0] = math.nan
            return True
        if hasattr(v, "__dataclass_fields__") and poison(v):
            return True
    return False


def nudge(msg: object) -> bool:
    """Change the first float found by +1 (a plausible, well-formed lie); False if there is none."""
    for name in getattr(msg, "__dataclass_fields__", {}):
        v = getattr(msg, name)
        if isinstance(v, float):
            setattr(msg, name, v + 1.0)
            return True
        if isinstance(v, list) and v and isinstance(v[0], float):
            v[0] += 1.0
            return True
        if hasattr(v, "__dataclass_fields__") and nudge(v):
            return True
    return False


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--domain", type=int, default=0, help="ROS 2 domain id of the simulation")
    ap.add_argument("--rate", type=float, default=300.0, help="bad samples per second, all keys together")
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--auth", help="Zenoh config file with the run's user and password (an insider)")
    ap.add_argument("--kinds", default=",".join(KINDS), help="comma-separated, of: " + ", ".join(KINDS))
    args = ap.parse_args()
    kinds = [k for k in args.kinds.split(",") if k in KINDS] or list(KINDS)
    rng = random.Random(1)
    gid = os.urandom(16)
    zc = ZenohConfig(mode="client", connect=[args.connect], auth=args.auth)
    try:
        session = transport.open_session(zc)
    except ConnectionError as e:
        print(json.dumps({"connected": False, "error": str(e).splitlines()[0]}), flush=True)
        return 0
    latest: dict[str, tuple[bytes, transport.Attachment]] = {}
    old: dict[str, list[tuple[float, bytes, bytes]]] = {}  # key -> (when, payload, attachment) seen before
    lock = threading.Lock()

    forged: set[tuple[bytes, int, int]] = set()  # (gid, seq, payload hash) of what it sent with a real gid

    def on_sample(s: zenoh.Sample) -> None:
        att = transport.read_attachment(s)
        if att is None or att.gid == gid:
            return  # keep real samples only, not our own
        k = str(s.key_expr)
        payload = s.payload.to_bytes()
        with lock:
            if (att.gid, att.seq, hash(payload)) in forged:
                return  # its own forgery coming back: copying it would send old content under a new number
            latest[k] = (payload, att)
            kept = old.setdefault(k, [])
            if len(kept) < 64 and (not kept or time.monotonic() - kept[-1][0] > 0.05):
                kept.append((time.monotonic(), latest[k][0], s.attachment.to_bytes()))

    sub = session.declare_subscriber(f"{args.domain}/**", on_sample)  # every data key of the ROS 2 domain
    pubs: dict[str, zenoh.Publisher] = {}
    sent: Counter[str] = Counter()
    keys_hit: set[str] = set()
    served = [Keys(domain=args.domain).service(n) for n in ("planner/goal", "planner/cancel",
                                                            "controller/set_parameters")]
    seqs: Counter[str] = Counter()
    # the planner hands its trajectory on a key only it may write; its copies also go to joint_trajectory
    planner_traj, person_traj = (Keys(domain=args.domain).topic(t) for t in ("planner/joint_trajectory",
                                                                              "joint_trajectory"))
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    end = time.monotonic() + args.seconds
    period = 1.0 / args.rate
    while not stop.is_set() and time.monotonic() < end:
        with lock:
            items = list(latest.items())
        if not items:
            stop.wait(0.05)
            continue
        kind = kinds[sent.total() % len(kinds)]
        # a quarter of the attacks on the trajectory: the data key a person may write, so the router lets
        # them through and its receiver (the controller) must refuse each kind itself; at random, on a
        # loaded machine (fewer attacks sent) some kinds never landed on it. Not the 1 MB ones: a quarter
        # of those, all let through, stalled a niced recorder on a loaded machine
        trajectory = [kv for kv in items if kv[0].split("/")[-3:-2] == ["joint_trajectory"]]
        favour = trajectory and kind != "huge" and rng.random() < 0.25
        key, (good, real) = rng.choice(trajectory if favour else items)
        if key == planner_traj and favour and rng.random() < 0.5:
            key = person_traj  # the planner's trajectory sent on the key a person may write: a replay there
        try:
            cls = message_type(key)
        except UnknownKey:
            continue
        att = None
        if kind == "empty":
            data = b""
        elif kind == "random":
            data = rng.randbytes(rng.randint(1, 300))
        elif kind == "truncated":
            data = good[: max(1, len(good) // 2)]
        elif kind == "bitflip":
            b = bytearray(good)
            for _ in range(3):
                i = rng.randrange(len(b))
                b[i] ^= 1 << rng.randrange(8)
            data = bytes(b)
        elif kind == "huge":
            data = good[:4] + rng.randbytes(1 << 20)
        elif kind == "nan":
            try:
                m = msgs.decode(cls, good)
            except msgs.BadMessage:
                continue
            if not poison(m):
                continue
            data = msgs.encode(m)
        elif kind in ("forged_writer", "forged_ahead"):
            # its writer's own gid and next sequence number (or one far ahead), one value changed: on a key
            # the identity may not write, the router keeps it out; on one it may, the receivers deliver the
            # writer's own samples all the same (hilsim.core.provenance)
            try:
                m = msgs.decode(cls, good)
            except msgs.BadMessage:
                continue
            # nothing to nudge (a trajectory): the sample itself, only its number forged
            data = msgs.encode(m) if nudge(m) else good
            seq = real.seq + (1 if kind == "forged_writer" else AHEAD)
            att = transport.attachment_bytes(seq, real.gid)
            with lock:
                forged.add((real.gid, seq, hash(data)))
        elif kind == "replay":
            with lock:
                aged = [x for x in old.get(key, []) if time.monotonic() - x[0] > REPLAY_AGE_S]
            if not aged:
                stop.wait(0.01)  # nothing old enough yet
                continue
            _, data, att = rng.choice(aged)  # exactly as it came: its writer's gid and number
        elif kind == "query_garbage":
            q = rng.choice(served)
            for _ in session.get(q, payload=rng.randbytes(rng.randint(0, 64)), timeout=0.5):
                pass
            sent[kind] += 1
            keys_hit.add(q)
            stop.wait(period)
            continue
        else:
            data = good  # a real sample, replayed by a stranger
            if kind == "copy_foreign_writer":
                seqs[key] += 1  # consecutive per key, like a real writer's
                att = transport.attachment_bytes(seqs[key], gid)
        pub = pubs.get(key)
        if pub is None:
            # blocking, not dropping: a sample of its own that Zenoh dropped behind its 1 MiB ones (the default
            # congestion control) is a gap in its own writer's numbers on the open trajectory key, which the
            # recorder rightly counts as lost in transport: a loss of the attacker's, failing the lockstep run
            # (CI, twice: sample 13 of its copy_foreign_writer stream missing from the bag)
            pub = pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        if att is None:
            pub.put(data)
        else:
            pub.put(data, attachment=att)
        sent[kind] += 1
        keys_hit.add(key)
        stop.wait(period)
    sub.undeclare()
    for p in pubs.values():
        p.undeclare()
    session.close()
    print(json.dumps({**sent, "keys": len(keys_hit)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
