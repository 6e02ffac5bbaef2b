"""Writing rosbag2 bags (MCAP storage) of raw CDR samples, fast enough for the recorder's worker.

A bag is a directory (``<run dir>/bag/``) as rosbag2 makes one: ``metadata.yaml``
(:func:`hilsim.record.bag_read.write_metadata`) beside ``bag_0.mcap`` (a recorder restarted by
``hilsim up``: ``bag_<n>.mcap``, a further file of the same bag). The MCAP file follows MCAP's
``ros2`` profile as rosbag2's ``mcap`` storage plug-in writes it:

- one channel per Zenoh key: topic = the key's ROS 2 topic name (``/arm/joint_states``),
  ``message_encoding`` ``cdr``; its schema ``pkg/msg/Type``, encoding ``ros2msg``, data the
  ``.msg`` text with its dependencies (:func:`hilsim.core.ros2.types.full_definition`);
  channel metadata ``offered_qos_profiles`` (the QoS hilsim's publishers offer, as the YAML list
  rosbag2 writes), ``topic_type_hash`` (RIHS01) and ``hilsim_key`` (the Zenoh key itself);
- each message's data is the sample's payload as it arrived (raw CDR, never re-encoded);
  ``log_time`` = when the recorder received it (ns since the UNIX epoch), ``publish_time`` = its
  sim-time stamp (``header.stamp``, a Clock's ``clock``, a Log's ``stamp``, a TFMessage's first
  transform's stamp; else the receive time); ``sequence`` = the sequence number of its rmw_zenoh
  attachment (its low 32 bits; 0 without an attachment);
- the writer's gid of each message: MCAP metadata records ``hilsim_writer`` (``index``,
  ``gid`` hex, ``key``, ``topic``) name every writer once, before its first message; each chunk
  is preceded by an MCAP attachment ``hilsim_writers`` whose data is one little-endian uint16 per
  message of that chunk, in the chunk's order: the writer's index (65535: no attachment);
- chunks of at most ``CHUNK_BYTES`` (uncompressed), zstd-compressed, with message indexes, a
  summary section and footer, as any MCAP writer (readers seek by the chunk indexes).

Speed: :meth:`BagWriter.add` only appends a tuple; :meth:`BagWriter.flush` (the recorder calls it
with every batch of rows, twice a second) turns the batch into chunks with numpy (record headers,
stamps, message indexes) and writes them, so the file holds everything up to the last flush. A
writer killed before :meth:`BagWriter.close` leaves no summary or footer:
:func:`hilsim.record.bag_read.recover_bag` rewrites what is whole.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import yaml
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding

from hilsim.core.keys import UnknownKey, topic_name
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire

MAGIC = b"\x89MCAP0\r\n"
CHUNK_BYTES = 1 << 20  # uncompressed bytes of messages per chunk, at most (one batch may make several)
ZSTD_LEVEL = 1  # fast: the recorder's CPU matters more than the last 10 % of size
NO_WRITER = 0xFFFF  # writer index of a message that came without an attachment
NO_ATTACHMENT = (0, 0, None)  # a queued sample's attachment when it had none
_SEQ, _GID = itemgetter(0), itemgetter(2)
_KEY, _DATA, _ATT, _LOG = itemgetter(0), itemgetter(1), itemgetter(2), itemgetter(3)
WRITERS_ATTACHMENT = "hilsim_writers"  # before each chunk: uint16 writer index per message
WRITERS_MEDIA_TYPE = "application/x-hilsim-writer-index"
WRITER_METADATA = "hilsim_writer"  # one per writer: index, gid, key, topic
BAG_METADATA = "hilsim_bag"  # once: how the times and the writers are to be read
FILE_PATTERN = "bag_{}.mcap"
LIBRARY = "hilsim"  # the MCAP header's writer name
TIME_NOTE = ("log_time: when the recorder received the sample (ns since the UNIX epoch); publish_time: the "
             "sample's sim-time stamp (ns); sequence: its rmw_zenoh sequence number (low 32 bits)")

# a message record's fixed part: opcode, record length, channel id, sequence, log time, publish time
_MSG_HEAD = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")])
_HEAD = _MSG_HEAD.itemsize  # 31
_PUB_AT = _MSG_HEAD.fields["pub"][1]  # 23: where a record's publish time is
_INDEX_HEAD = struct.Struct("<BQHI")  # message index record: opcode, length, channel id, array byte length
_CHUNK_HEAD = struct.Struct("<BQQQQI")  # chunk record: opcode, length, start, end, uncompressed size, crc
_INFINITE = {"sec": wire.DURATION_INFINITE[0], "nsec": wire.DURATION_INFINITE[1]}


class BagError(RuntimeError):
    """A bag that cannot be written, found or read; the message is one line."""


def offered_qos(topic: str) -> wire.Qos:
    """The QoS hilsim's publishers offer on ``topic``: rclcpp's ClockQoS on ``/clock``, transient
    local (keep-last 1) on ``/tf_static`` and ``…/robot_description``, else the default profile."""
    if topic == "/clock":
        return wire.QOS_CLOCK
    if topic == "/tf_static" or topic.endswith("/robot_description"):
        return wire.QOS_LATCHED
    return wire.QOS_DEFAULT


def qos_profiles(topic: str) -> list[dict[str, Any]]:
    """:func:`offered_qos` as rosbag2 (metadata version 9) lists a topic's ``offered_qos_profiles``."""
    q = offered_qos(topic).adapted()
    names = {wire.Reliability.RELIABLE: "reliable", wire.Reliability.BEST_EFFORT: "best_effort"}
    dur = {wire.Durability.VOLATILE: "volatile", wire.Durability.TRANSIENT_LOCAL: "transient_local"}

    def d(v: tuple[int, int]) -> dict[str, int]:
        return {"sec": int(v[0]), "nsec": int(v[1])}

    return [{
        "history": "keep_last" if q.history == wire.History.KEEP_LAST else "keep_all",
        "depth": int(q.depth),
        "reliability": names.get(wire.Reliability(q.reliability), "reliable"),
        "durability": dur.get(wire.Durability(q.durability), "volatile"),
        "deadline": d(q.deadline) if tuple(q.deadline) != wire.DURATION_INFINITE else dict(_INFINITE),
        "lifespan": d(q.lifespan) if tuple(q.lifespan) != wire.DURATION_INFINITE else dict(_INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": d(q.lease) if tuple(q.lease) != wire.DURATION_INFINITE else dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }]


def qos_yaml(profiles: list[dict[str, Any]]) -> str:
    """The channel metadata ``offered_qos_profiles``: the list as YAML text (rosbag2's MCAP channels)."""
    return str(yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False)).strip()


def stamp_offset(ros_type: str) -> int:
    """Where a type's sim-time stamp sits in its CDR payload (encapsulation header included): 4 if
    its first field is a ``std_msgs/Header`` or a ``builtin_interfaces/Time``; 8 if it is a
    sequence of such stamped messages (TFMessage: the first one's); -1: the type has none."""
    if not ros2types.is_known(ros_type):
        return -1
    fs = ros2types.fields(ros_type)
    if not fs:
        return -1
    f = fs[0]
    stamped = ("std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    if f.type in stamped and f.container == "":
        return 4
    if f.container == "sequence" and f.is_nested and ros2types.is_known(f.type):
        inner = ros2types.fields(f.type)
        if inner and inner[0].type in stamped and inner[0].container == "":
            return 8
    return -1


@dataclass
class ChannelInfo:
    id: int
    key: str
    topic: str
    type: str
    schema_id: int
    stamp_at: int  # stamp_offset of its type


@dataclass
class _Stats:
    messages: int = 0
    start: int = 0
    end: int = 0
    per_channel: Counter[int] = field(default_factory=Counter)


class BagWriter:
    """One MCAP file of a rosbag2 bag, written by the recorder's worker (one thread)."""

    def __init__(self, directory: str | Path, index: int = 0, *, chunk_bytes: int = CHUNK_BYTES,
                 compression: str = "zstd", custom: dict[str, str] | None = None, describe: bool = True,
                 name: str | None = None) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / (name or FILE_PATTERN.format(index))
        self.chunk_bytes = chunk_bytes
        if compression not in ("zstd", ""):
            raise BagError(f"compression {compression!r}: expected zstd or '' (none)")
        self.compression = compression
        self._zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL) if compression == "zstd" else None
        self._f: BinaryIO = open(self.path, "wb")  # closed by close() or abandon()
        self._pos = 0
        self._schemas: dict[str, int] = {}
        self._schema_records: list[Schema] = []
        self._channels: dict[str, ChannelInfo] = {}
        self._channel_records: list[Channel] = []
        self._by_id: list[ChannelInfo | None] = [None]
        self._stamp_at = np.full(1, -1, np.int64)  # per channel id
        self._writers: dict[bytes, int] = {}
        self._new_writers: list[tuple[int, bytes, str, str]] = []  # index, gid, key, topic
        # queued samples: (key, payload, attachment (seq, source ns, gid) or NO_ATTACHMENT, receive ns)
        self._batch: list[tuple[str, bytes, tuple[int, int, bytes | None], int]] = []
        self.append = self._batch.append
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._stats = _Stats()
        self.written: Counter[str] = Counter()  # messages per key in the file (as of the last flush)
        self.closed = False
        self._write(MAGIC)
        rb = RecordBuilder()
        Header(profile=Profile.ROS2, library=LIBRARY).write(rb)
        self._write(rb.end())
        if describe:  # how to read this file's times and writers (a recovered file has its original's)
            self.add_metadata(BAG_METADATA, {"times": TIME_NOTE, "writers": (
            f"metadata '{WRITER_METADATA}' per writer (index, gid, key, topic); before each chunk an attachment "
            f"'{WRITERS_ATTACHMENT}': uint16 LE writer index per message of the chunk ({NO_WRITER}: none)"),
                **(custom or {})})

    # ------------------------------------------------------------------ low level
    def _write(self, data: bytes | bytearray | memoryview) -> None:
        self._f.write(data)
        self._pos += len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        rb = RecordBuilder()
        Metadata(name=name, metadata=data).write(rb)
        raw = rb.end()
        self._metadata_indexes.append(MetadataIndex(offset=self._pos, length=len(raw), name=name))
        self._write(raw)

    def _attachment(self, name: str, media_type: str, data: bytes, log_time: int, create_time: int) -> None:
        rb = RecordBuilder()
        Attachment(create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data).write(rb)
        raw = rb.end()
        self._attachment_indexes.append(AttachmentIndex(offset=self._pos, length=len(raw), log_time=log_time,
                                                        create_time=create_time, data_size=len(data), name=name,
                                                        media_type=media_type))
        self._write(raw)

    # ------------------------------------------------------------------ channels
    def channel(self, key: str) -> ChannelInfo:
        """The channel of ``key``, registered (schema and channel records written) on first use."""
        ch = self._channels.get(key)
        if ch is None:
            ch = self._register(key)
        return ch

    def _register(self, key: str) -> ChannelInfo:
        parts = key.split("/")
        try:
            topic = topic_name(key)
            ros_type = wire.ros_type_name(parts[-2])
            type_hash = parts[-1]
        except UnknownKey:  # not a ROS 2 data key: kept all the same, under a topic named after it
            topic, ros_type, type_hash = "/" + key.strip("/"), "", ""
        schema_id = 0
        if ros_type and ros2types.is_known(ros_type):
            schema_id = self._schema(ros_type, SchemaEncoding.ROS2, ros2types.full_definition(ros_type).encode())
        meta = {"offered_qos_profiles": qos_yaml(qos_profiles(topic)), "topic_type_hash": type_hash,
                "hilsim_key": key}
        return self._channel(key, topic, ros_type or "unknown", schema_id, MessageEncoding.CDR, meta)

    def _schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = self._schemas.get(name, 0)
        if not schema_id:
            schema_id = len(self._schema_records) + 1
            s = Schema(id=schema_id, name=name, encoding=encoding, data=data)
            self._schemas[name] = schema_id
            self._schema_records.append(s)
            rb = RecordBuilder()
            s.write(rb)
            self._write(rb.end())
        return schema_id

    def _channel(self, key: str, topic: str, ros_type: str, schema_id: int, encoding: str,
                 meta: dict[str, str]) -> ChannelInfo:
        cid = len(self._channel_records) + 1
        c = Channel(id=cid, topic=topic, message_encoding=encoding, schema_id=schema_id, metadata=meta)
        self._channel_records.append(c)
        rb = RecordBuilder()
        c.write(rb)
        self._write(rb.end())
        info = ChannelInfo(cid, key, topic, ros_type, schema_id,
                           stamp_offset(ros_type) if encoding == MessageEncoding.CDR else -1)
        self._channels[key] = info
        self._by_id.append(info)
        self._stamp_at = np.append(self._stamp_at, info.stamp_at)
        return info

    def json_channel(self, topic: str, schema_name: str, schema: dict[str, Any]) -> ChannelInfo:
        """A channel of JSON messages (``message_encoding`` json, a ``jsonschema`` schema): what
        ``hilsim export`` writes for rows that make no ROS 2 message. Its key is ``json:<topic>``."""
        sid = self._schema(schema_name, SchemaEncoding.JSONSchema, json.dumps(schema).encode())
        return self._channel(f"json:{topic}", topic, schema_name, sid, MessageEncoding.JSON, {})

    def declare_channel(self, c: Channel, schema: Schema | None) -> ChannelInfo:
        """A channel (and its schema) as another file had them, ids kept (recovery)."""
        if schema is not None and schema.name not in self._schemas:
            s = Schema(id=schema.id, name=schema.name, encoding=schema.encoding, data=schema.data)
            self._schemas[schema.name] = schema.id
            self._schema_records.append(s)
            rb = RecordBuilder()
            s.write(rb)
            self._write(rb.end())
        self._channel_records.append(c)
        rb = RecordBuilder()
        c.write(rb)
        self._write(rb.end())
        ros_type = schema.name if schema is not None else "unknown"
        info = ChannelInfo(c.id, c.metadata.get("hilsim_key", c.topic), c.topic, ros_type, c.schema_id,
                           stamp_offset(ros_type) if schema is not None else -1)
        self._channels[info.key] = info
        while len(self._by_id) <= c.id:
            self._by_id.append(None)
            self._stamp_at = np.append(self._stamp_at, -1)
        self._by_id[c.id] = info
        self._stamp_at[c.id] = info.stamp_at
        return info

    def declare_writer(self, index: int, gid: bytes, key: str, topic: str) -> None:
        """A writer as another file named it, index kept (recovery)."""
        self._writers[gid] = index
        self._new_writers.append((index, gid, key, topic))

    # ------------------------------------------------------------------ messages
    def add(self, key: str, data: bytes, log_ns: int, seq: int = 0, gid: bytes | None = None) -> None:
        """Queue one sample: ``data`` its raw CDR payload, ``log_ns`` when it was received, ``seq`` and
        ``gid`` from its attachment (``gid`` None: it had none). Written by the next :meth:`flush`.
        The recorder's worker appends ``(key, payload, attachment, receive ns)`` to :attr:`append`
        itself (an attachment is ``(seq, source ns, gid)``; :data:`NO_ATTACHMENT` for none)."""
        self.append((key, data, NO_ATTACHMENT if gid is None else (seq, 0, gid), log_ns))

    def add_to(self, ch: ChannelInfo, data: bytes, log_ns: int) -> None:
        """Queue a message on a channel of this file (no attachment), e.g. a :meth:`json_channel`'s."""
        self.append((ch.key, data, NO_ATTACHMENT, log_ns))

    @property
    def pending(self) -> int:
        return len(self._batch)

    @property
    def size(self) -> int:
        """Bytes written to the file so far."""
        return self._pos

    @property
    def messages(self) -> int:
        """Messages written to the file so far (as of the last flush)."""
        return self._stats.messages

    def flush(self) -> Counter[str]:
        """Write every queued message (chunks of at most ``chunk_bytes``) and flush the file to the
        OS; returns how many messages per key this flush wrote. The per-message work is C loops
        (``zip``, ``map``, ``np.fromiter``) over the batch, the rest numpy per chunk."""
        batch = self._batch[:]
        self._batch.clear()
        out: Counter[str] = Counter()
        if batch:
            n = len(batch)
            # columns by C-level maps: zip(*batch) makes an iterator per sample (GC work, 4x slower here)
            keys, data, atts = list(map(_KEY, batch)), list(map(_DATA, batch)), list(map(_ATT, batch))
            chans = self._channels
            for k in set(keys).difference(chans):
                self._register(k)
            cid = {k: c.id for k, c in chans.items()}
            ch = np.fromiter(map(cid.__getitem__, keys), np.uint16, n)
            gids = list(map(_GID, atts))
            known = self._writers
            for g in set(gids).difference(known):
                if g is None:
                    continue
                if len(known) >= NO_WRITER:
                    raise BagError(f"more than {NO_WRITER - 1} writers")
                k = keys[gids.index(g)]
                known[g] = len(known)
                self._new_writers.append((known[g], g, k, chans[k].topic))
            wmap = {None: NO_WRITER, **known}
            self.write_chunks(ch, np.fromiter(map(_SEQ, atts), np.uint64, n).astype(np.uint32),
                              np.fromiter(map(wmap.__getitem__, gids), np.uint16, n),
                              np.fromiter(map(_LOG, batch), np.uint64, n),
                              None, data)
            for c, k in zip(*np.unique(ch, return_counts=True), strict=True):
                info = self._by_id[int(c)]
                assert info is not None
                out[info.key] += int(k)
            self.written.update(out)
        self._f.flush()
        return out

    def _stamps(self, records: bytearray, ch: np.ndarray, offsets: np.ndarray, lens: np.ndarray) -> None:
        """Set each message's publish time to its sim-time stamp, read from its CDR bytes (little-endian
        encapsulation) in one numpy pass over the chunk's records; where its type has none or the
        payload is too short for it, the receive time (already there) stays."""
        at = self._stamp_at[ch]
        ok = (at >= 0) & (lens >= at + 8)
        if not ok.any():
            return
        buf = np.frombuffer(records, np.uint8)
        starts = offsets.astype(np.int64) + _HEAD  # the payloads
        ok[ok] &= buf[starts[ok] + 1] == 1  # CDR_LE (00 01): the stamp is little endian
        seq_stamp = ok & (at == 8)
        if seq_stamp.any():  # a sequence of stamped messages: there must be one
            count = buf[(starts[seq_stamp] + 4)[:, None] + np.arange(4)].copy().view("<u4")[:, 0]
            ok[seq_stamp] = count > 0
        if not ok.any():
            return
        raw = buf[(starts + at)[ok][:, None] + np.arange(8)].copy()
        stamp = raw[:, :4].copy().view("<i4")[:, 0].astype(np.int64) * 1_000_000_000
        stamp += raw[:, 4:].copy().view("<u4")[:, 0]
        good = stamp >= 0
        where = (offsets.astype(np.int64)[ok][good] + _PUB_AT)[:, None] + np.arange(8)
        buf[where] = stamp[good].astype("<u8").view(np.uint8).reshape(-1, 8)

    def write_chunks(self, ch: np.ndarray, seq: np.ndarray, w: np.ndarray, log: np.ndarray, pub: np.ndarray | None,
                     data: Sequence[bytes]) -> None:
        """Write messages (arrays of equal length, ``data`` their payloads) as chunks of at most
        ``chunk_bytes``, each after its writers' records and writer-index attachment; ``pub`` None:
        each message's publish time is read from its payload (:meth:`_stamps`)."""
        lens = np.fromiter(map(len, data), np.int64, len(data))
        size = lens + _HEAD
        ends = np.cumsum(size)
        cut = 0
        while cut < len(data):
            stop = int(np.searchsorted(ends, ends[cut] - size[cut] + self.chunk_bytes, side="right"))
            stop = max(stop, cut + 1)
            self._chunk(ch[cut:stop], seq[cut:stop], w[cut:stop], log[cut:stop],
                        None if pub is None else pub[cut:stop], data[cut:stop], lens[cut:stop])
            cut = stop

    def _chunk(self, ch: np.ndarray, seq: np.ndarray, w: np.ndarray, log: np.ndarray, pub: np.ndarray | None,
               data: Sequence[bytes], lens: np.ndarray) -> None:
        n = len(data)
        head = np.empty(n, _MSG_HEAD)
        head["op"] = Opcode.MESSAGE
        head["len"] = lens + (_HEAD - 9)
        head["ch"] = ch
        head["seq"] = seq
        head["log"] = log
        head["pub"] = log if pub is None else pub
        hb = head.tobytes()
        parts: list[bytes] = [b""] * (2 * n)
        parts[0::2] = [hb[i:i + _HEAD] for i in range(0, n * _HEAD, _HEAD)]
        parts[1::2] = data
        records = bytearray().join(parts)
        offsets = np.zeros(n, np.uint64)
        np.cumsum((lens + _HEAD)[:-1], out=offsets[1:])
        if pub is None:
            self._stamps(records, ch, offsets, lens)
        start, end = int(log.min()), int(log.max())
        # who wrote each message: the new writers' records, then the index of this chunk
        for index, gid, key, topic in self._new_writers:
            self.add_metadata(WRITER_METADATA, {"index": str(index), "gid": gid.hex(), "key": key, "topic": topic})
        self._new_writers.clear()
        self._attachment(WRITERS_ATTACHMENT, WRITERS_MEDIA_TYPE, w.astype("<u2").tobytes(), start, end)
        compressed = self._zstd.compress(records) if self._zstd is not None else records
        comp = self.compression.encode()
        body_len = 8 + 8 + 8 + 4 + 4 + len(comp) + 8 + len(compressed)
        chunk_start = self._pos
        self._write(_CHUNK_HEAD.pack(Opcode.CHUNK, body_len, start, end, len(records), zlib.crc32(records))
                    + struct.pack("<I", len(comp)) + comp + struct.pack("<Q", len(compressed)))
        self._write(compressed)
        chunk_len = self._pos - chunk_start
        # message indexes: per channel, (log time, offset in the chunk) of each of its messages
        index_start = self._pos
        index_offsets: dict[int, int] = {}
        order = np.argsort(ch, kind="stable")
        ids, first, counts = np.unique(ch[order], return_index=True, return_counts=True)
        pairs = np.empty((n, 2), "<u8")
        pairs[:, 0] = log[order]
        pairs[:, 1] = offsets[order]
        out = bytearray()
        for cid, f, k in zip(ids.tolist(), first.tolist(), counts.tolist(), strict=True):
            index_offsets[cid] = index_start + len(out)
            out += _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + 16 * k, cid, 16 * k)
            out += pairs[f:f + k].tobytes()
            self._stats.per_channel[cid] += k
        self._write(out)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_start, chunk_length=chunk_len,
            message_index_offsets=index_offsets, message_index_length=len(out), compression=self.compression,
            compressed_size=len(compressed), uncompressed_size=len(records)))
        st = self._stats
        st.start = start if st.messages == 0 else min(st.start, start)
        st.end = max(st.end, end)
        st.messages += n

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Flush, then write the summary section and footer: the file is complete. Safe to call twice."""
        if self.closed:
            return
        self.flush()
        self.closed = True
        rb = RecordBuilder()
        DataEnd(data_section_crc=0).write(rb)
        self._write(rb.end())
        summary_start = self._pos
        sb = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: Iterable[Any]) -> None:
            start = sb.count
            for r in records:
                r.write(sb)
            if sb.count > start:
                offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                             group_length=sb.count - start))

        st = self._stats
        stats = Statistics(message_count=st.messages, schema_count=len(self._schema_records),
                           channel_count=len(self._channel_records), attachment_count=len(self._attachment_indexes),
                           metadata_count=len(self._metadata_indexes), chunk_count=len(self._chunk_indexes),
                           message_start_time=st.start, message_end_time=st.end,
                           channel_message_counts=dict(st.per_channel))
        group(Opcode.SCHEMA, self._schema_records)
        group(Opcode.CHANNEL, self._channel_records)
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        offset_start = summary_start + sb.count
        for o in offsets:
            o.write(sb)
        summary = sb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
        self._write(summary)
        rb = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc).write(rb)
        self._write(rb.end())
        self._write(MAGIC)
        self._f.close()

    def abandon(self) -> None:
        """Close the file as it is (no summary): what a killed writer leaves (tests)."""
        if not self.closed:
            self.closed = True
            self._f.close()

    @property
    def channels(self) -> dict[str, ChannelInfo]:
        return dict(self._channels)
