"""Batches for the recorder (``logger.batch``): a service's samples sent on one key, many at a time.

When the run's recorder takes batches, every hilsim service (but the recorder) keeps a
:class:`Batcher`: each sample a publisher of the service sends is appended to it, with
its key, sequence number, source time and writer gid (the attachment it would carry on its own
key), and the batch is put on the service's batch key (``Keys.batch``:
``<prefix>/batch/<domain>/<service>/<zid>/<node id>``) once it holds ``logger.batch`` samples or its first
sample is ``logger.batch_max_age_ms`` old, and at the service's stop before its publishers go. The
recorder unpacks it into the same path as a sample it received on the key itself
(``services/logger.py``). The same key is the batcher's liveliness token, declared before the
service's publishers announce themselves: it tells the recorder which writers it needs no
subscription of their own for.

Writes: the batch key (puts and its liveliness token). Reads: nothing.

The frame (all little endian), version 1::

    magic "HSB" (3 bytes), version u8, writers u16, records u32
    writers × (key length u16, key UTF-8, gid 16 bytes)
    records × (writer index u16, seq u64, source time ns i64, payload length u32, payload)

:func:`decode` checks every length against the frame and raises :class:`BatchError` on anything
that does not add up (a wrong magic or version, a frame cut short, a length or index that lies,
bytes left over): a receiver counts such a frame as rejected and goes on.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

MAGIC = b"HSB"
VERSION = 1
GID_SIZE = 16
_HEAD = struct.Struct("<3sBHI")
_KEYLEN = struct.Struct("<H")
_REC = struct.Struct("<HQqI")
MAX_WRITERS = 0xFFFF
# A frame stays below Zenoh's transport batch (65535 bytes, less its headers): a larger one is sent in
# fragments, and on a congested link a DROP put loses fragments, not frames: seen on a loaded machine
# as frames the recorder got with their start missing ("not a batch (magic b'\x00jo')"), every record
# in them lost. A single sample larger than this still goes, alone in its frame.
MAX_FRAME = 60_000


class BatchError(ValueError):
    """A frame that is not a well-formed batch (:func:`decode`)."""


class Record(NamedTuple):
    key: str
    seq: int
    source_ns: int
    gid: bytes
    payload: bytes


def encode(writers: list[tuple[str, bytes]], records: list[tuple[int, int, int, bytes]]) -> bytes:
    """A frame of ``records`` ``(writer index, seq, source time ns, payload)`` whose writers are
    ``writers`` ``(key, gid)``."""
    if len(writers) > MAX_WRITERS:
        raise ValueError(f"{len(writers)} writers: a batch holds at most {MAX_WRITERS}")
    parts = [_HEAD.pack(MAGIC, VERSION, len(writers), len(records))]
    for key, gid in writers:
        if len(gid) != GID_SIZE:
            raise ValueError(f"gid of {key}: {len(gid)} bytes, not {GID_SIZE}")
        k = key.encode()
        parts += [_KEYLEN.pack(len(k)), k, gid]
    pack = _REC.pack
    for w, seq, t_ns, payload in records:
        parts += [pack(w, seq, t_ns, len(payload)), payload]
    return b"".join(parts)


def decode(frame: bytes | bytearray | memoryview) -> list[Record]:
    """The records of a frame, in the order they were added; :class:`BatchError` if it is malformed."""
    buf = memoryview(frame)
    n = len(buf)
    if n < _HEAD.size:
        raise BatchError(f"{n} bytes: shorter than a batch header ({_HEAD.size})")
    magic, version, n_writers, n_records = _HEAD.unpack_from(buf, 0)
    if magic != MAGIC:
        raise BatchError(f"not a batch (magic {bytes(magic)!r})")
    if version != VERSION:
        raise BatchError(f"batch version {version}, this reader knows {VERSION}")
    pos = _HEAD.size
    writers: list[tuple[str, bytes]] = []
    for i in range(n_writers):
        if pos + _KEYLEN.size > n:
            raise BatchError(f"cut short in writer {i} of {n_writers}")
        (klen,) = _KEYLEN.unpack_from(buf, pos)
        pos += _KEYLEN.size
        if pos + klen + GID_SIZE > n:
            raise BatchError(f"writer {i}: key of {klen} bytes and gid go past the end ({n} bytes)")
        try:
            key = bytes(buf[pos:pos + klen]).decode()
        except UnicodeDecodeError as e:
            raise BatchError(f"writer {i}: key is not UTF-8: {e}") from None
        pos += klen
        writers.append((key, bytes(buf[pos:pos + GID_SIZE])))
        pos += GID_SIZE
    # each record takes its header at least: a count that cannot fit is a lie, caught before the loop
    if n_records * _REC.size > n - pos:
        raise BatchError(f"{n_records} records cannot fit in the {n - pos} bytes left")
    out: list[Record] = []
    unpack = _REC.unpack_from
    for i in range(n_records):
        if pos + _REC.size > n:
            raise BatchError(f"cut short in record {i} of {n_records}")
        w, seq, t_ns, plen = unpack(buf, pos)
        pos += _REC.size
        if w >= n_writers:
            raise BatchError(f"record {i}: writer {w}, but the batch has {n_writers}")
        if pos + plen > n:
            raise BatchError(f"record {i}: payload of {plen} bytes goes past the end ({n} bytes)")
        key, gid = writers[w]
        out.append(Record(key, seq, t_ns, gid, bytes(buf[pos:pos + plen])))
        pos += plen
    if pos != n:
        raise BatchError(f"{n - pos} bytes after the last record")
    return out


class Batcher:
    """One service's batch: :meth:`add` from its publishers, sent by :meth:`flush` when full, by a
    thread when ``max_age_s`` old, and at :meth:`undeclare` (the service stopping)."""

    def __init__(self, pub: Any, token: Any, size: int, max_age_s: float,
                 last_put: Callable[[bytes], None] | None = None) -> None:
        self._pub = pub  # a Zenoh publisher of the batch key (hilsim.core.transport.publisher)
        # the last batch's put where the publisher's would drop it on a congested link (realtime): it holds
        # the service's last health, its last word
        self._last_put = last_put
        self._token = token
        self.size = size
        self.max_age_s = max_age_s
        self.writers: list[tuple[str, bytes]] = []
        self._writers_size = _HEAD.size  # the frame's header and writer table, in bytes
        self._records: list[tuple[int, int, int, bytes]] = []
        self._size = 0  # the records held, in bytes of the frame
        self._first = 0.0  # time.monotonic() of the oldest record held
        # one lock for adding, swapping and sending: batches leave in the order their records came
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self.batches = 0  # frames sent
        self.samples = 0  # records sent in them
        self._thread = threading.Thread(target=self._age, daemon=True, name="batch-flusher")
        self._thread.start()

    def writer(self, key: str, gid: bytes) -> int:
        """The index of a publisher (``key``, ``gid``) in this service's writer table."""
        with self._lock:
            self.writers.append((key, gid))
            self._writers_size += _KEYLEN.size + len(key.encode()) + GID_SIZE
            return len(self.writers) - 1

    def add(self, writer: int, seq: int, t_ns: int, payload: bytes) -> bool:
        """Append a sample; True when the batch is full (the caller then calls :meth:`flush`, outside
        its own lock)."""
        size = _REC.size + len(payload)
        with self._lock:
            if self._records and self._writers_size + self._size + size > MAX_FRAME:
                self._send()  # this sample would make the frame one Zenoh sends in fragments
            recs = self._records
            if not recs:
                self._first = time.monotonic()
                self._wake.notify()  # the flusher now has a deadline to wait for
            recs.append((writer, seq, t_ns, payload))
            self._size += size
            return len(recs) >= self.size or self._writers_size + self._size >= MAX_FRAME

    def flush(self, older_than: float | None = None, *, last: bool = False) -> None:
        """Send what is held (with ``older_than``: only if its first sample is at least that old; ``last``:
        the service's last batch, never dropped)."""
        with self._lock:
            if not self._records or (older_than is not None and time.monotonic() - self._first < older_than):
                return
            self._send(last)

    def _send(self, last: bool = False) -> None:
        recs, self._records, self._size = self._records, [], 0
        data = encode(self.writers, recs)
        if last and self._last_put is not None:
            self._last_put(data)
        else:
            self._pub.put(data)
        self.batches += 1
        self.samples += len(recs)

    def _age(self) -> None:
        # no sample waits longer than max_age_s for the batch to fill (a slow key, a quiet service)
        while True:
            with self._lock:
                while not self._records and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                wait = self._first + self.max_age_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            try:
                self.flush(older_than=self.max_age_s)
            except Exception:  # the session closing under us: the service's stop flushes what is left
                return

    def undeclare(self) -> None:
        """Send what is held, stop the flusher, withdraw the token and the publisher."""
        try:
            self.flush()
        finally:
            with self._lock:
                self._closed = True
                self._wake.notify()
            self._thread.join(1.0)
            self._token.undeclare()
            self._pub.undeclare()
