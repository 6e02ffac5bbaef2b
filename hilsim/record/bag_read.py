"""Reading hilsim's rosbag2 bags back: messages with their writers, ``metadata.yaml``, recovery, info.

- :func:`open_bag` finds a bag (a run directory, its ``bag/``, or one ``.mcap`` file) and reads it
  record by record, as far as its records are whole: a file whose writer was killed (no summary,
  no footer, maybe a record cut in the middle) reads up to its last whole chunk. Messages come in
  file order with their channel, receive time, sim-time stamp, sequence number and writer gid
  (the layout is :mod:`hilsim.record.bag`'s).
- :func:`write_metadata` writes ``metadata.yaml`` in rosbag2's format (version 9, Jazzy) from the
  files' own contents, so ``ros2 bag info``, ``ros2 bag play`` and ``rosbags.rosbag2.Reader``
  open the directory.
- :func:`recover_bag` rewrites every file of a bag that lacks its footer from the chunks that
  reached the disk whole (schemas, channels, writers and messages kept, ids unchanged), checks
  that the rewritten file reads back with the same messages, replaces it, and regenerates
  ``metadata.yaml``.
- :func:`info` is ``hilsim bag info``: topics, types, counts, duration, start and end, as
  ``ros2 bag info`` prints them, plus the sim-time span and the writers.
"""

from __future__ import annotations

import io
import os
import struct
import time
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import lz4.frame
import numpy as np
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Footer, Header, Metadata, Schema

from hilsim.record.bag import (
    MAGIC,
    NO_WRITER,
    WRITER_METADATA,
    WRITERS_ATTACHMENT,
    BagError,
    BagWriter,
    stamp_offset,
)

BAG_DIR = "bag"  # in a run directory
METADATA_NAME = "metadata.yaml"
ROSBAG2_VERSION = 9  # metadata.yaml as rosbag2 in Jazzy writes it
_MSG = struct.Struct("<BQHIQQ")  # a message record's fixed part (opcode, length, channel, seq, log, publish)
_REC = struct.Struct("<BQ")


class BagMessage(NamedTuple):
    topic: str
    key: str  # the Zenoh key it was recorded from (channel metadata), else ""
    type: str  # pkg/msg/Type
    log_ns: int  # when the recorder received it (ns since the UNIX epoch)
    pub_ns: int  # its sim-time stamp
    seq: int  # its rmw_zenoh sequence number (low 32 bits)
    gid: bytes | None  # its writer's gid; None if it came without an attachment (or the index is lost)
    data: bytes  # the raw CDR payload (a JSON channel of ``hilsim export``: JSON text)
    encoding: str = "cdr"  # the channel's message encoding


@dataclass
class BagFile:
    """One MCAP file read as far as it is whole."""

    path: Path
    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    writers: dict[int, bytes] = field(default_factory=dict)  # index -> gid
    metadata: list[Metadata] = field(default_factory=list)
    # per chunk: (channel ids, sequences, writer indexes, log times, publish times, payloads)
    chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[bytes]]] = field(
        default_factory=list)
    complete: bool = False  # a footer and the closing magic were read
    cut_at: int | None = None  # where the whole records end, if not complete
    size: int = 0

    @property
    def message_count(self) -> int:
        return sum(len(c[0]) for c in self.chunks)

    def counts(self) -> Counter[int]:
        """Messages per channel id."""
        out: Counter[int] = Counter()
        for c in self.chunks:
            ids, n = np.unique(c[0], return_counts=True)
            out.update(dict(zip(ids.tolist(), n.tolist(), strict=True)))
        return out

    def type_of(self, cid: int) -> str:
        s = self.schemas.get(self.channels[cid].schema_id)
        return s.name if s is not None else "unknown"

    def messages(self) -> Iterator[BagMessage]:
        """Every message in file order."""
        info = {cid: (c.topic, c.metadata.get("hilsim_key", ""), self.type_of(cid), c.message_encoding)
                for cid, c in self.channels.items()}
        gids = self.writers
        for ch, seq, w, log, pub, data in self.chunks:
            for c, s, wi, lt, pt, d in zip(ch.tolist(), seq.tolist(), w.tolist(), log.tolist(), pub.tolist(), data,
                                           strict=True):
                topic, key, typ, enc = info[c]
                yield BagMessage(topic, key, typ, lt, pt, s, gids.get(wi), d, enc)


# ---------------------------------------------------------------------------------------- reading
def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise BagError(f"chunk compression {chunk.compression!r} is not supported")
    if len(data) != chunk.uncompressed_size or (chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc):
        raise BagError("a chunk's data does not match its size or CRC")
    return data


def _chunk_messages(bf: BagFile, data: bytes, writers: np.ndarray | None) -> None:
    chs: list[int] = []
    seqs: list[int] = []
    logs: list[int] = []
    pubs: list[int] = []
    payloads: list[bytes] = []
    pos, end = 0, len(data)
    unpack, mv = _MSG.unpack_from, memoryview(data)
    while pos + 9 <= end:
        op, length = _REC.unpack_from(data, pos)
        if pos + 9 + length > end:
            raise BagError("a record runs past the end of its chunk")
        if op == Opcode.MESSAGE:
            _, _, c, s, lt, pt = unpack(data, pos)
            chs.append(c)
            seqs.append(s)
            logs.append(lt)
            pubs.append(pt)
            payloads.append(bytes(mv[pos + 31: pos + 9 + length]))
        elif op == Opcode.SCHEMA:
            s_ = Schema.read(ReadDataStream(io.BytesIO(data[pos + 9: pos + 9 + length])))
            bf.schemas[s_.id] = s_
        elif op == Opcode.CHANNEL:
            c_ = Channel.read(ReadDataStream(io.BytesIO(data[pos + 9: pos + 9 + length])))
            bf.channels[c_.id] = c_
        pos += 9 + length
    n = len(chs)
    w = writers if writers is not None and len(writers) == n else np.full(n, NO_WRITER, np.uint16)
    bf.chunks.append((np.array(chs, np.uint16), np.array(seqs, np.uint32), w, np.array(logs, np.uint64),
                      np.array(pubs, np.uint64), payloads))


def read_file(path: str | Path) -> BagFile:
    """Read one MCAP file record by record, up to the last whole record (a chunk must also
    decompress and match its CRC); :attr:`BagFile.complete` says whether it ended properly."""
    p = Path(path)
    bf = BagFile(p)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise BagError(f"{p}: cannot read: {e.strerror}") from None
    bf.size = len(raw)
    if raw[:8] != MAGIC:
        raise BagError(f"{p}: not an MCAP file (no MCAP magic at its start)")
    pos, end = 8, len(raw)
    pending_writers: np.ndarray | None = None
    while True:
        if pos + 9 > end:
            bf.cut_at = pos
            break
        op, length = _REC.unpack_from(raw, pos)
        body_at, nxt = pos + 9, pos + 9 + length
        if nxt > end:
            bf.cut_at = pos
            break
        body = raw[body_at:nxt]
        try:
            stream = ReadDataStream(io.BytesIO(body))
            if op == Opcode.HEADER:
                bf.header = Header.read(stream)
            elif op == Opcode.SCHEMA:
                s = Schema.read(stream)
                bf.schemas[s.id] = s
            elif op == Opcode.CHANNEL:
                c = Channel.read(stream)
                bf.channels[c.id] = c
            elif op == Opcode.METADATA:
                m = Metadata.read(stream)
                bf.metadata.append(m)
                if m.name == WRITER_METADATA:
                    bf.writers[int(m.metadata["index"])] = bytes.fromhex(m.metadata["gid"])
            elif op == Opcode.ATTACHMENT:
                a = Attachment.read(stream)
                if a.name == WRITERS_ATTACHMENT:
                    pending_writers = np.frombuffer(a.data, "<u2").astype(np.uint16)
            elif op == Opcode.CHUNK:
                _chunk_messages(bf, _decompress(Chunk.read(stream)), pending_writers)
                pending_writers = None
            elif op == Opcode.MESSAGE:  # outside any chunk (another writer's file)
                _chunk_messages(bf, raw[pos:nxt], None)
            elif op == Opcode.FOOTER:
                Footer.read(stream)
                bf.complete = raw[nxt:nxt + 8] == MAGIC
                if not bf.complete:
                    bf.cut_at = pos
                break
        except Exception:  # a damaged record: the file is whole up to here
            bf.cut_at = pos
            break
        pos = nxt
    if bf.header is None:
        raise BagError(f"{p}: no MCAP header record: not a bag, or cut before anything was written")
    return bf


@dataclass
class Bag:
    """A bag directory (or one .mcap file) and its files, read."""

    path: Path  # the directory (or the file given)
    files: list[BagFile]

    @property
    def complete(self) -> bool:
        return all(f.complete for f in self.files)

    def messages(self) -> Iterator[BagMessage]:
        for f in self.files:
            yield from f.messages()

    @property
    def message_count(self) -> int:
        return sum(f.message_count for f in self.files)

    def topic_counts(self) -> Counter[tuple[str, str]]:
        """Messages per (topic, type)."""
        out: Counter[tuple[str, str]] = Counter()
        for f in self.files:
            for cid, n in f.counts().items():
                out[(f.channels[cid].topic, f.type_of(cid))] += n
        return out

    def key_counts(self) -> Counter[str]:
        """Messages per Zenoh key (channel metadata ``hilsim_key``; the topic where it has none)."""
        out: Counter[str] = Counter()
        for f in self.files:
            for cid, n in f.counts().items():
                c = f.channels[cid]
                out[c.metadata.get("hilsim_key", c.topic)] += n
        return out


def _file_index(p: Path) -> int:
    stem = p.stem.rsplit("_", 1)[-1]
    return int(stem) if stem.isdigit() else 0


def bag_paths(path: str | Path) -> tuple[Path, list[Path]]:
    """(the bag directory, its .mcap files in order) for a run directory, a bag directory or one
    .mcap file; :class:`BagError` (one line) if there is none."""
    p = Path(path)
    if p.is_file():
        return p.parent, [p]
    if p.is_dir() and (p / BAG_DIR).is_dir() and not list(p.glob("*.mcap")):
        p = p / BAG_DIR
    if not p.is_dir():
        raise BagError(f"{path}: no such bag (a run directory, its bag/ directory or an .mcap file)")
    files = sorted(p.glob("*.mcap"), key=lambda f: (_file_index(f), f.name))
    if not files:
        raise BagError(f"{path}: no .mcap file in {p} (not a bag)")
    return p, files


def open_bag(path: str | Path) -> Bag:
    d, files = bag_paths(path)
    return Bag(d if Path(path).is_dir() else Path(path), [read_file(f) for f in files])


def key_counts(path: str | Path) -> Counter[str]:
    """Messages per Zenoh key in a bag, counted in its files: from each complete file's summary
    (its statistics), else by reading the file as far as it is whole."""
    _, files = bag_paths(path)
    out: Counter[str] = Counter()
    for f in files:
        summary = None
        try:
            with open(f, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # no footer, no summary: read it
            summary = None
        if summary is None or summary.statistics is None:
            out.update(open_bag(f).key_counts())
            continue
        for cid, n in summary.statistics.channel_message_counts.items():
            c = summary.channels[cid]
            out[c.metadata.get("hilsim_key", c.topic)] += n
    return out


# ---------------------------------------------------------------------------------------- metadata.yaml
def _qos_list(c: Channel) -> list[dict[str, Any]]:
    text = c.metadata.get("offered_qos_profiles", "")
    if not text:
        return []
    try:
        got = yaml.safe_load(text)
    except yaml.YAMLError:
        return []
    return got if isinstance(got, list) else []


@dataclass
class FileSummary:
    """What ``metadata.yaml`` says of one file: its channels and their types, messages per channel and
    the span of its receive times (CDR channels only)."""

    name: str
    channels: dict[int, Channel]
    types: dict[int, str]
    counts: Counter[int]
    start: int
    stop: int

    @property
    def cdr(self) -> bool:
        """Whether rosbag2 can list it: it has channels, every one CDR (not ``hilsim export``'s JSON rows)."""
        return bool(self.channels) and all(c.message_encoding == "cdr" for c in self.channels.values())

    @classmethod
    def of(cls, f: BagFile) -> FileSummary:
        cdr = np.array([cid for cid, c in f.channels.items() if c.message_encoding == "cdr"], np.uint16)
        logs = [a for a in (c[3][np.isin(c[0], cdr)] for c in f.chunks) if len(a)]
        start = int(min(int(a.min()) for a in logs)) if logs else 0
        stop = int(max(int(a.max()) for a in logs)) if logs else 0
        return cls(f.path.name, dict(f.channels), {cid: f.type_of(cid) for cid in f.channels}, f.counts(), start, stop)


def file_summary(path: Path) -> FileSummary:
    """A file's :class:`FileSummary`, from its MCAP summary section if it is complete (a seek to its
    footer: a split bag's earlier files are not read again at each split), else read as far as it is whole."""
    try:
        with open(path, "rb") as fh:
            s = make_reader(fh).get_summary()
    except Exception:  # no footer (a killed writer): read it
        s = None
    if s is None or s.statistics is None:
        return FileSummary.of(read_file(path))
    st = s.statistics
    types = {cid: (s.schemas[c.schema_id].name if c.schema_id in s.schemas else "unknown")
             for cid, c in s.channels.items()}
    counts: Counter[int] = Counter({cid: n for cid, n in st.channel_message_counts.items() if n})
    n = st.message_count
    return FileSummary(path.name, dict(s.channels), types, counts, st.message_start_time if n else 0,
                       st.message_end_time if n else 0)


def metadata_dict(bag: Bag | list[FileSummary], custom: dict[str, str] | None = None) -> dict[str, Any]:
    """``metadata.yaml``'s content for a bag (rosbag2 version 9): times are log times (receive).
    Only files of CDR channels are listed (rosbag2 and rosbags know no other): the JSON rows of
    ``hilsim export`` (a file of their own) are for MCAP readers (Foxglove) alone. A bag split into
    several files (``logger.max_bag_size``, a restarted recorder) lists them all, in order."""
    summaries = [FileSummary.of(f) for f in bag.files] if isinstance(bag, Bag) else bag
    topics: dict[tuple[str, str], dict[str, Any]] = {}
    files = []
    t0s, t1s = [], []
    total = 0
    listed = [f for f in summaries if f.cdr]
    for f in listed:
        n = sum(f.counts.values())
        total += n
        if n:
            t0s.append(f.start)
            t1s.append(f.stop)
        files.append({"path": f.name, "starting_time": {"nanoseconds_since_epoch": f.start},
                      "duration": {"nanoseconds": f.stop - f.start}, "message_count": n})
        for cid, c in sorted(f.channels.items()):
            t = (c.topic, f.types[cid])
            entry = topics.setdefault(t, {"topic_metadata": {
                "name": c.topic, "type": t[1], "serialization_format": c.message_encoding,
                "offered_qos_profiles": _qos_list(c),
                "type_description_hash": c.metadata.get("topic_type_hash", "")}, "message_count": 0})
            entry["message_count"] += f.counts.get(cid, 0)
    start = min(t0s) if t0s else 0
    return {"rosbag2_bagfile_information": {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": (max(t1s) - start) if t1s else 0},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [topics[k] for k in sorted(topics)],
        "compression_format": "",  # MCAP compresses its chunks itself: no rosbag2 file or message compression
        "compression_mode": "",
        "relative_file_paths": [f.name for f in listed],
        "files": files,
        "custom_data": custom or {},
        "ros_distro": "jazzy",  # the type descriptions and hashes are Jazzy's (REP 2016)
    }}


def write_metadata(path: str | Path, custom: dict[str, str] | None = None) -> Path:
    """(Re)write ``<bag>/metadata.yaml`` from the bag's files (atomically); returns its path. A complete
    file is summarised from its MCAP summary, one without a footer read as far as it is whole."""
    d, files = bag_paths(path)
    if not custom:
        old = d / METADATA_NAME
        if old.is_file():
            try:
                custom = yaml.safe_load(old.read_text())["rosbag2_bagfile_information"].get("custom_data") or None
            except (yaml.YAMLError, KeyError, TypeError):
                custom = None
    out = d / METADATA_NAME
    tmp = out.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump(metadata_dict([file_summary(f) for f in files], custom), sort_keys=False,
                                  default_flow_style=False))
    tmp.replace(out)
    return out


# ---------------------------------------------------------------------------------------- recovery
@dataclass
class Recovered:
    path: Path
    rewritten: bool  # False: it was complete already
    messages: int
    dropped_bytes: int  # bytes after the last whole record (a record cut by the kill)


def recover_file(path: str | Path) -> Recovered:
    """Make one MCAP file of a bag whole again if its writer was killed (see the module docstring);
    a complete file is left alone. :class:`BagError` if nothing of it can be read, or the rewrite
    would lose a message (the original is then kept)."""
    p = Path(path)
    bf = read_file(p)
    if bf.complete:
        return Recovered(p, False, bf.message_count, 0)
    tmp_dir = p.with_name(p.name + ".recovering")
    tmp_dir.mkdir(exist_ok=True)
    try:
        w = BagWriter(tmp_dir, index=0, describe=False)  # the original's metadata records are copied below
        for _, c in sorted(bf.channels.items()):
            w.declare_channel(c, bf.schemas.get(c.schema_id))
        for m in bf.metadata:
            if m.name == WRITER_METADATA:
                w.declare_writer(int(m.metadata["index"]), bytes.fromhex(m.metadata["gid"]), m.metadata.get("key", ""),
                                 m.metadata.get("topic", ""))
            else:
                w.add_metadata(m.name, dict(m.metadata))
        for ch, seq, wi, log, pub, data in bf.chunks:
            if len(data):
                w.write_chunks(ch, seq, wi, log, pub, data)
        w.close()
        again = read_file(w.path)
        if not again.complete or again.message_count != bf.message_count:
            raise BagError(f"{p}: the rewritten file holds {again.message_count} of {bf.message_count} messages; "
                           "the original is kept")
        os.replace(w.path, p)
    finally:
        for f in tmp_dir.glob("*"):
            f.unlink()
        tmp_dir.rmdir()
    return Recovered(p, True, bf.message_count, bf.size - (bf.cut_at or bf.size))


def recover_bag(path: str | Path) -> list[Recovered]:
    """Recover every file of a bag (:func:`recover_file`), then regenerate its ``metadata.yaml``."""
    d, files = bag_paths(path)
    done = [recover_file(f) for f in files]
    write_metadata(d)
    return done


# ---------------------------------------------------------------------------------------- info
def _human_size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"


def _when(ns: int) -> str:
    s = ns / 1e9
    return time.strftime("%b %d %Y %H:%M:%S", time.localtime(s)) + f".{ns % 1_000_000_000:09d}"[:4] + f" ({s:.9f})"


def info(path: str | Path) -> str:
    """``hilsim bag info``: what a bag holds, laid out like ``ros2 bag info``."""
    bag = open_bag(path)
    logs = [c[3] for f in bag.files for c in f.chunks if len(c[3])]
    # sim time: the stamps of the stamped types (the others' publish time is their receive time)
    pubs = []
    for f in bag.files:
        stamped = np.array([cid for cid in f.channels if stamp_offset(f.type_of(cid)) >= 0], np.uint16)
        pubs += [c[4][np.isin(c[0], stamped)] for c in f.chunks]
    pubs = [a for a in pubs if len(a)]
    start = int(min(int(a.min()) for a in logs)) if logs else 0
    end = int(max(int(a.max()) for a in logs)) if logs else 0
    size = sum(f.size for f in bag.files)
    counts = bag.topic_counts()
    names = {}
    for f in bag.files:
        for cid, c in f.channels.items():
            names[(c.topic, f.type_of(cid))] = c.message_encoding
    lines = [
        f"Files:             {', '.join(str(f.path.name) for f in bag.files)}",
        f"Bag size:          {_human_size(size)}",
        "Storage id:        mcap",
        "ROS Distro:        jazzy",
        f"Duration:          {(end - start) / 1e9:.9f}s",
        f"Start:             {_when(start) if logs else '-'}",
        f"End:               {_when(end) if logs else '-'}",
        f"Messages:          {bag.message_count}",
    ]
    if pubs:
        p0 = int(min(int(a.min()) for a in pubs))
        p1 = int(max(int(a.max()) for a in pubs))
        lines.append(f"Sim time:          {p0 / 1e9:.6f} s to {p1 / 1e9:.6f} s (publish times)")
    lines.append(f"Writers:           {sum(len(f.writers) for f in bag.files)}")
    topic_lines = [f"Topic: {t} | Type: {ty} | Count: {counts[(t, ty)]} | Serialization Format: {names[(t, ty)]}"
                   for t, ty in sorted(names)]
    lines.append("Topic information: " + ("\n" + " " * 19).join(topic_lines))
    if not bag.complete:
        cut = [f for f in bag.files if not f.complete]
        lines.append(f"INCOMPLETE:        {', '.join(f.path.name for f in cut)} ended without a footer (its writer "
                     f"was killed?): shown as far as it is whole; `hilsim bag recover {bag.path}` makes it whole")
    return "\n".join(lines)
