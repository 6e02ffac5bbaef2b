"""Who sent what: the announced writers of each key and each writer's sequence of samples.

Every hilsim publisher announces itself as a ROS 2 node's publisher does on rmw_zenoh: a graph
token ``@ros2_lv/<domain>/…/MP/…/<topic>/<type>/<hash>/<qos>`` (:mod:`hilsim.core.ros2.wire`), whose
XXH3-128 hash is the publisher's gid, and it stamps every sample with rmw_zenoh's attachment
(sequence number, source time, that gid; :mod:`hilsim.core.transport`). A ROS 2 node's publisher
(say a lab's teleop on ``/rover/cmd_vel``) announces itself the same way, so it is a writer too.
A receiver keeps a :class:`Provenance` and asks it about every sample:

- a key that has had an announced writer is *restricted*: a sample on it without an attachment,
  or from a writer that has not announced itself for that key, is rejected (an impostor, or a
  tool publishing by hand while the real writer runs). A key nobody announced stays open, so a
  test or a tool may still drive a service alone. A key expression with wildcards is no key: rejected;
- per writer, a :class:`Sequence` (below) rejects only a proven duplicate and never drops a sample
  for its order; what does not fit the writer's sequence is delivered and counted as *suspect*;
- a writer whose token went away is still believed for ``WITHDRAW_GRACE_S``: a stopping
  service's last samples may arrive after its token's withdrawal.

**A writer's sequence, and why nothing can poison it** (docs/keys.md, "Suspect samples"). A gid is
public (the graph token's hash, in every sample), so whoever may write a key can send samples with a
real writer's gid and any sequence number; the router's access control (hilsim.core.rights) limits that
to the keys the sender may write anyway. Zenoh delivers one writer's samples in order and once, so the
writer's own samples always come with growing numbers; the checks therefore never drop a sample because
of what came before it (a forged number far ahead once made every later genuine sample "out of order"):

- *duplicate* (rejected): the same sequence number again *with the same payload* (a replay of a recent
  sample; the recorder's two ways of receiving one, batch and key). Judged over the writer's last
  ``WINDOW`` numbers;
- the same number with a *different* payload: one of the two is not the writer's; both are delivered,
  the second counted as suspect;
- the *baseline* (the writer's newest number) moves only forward, and only by a jump the writer could
  have made: 1, or at most ``JUMP_SLACK`` + ``MAX_RATE_HZ`` × the seconds since it last moved (samples a
  realtime publisher dropped). A jump beyond is suspect and moves nothing, so the writer's own next
  sample still continues the baseline;
- a number behind the baseline fills a gap counted before (a sample that came the other way, for the
  recorder), else it is suspect (a replay older than the window, a number someone else took first);
  for a receiver with one way only (a service), any number behind the baseline is suspect;
- the first sample anchors the baseline: what the writer sent before is not a loss (``before_first``).
  A forged first sample far ahead makes the writer's own samples suspect (delivered, counted), not lost.

A writer with a suspect sample is *contested*: its gaps could be anyone's, so they are withdrawn from
its losses (``lost``) and said apart; the summary judges losses against what each service says it
published (only it may write its health). So no forged or replayed sample drops a genuine one (it is at
worst delivered beside it, on a key the sender may write anyway), nor makes a loss of one that arrived.

Pure bookkeeping, no transport: unit-tested on its own, used by :class:`hilsim.core.service.Service` and
the recorder (services/logger.py).
"""

from __future__ import annotations

import time
from array import array
from collections import Counter
from collections.abc import Callable
from typing import Any

import zenoh

from hilsim.core.ros2 import wire
from hilsim.core.transport import Attachment

# A writer's last samples may arrive after its token was withdrawn (a service stopping: the token
# and the data travel separately): for this long they are still its own, not an impostor's.
WITHDRAW_GRACE_S = 1.0
WINDOW = 1024  # sequence numbers (and payload digests) kept per writer to judge duplicates
JUMP_SLACK = 32  # a jump a writer may make at any time (samples a realtime publisher dropped)
MAX_RATE_HZ = 20_000.0  # samples per second a writer may send at most (the arm's fastest keys: 1 kHz × speed)
MAX_HOLES = 10_000  # gaps kept per writer (a long lossy realtime run: the oldest stay lost for good)
REANCHOR_SAMPLES = 8  # a sequence off the baseline this long, while the baseline is quiet …
REANCHOR_QUIET_S = 0.5  # … for this long, becomes the baseline
DUPLICATE, TAKEN, SUSPECT = 0, 1, 2
LOST, BEFORE, UNCOUNTED = 0, 1, 2  # what a gap is: samples lost, sent before the first, or not ours to count


class Sequence:
    """One writer's sample sequence on one key (module docstring): :meth:`take` judges each sample."""

    __slots__ = ("before", "conflicts", "contested", "digests", "first", "holes", "last", "lost", "other", "seqs",
                 "suspect", "t_last")

    def __init__(self) -> None:
        self.first = self.last = -1
        self.t_last = 0.0
        self.seqs = array("q", [-1]) * WINDOW
        self.digests = array("q", [0]) * WINDOW
        self.holes: list[list[int]] = []  # [lo, hi, LOST | BEFORE | UNCOUNTED], oldest first
        self.lost = 0  # in LOST holes
        self.before = 0  # in BEFORE holes
        self.contested = False
        self.suspect = 0
        # the numbers that do not fit the baseline, if they form a sequence of their own: [first, last,
        # when it last moved, samples, gaps]. Taken over as the baseline when that has gone quiet (a forged
        # first sample far ahead of the writer's own, which then come here)
        self.other: list[float] | None = None
        self.conflicts: dict[int, set[int]] = {}  # number -> digests of further samples with it (the window's)

    def take(self, seq: int, digest: int, now: float, *, one_way: bool = True, counted: bool = True,
             ) -> tuple[int, str]:
        """(DUPLICATE, why): drop it; (TAKEN, ""): deliver; (SUSPECT, why): deliver, and count it.
        ``one_way``: the receiver gets each sample one way only (not the recorder's batches and keys);
        ``counted``: gaps before this sample are losses (its writer is announced)."""
        i = seq % WINDOW
        if self.seqs[i] == seq:
            if self.digests[i] == digest or digest in self.conflicts.get(seq, ()):
                return DUPLICATE, f"duplicate of sample {seq} from this writer"
            self.conflicts.setdefault(seq, set()).add(digest)  # a replay of this one is a duplicate too
            if len(self.conflicts) > WINDOW:
                del self.conflicts[next(iter(self.conflicts))]
            return self._suspect(f"a second sample {seq} from this writer, unlike the first: one is not its own")
        self.seqs[i], self.digests[i] = seq, digest
        last = self.last
        if last < 0:  # the first: what came before is not a loss
            self.first, self.last, self.t_last = seq, seq, now
            if seq > 1:
                self._hole(1, seq - 1, BEFORE if counted else UNCOUNTED)
            return TAKEN, ""
        d = seq - last
        if d == 1:
            self.last, self.t_last = seq, now
            return TAKEN, ""
        if d > 1:
            if d > JUMP_SLACK + MAX_RATE_HZ * (now - self.t_last):
                return self._suspect(f"sample {seq} after {last}: a jump of {d - 1} in {now - self.t_last:.3f} s, "
                                     "more than this writer can send", seq, now)
            self._hole(last + 1, seq - 1, LOST if counted else UNCOUNTED)
            self.last, self.t_last = seq, now
            return TAKEN, ""
        # behind the baseline: a gap filled (the other way), else a number someone else sent
        holes = self.holes
        for j in range(len(holes) - 1, -1, -1):  # the newest first: a late sample is a recent one
            lo, hi, kind = holes[j]
            if lo <= seq <= hi:
                if kind == BEFORE and seq < self.first - WINDOW:
                    break  # far before the first sample: not a late one of its own
                self._fill(j, seq)
                if one_way:
                    return self._suspect(f"sample {seq} after {last}: this writer's numbers grow, so one of them "
                                         "is not its own")
                return TAKEN, ""
        return self._suspect(f"sample {seq} after {last} and not missing: a replay, or not this writer's", seq, now)

    def _suspect(self, why: str, seq: int | None = None, now: float = 0.0) -> tuple[int, str]:
        self.suspect += 1
        self.contested = True
        if seq is not None:
            self._other(seq, now)
        return SUSPECT, why

    def _other(self, seq: int, now: float) -> None:
        """A number off the baseline: it continues the other sequence, or starts it. The other takes the
        baseline's place once it has ``REANCHOR_SAMPLES`` samples and the baseline has not moved for
        ``REANCHOR_QUIET_S``: re-anchored on the sequence that goes on."""
        o = self.other
        if o is not None and 0 < seq - o[1] <= JUMP_SLACK + MAX_RATE_HZ * (now - o[2]):
            o[4] += seq - o[1] - 1
            o[1], o[2], o[3] = seq, now, o[3] + 1
        else:
            o = self.other = [seq, seq, now, 1, 0]
        if o[3] >= REANCHOR_SAMPLES and now - self.t_last >= REANCHOR_QUIET_S:
            self.other = [self.first, self.last, self.t_last, 0, self.lost]
            self.first, self.last, self.t_last, self.lost = int(o[0]), int(o[1]), o[2], int(o[4])
            self.holes = [[1, self.first - 1, BEFORE]] if self.first > 1 else []
            self.before = max(self.first - 1, 0)

    def _hole(self, lo: int, hi: int, kind: int) -> None:
        self.holes.append([lo, hi, kind])
        n = hi - lo + 1
        if kind == LOST:
            self.lost += n
        elif kind == BEFORE:
            self.before += n
        if len(self.holes) > MAX_HOLES:  # the oldest stay as they are counted, for good
            del self.holes[0]

    def _fill(self, i: int, seq: int) -> None:
        lo, hi, kind = self.holes[i]
        if kind == LOST:
            self.lost -= 1
        elif kind == BEFORE:
            self.before -= 1
        self.holes[i:i + 1] = [x for x in ([lo, seq - 1, kind], [seq + 1, hi, kind]) if x[0] <= x[1]]

    @property
    def counted_lost(self) -> int:
        """Its losses, as far as they are its own: none said while it is contested."""
        return 0 if self.contested else self.lost

    @property
    def contested_lost(self) -> int:
        """The gaps of a contested writer (the baseline's and the other sequence's): said, not counted."""
        return self.lost + int(self.other[4] if self.other is not None else 0) if self.contested else 0


def digest_of(payload: bytes | None) -> int:
    """What tells two payloads apart for :meth:`Sequence.take` (0: none to compare, a composed message)."""
    return hash(payload) if payload is not None else 0


class Provenance:
    def __init__(self, grace: float = WITHDRAW_GRACE_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.writers: dict[str, set[bytes]] = {}
        self.restricted: set[str] = set()
        self.gid_key: dict[bytes, str] = {}  # each announced writer's key (kept after it went: a gid is never reused)
        self.streams: dict[tuple[str, bytes], Sequence] = {}
        self.withdrawn: dict[tuple[str, bytes], float] = {}  # (key, gid) -> when its token went
        self.grace, self.clock = grace, clock
        self.suspect: Counter[str] = Counter()  # samples per key that do not fit their writer's sequence
        # called with (key, why) for every suspect sample (a service logs the first of each key)
        self.on_suspect: Callable[[str, str], None] | None = None

    # ------------------------------------------------------------------ announcements
    def announce(self, key: str, gid: bytes) -> None:
        self.writers.setdefault(key, set()).add(gid)
        self.restricted.add(key)
        self.gid_key[gid] = key

    def announced_elsewhere(self, key: str, gid: bytes) -> bool:
        """True for a writer announced for another key: a gid is the hash of its writer's graph token, topic
        included, so its samples on ``key`` (an open one: it would be refused on a restricted one) are someone
        else's, e.g. an insider's copy of the planner's trajectory with the planner's id and a number of its
        choosing. Delivered as any sample on an open key, but the gaps in those numbers are no loss."""
        other = self.gid_key.get(gid)
        return other is not None and other != key

    def withdraw(self, key: str, gid: bytes) -> None:
        """A writer went away (its token was undeclared); the key stays restricted. Its samples
        still in flight are accepted for ``grace`` seconds."""
        self.writers.get(key, set()).discard(gid)
        now = self.clock()
        for k in [k for k, t in self.withdrawn.items() if now - t > self.grace]:
            del self.withdrawn[k]
            self.streams.pop(k, None)  # gone for good (a restarted writer has a new gid)
        if self.grace > 0:
            self.withdrawn[(key, gid)] = now
        else:
            self.streams.pop((key, gid), None)

    def on_token(self, sample: Any) -> None:
        """Liveliness callback for ``Keys.all_writers`` (the ROS 2 graph): a writer appeared or went away."""
        parsed = parse_writer_token(str(sample.key_expr))
        if parsed is None:
            return
        key, gid = parsed
        if sample.kind == zenoh.SampleKind.PUT:
            self.announce(key, gid)
        else:
            self.withdraw(key, gid)

    def _lately_withdrawn(self, key: str, gid: bytes) -> bool:
        t = self.withdrawn.get((key, gid))
        return t is not None and self.clock() - t <= self.grace

    # ------------------------------------------------------------------ samples
    def check(self, key: str, att: Attachment | None, payload: bytes | None = None) -> tuple[str | None, int]:
        """(reason to reject the sample or None, the change it makes to the key's lost samples: the gap
        before it, a gap it fills (negative), or a writer's gaps withdrawn once it is contested).
        ``payload``: its bytes, to tell a duplicate from a forgery with the same number."""
        if "*" in key:
            return "a key expression with wildcards, not a key: nobody writes such a sample", 0
        if key in self.restricted:
            if att is None:
                return "no attachment: the sender is unknown (every hilsim writer attaches its id)", 0
            if att.gid not in self.writers.get(key, ()) and not self._lately_withdrawn(key, att.gid):
                return f"from writer {att.gid.hex()[:12]}…, which has not announced itself for this key", 0
        if att is None:
            return None, 0
        w = (key, att.gid)
        st = self.streams.get(w)
        if st is None:
            st = self.streams[w] = Sequence()
        before = st.counted_lost
        verdict, why = st.take(att.seq, digest_of(payload), self.clock(),
                               counted=not self.announced_elsewhere(key, att.gid))
        if verdict == DUPLICATE:
            return why, 0
        if verdict == SUSPECT:
            self.suspect[key] += 1
            if self.on_suspect is not None:
                self.on_suspect(key, why)
        return None, st.counted_lost - before

    def contested(self, key: str) -> int:
        """Gaps of the key's contested writers: not counted as lost (see the module docstring)."""
        return sum(st.contested_lost for (k, _), st in self.streams.items() if k == key)


def parse_writer_token(token: str) -> tuple[str, bytes] | None:
    """A publisher's (``MP``) graph token → (the data key it writes, its gid); None for any other token."""
    if "/MP/" not in token:
        return None
    try:
        tok = wire.parse_token(token)
    except ValueError:
        return None
    if tok.topic is None or tok.dds_type is None or tok.type_hash is None:
        return None
    return wire.topic_key(tok.domain, tok.topic, tok.dds_type, tok.type_hash), tok.gid
