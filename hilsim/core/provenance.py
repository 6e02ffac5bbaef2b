"""Who sent what: the announced writers of each key and what each writer sent last.

Every hilsim publisher announces itself as a ROS 2 node's publisher does on rmw_zenoh: a graph
token ``@ros2_lv/<domain>/…/MP/…/<topic>/<type>/<hash>/<qos>`` (:mod:`hilsim.core.ros2.wire`), whose
XXH3-128 hash is the publisher's gid, and it stamps every sample with rmw_zenoh's attachment
(sequence number, source time, that gid; :mod:`hilsim.core.transport`). A ROS 2 node's publisher
(say a lab's teleop on ``/rover/cmd_vel``) announces itself the same way, so it is a writer too.
A receiver keeps a :class:`Provenance` and asks it about every sample:

- a key that has had an announced writer is *restricted*: a sample on it without an attachment,
  or from a writer that has not announced itself for that key, is rejected (an impostor, or a
  tool publishing by hand while the real writer runs). A key nobody announced stays open, so a
  test or a tool may still drive a service alone;
- per writer, the sequence number must grow: the same number again is a duplicate, a smaller
  one is out of order — both are rejected; a jump is a gap, counted as lost samples;
- the first sample seen from a writer starts its count (what it sent before we listened is not
  a loss);
- a writer whose token went away is still believed for ``WITHDRAW_GRACE_S``: a stopping
  service's last samples may arrive after its token's withdrawal.

Pure bookkeeping, no transport: unit-tested on its own, used by :class:`hilsim.core.service.Service`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import zenoh

from hilsim.core.ros2 import wire
from hilsim.core.transport import Attachment

# A writer's last samples may arrive after its token was withdrawn (a service stopping: the token
# and the data travel separately): for this long they are still its own, not an impostor's.
WITHDRAW_GRACE_S = 1.0


class Provenance:
    def __init__(self, grace: float = WITHDRAW_GRACE_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.writers: dict[str, set[bytes]] = {}
        self.restricted: set[str] = set()
        self.last: dict[tuple[str, bytes], int] = {}
        self.withdrawn: dict[tuple[str, bytes], float] = {}  # (key, gid) -> when its token went
        self.grace, self.clock = grace, clock

    # ------------------------------------------------------------------ announcements
    def announce(self, key: str, gid: bytes) -> None:
        self.writers.setdefault(key, set()).add(gid)
        self.restricted.add(key)

    def withdraw(self, key: str, gid: bytes) -> None:
        """A writer went away (its token was undeclared); the key stays restricted. Its samples
        still in flight are accepted for ``grace`` seconds."""
        self.writers.get(key, set()).discard(gid)
        now = self.clock()
        for k in [k for k, t in self.withdrawn.items() if now - t > self.grace]:
            del self.withdrawn[k]
            self.last.pop(k, None)
        if self.grace > 0:
            self.withdrawn[(key, gid)] = now
        else:
            self.last.pop((key, gid), None)

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
    def check(self, key: str, att: Attachment | None) -> tuple[str | None, int]:
        """(reason to reject the sample or None, samples lost before it from its writer)."""
        if key in self.restricted:
            if att is None:
                return "no attachment: the sender is unknown (every hilsim writer attaches its id)", 0
            if att.gid not in self.writers.get(key, ()) and not self._lately_withdrawn(key, att.gid):
                return f"from writer {att.gid.hex()[:12]}…, which has not announced itself for this key", 0
        if att is None:
            return None, 0
        k = (key, att.gid)
        last = self.last.get(k)
        if last is not None:
            if att.seq == last:
                return f"duplicate of sample {att.seq} from this writer", 0
            if att.seq < last:
                return f"out of order: sample {att.seq} after {last} from this writer", 0
        self.last[k] = att.seq
        return None, 0 if last is None else att.seq - last - 1


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
