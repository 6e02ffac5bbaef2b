"""The recorder's running loss accounting: each writer's sequence on each key, as its samples are taken in.

- :meth:`LossAccounts.sequence`: per sample, the samples of its writer that never arrived (``gaps``), those
  its writer published before the first one that arrived (``before_first``) and those that do not fit its
  sequence (``suspect``, recorded all the same); False for a sample taken already (one that came both ways:
  a batch and its key, or a latched writer's cache and ``**``), which the recorder counts as a duplicate;
- :meth:`LossAccounts.note_published`: a service's final health, what it says it published per key;
- :meth:`LossAccounts.contested`, :meth:`LossAccounts.judged_lost`: at the end, the gaps of writers with
  suspect samples (no loss of ours), and the losses per key, one count per cause (:mod:`hilsim.record.loss`).

Each writer's sequence is a :class:`hilsim.core.provenance.Sequence` (docs/keys.md, "Suspect samples").
The counters are the recorder's: its receive callback, worker and health thread share them under its lock,
which this class takes where the recorder did. Reads and writes no key (services/logger.py hands it each
sample's key, attachment and payload).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Any

from hilsim.core import msgs, transport
from hilsim.core.provenance import DUPLICATE, TAKEN, Sequence, digest_of
from hilsim.record import loss


class LossAccounts:
    """Loss accounting of one recorder; ``lock`` is the recorder's (its health thread reads the counters
    under it); ``batching``: every sample may come two ways (``logger.batch`` > 0)."""

    def __init__(self, lock: threading.RLock, *, batching: bool) -> None:
        self.lock = lock
        self.batching = batching
        # each writer's sequence (hilsim.core.provenance.Sequence), per (key, writer gid)
        self._streams: dict[tuple[str, bytes], Sequence] = {}
        self.gaps: Counter[str] = Counter()  # lost in transport: sequence numbers never received
        self.suspect: Counter[str] = Counter()  # samples that do not fit their writer's sequence (recorded)
        self.before_first: Counter[str] = Counter()  # published before a writer's first received sample
        self.published: dict[str, dict[str, int]] = {}  # health key -> its final health's published:<key>
        self.say_suspect = ""  # a warning to publish once the lock is released
        # keys with a late-joiner subscription beside `**` (latched writers, without batches): their
        # samples can come both ways and are taken once, as batches are
        self.twice: set[str] = set()

    def takes_twice(self, key: str) -> None:
        """A key whose samples can come two ways (``**`` and a latched writer's cache): taken once."""
        with self.lock:
            self.twice.add(key)

    def sequence(self, key: str, att: transport.Attachment, payload: Any, *, counted: bool = True) -> bool:
        """Count the samples of this sample's writer that never arrived, and those that do not fit its
        sequence (suspect: recorded all the same), under the lock (hilsim.core.provenance.Sequence).
        False for a sample taken already: one that came both ways (batches, a latched writer's cache;
        same number, same payload). Taken one way only, such a repeat is a replay: recorded, suspect."""
        w = (key, att.gid)
        st = self._streams.get(w)
        if st is None:
            st = self._streams[w] = Sequence()
        lost0, before0 = st.counted_lost, 0 if st.contested else st.before
        two_ways = self.batching or key in self.twice
        verdict, why = st.take(att.seq, digest_of(payload if isinstance(payload, bytes) else None),
                               time.monotonic(), one_way=not two_ways, counted=counted)
        if verdict == DUPLICATE and two_ways:
            return False
        self.gaps[key] += st.counted_lost - lost0
        self.before_first[key] += (0 if st.contested else st.before) - before0
        if verdict != TAKEN and counted:
            self.suspect[key] += 1
            if self.suspect[key] == 1:  # said once the lock is released: the recorder receives its own log
                self.say_suspect = f"suspect sample on {key}: {why} (recorded; further ones are counted)"
        return True

    def note_published(self, key: str, msg: msgs.DiagnosticArray) -> None:
        """A service's final health (``final: 1``, only it may write its health): what it published per key,
        against which a gap in its sequence is judged at the end (:meth:`judged_lost`)."""
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if values.get("final") != "1":
                continue
            with self.lock:
                self.published[key] = {k[10:]: int(v) for k, v in values.items()
                                       if k.startswith("published:") and v.isdigit()}

    def contested(self) -> Counter[str]:
        """Gaps of writers with suspect samples, per key: not counted as lost (hilsim.core.provenance)."""
        out: Counter[str] = Counter()
        with self.lock:
            for (k, _), st in self._streams.items():
                if st.contested_lost:
                    out[k] += st.contested_lost
        return out

    def judged_lost(self, gaps: Counter[str], dropped: Counter[str], received: Counter[str]) -> Counter[str]:
        """The losses per key, one count per cause (:func:`hilsim.record.loss.judged_lost`)."""
        published: Counter[str] = Counter()
        with self.lock:
            for counts in self.published.values():
                published.update(counts)
            suspect, before = Counter(self.suspect), Counter(self.before_first)
        return loss.judged_lost(gaps, dropped, received, suspect, before, published)
