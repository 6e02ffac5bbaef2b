"""How large a run's recording may grow: the bag split into files, a cap, and the free disk.

- :class:`BagSeries` is the recorder's bag as rosbag2 writes a split one: ``bag_0.mcap``,
  ``bag_1.mcap``, … in one directory, a new file once the current one holds ``max_size`` bytes or
  spans ``max_duration`` seconds of receive time (rosbag2's ``--max-bag-size`` and
  ``--max-bag-duration``; checked as each batch reaches the file, twice a second). Each file is a
  complete MCAP file of its own (schemas, channels and writers declared again in it, summary and
  footer), closed as the next opens, and ``metadata.yaml`` is rewritten at each split to list every
  closed file: the directory is one bag for ``ros2 bag``, ``rosbags``, ``hilsim play`` and
  ``hilsim bag info`` (:mod:`hilsim.record.bag_read` reads the files in order) at every moment of
  the run, the file being written aside.
- :class:`RrdSeries` is the recorder's Rerun recording split the same way (``logger.max_rrd_size``,
  ``max_rrd_duration``): ``recording.rrd``, then ``recording.part-1.rrd``, … (the file sink of the
  one recording stream moved to the next file after a flush, :func:`hilsim.core.recording.split_name`).
  Each file is closed whole (Rerun writes its footer as the sink is replaced) and holds every row
  flushed before the split; all of them are one recording (one recording id), which Rerun's viewer
  opens as one (``rerun recording*.rrd``). The model, the world and the latched samples are in the
  first file, so a later part alone shows no robot: open the parts together.
- :func:`stop_reason` says when the recorder must stop recording: the run's recording (the
  ``.rrd`` and the bag together) reached ``logger.max_size``, or the free space of the file system
  the run directory is on fell below ``logger.min_free``. The recorder then closes its files whole
  and stops receiving; the simulation goes on (``services/logger.py``).

Reads and writes no Zenoh key: only the bag's directory and the run directory's ``.rrd`` files.
"""

from __future__ import annotations

import shutil
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from hilsim.core.recording import split_name
from hilsim.record.bag import FILE_PATTERN, BagWriter
from hilsim.record.bag_read import write_metadata


def human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"


class BagSeries:
    """The bag of one recorder process: a :class:`BagWriter` per file, split by size and duration."""

    def __init__(self, directory: str | Path, index: int = 0, *, max_size: int = 0, max_duration: float = 0.0,
                 custom: dict[str, str] | None = None, metadata: dict[str, str] | None = None) -> None:
        self.dir = Path(directory)
        self.max_size, self.max_duration = max_size, max_duration
        self.custom = custom
        self.metadata = metadata  # metadata.yaml's custom_data
        self.closed_bytes = 0  # bytes of this process's files closed so far
        self.splits = 0
        self.files: list[Path] = []
        self.writer = self._open(index)
        self._first_ns: int | None = None  # receive time of the current file's first message

    def _open(self, index: int) -> BagWriter:
        while (self.dir / FILE_PATTERN.format(index)).exists():  # a restarted recorder's predecessors' files
            index += 1
        w = BagWriter(self.dir, index, custom=self.custom)
        self.index = index
        self.files.append(w.path)
        return w

    @property
    def path(self) -> Path:
        """The file being written."""
        return self.writer.path

    @property
    def append(self):  # type: ignore[no-untyped-def]
        """The current file's queue (:attr:`BagWriter.append`); it changes at a split."""
        return self.writer.append

    @property
    def size(self) -> int:
        """Bytes this process wrote to the bag, every file of it."""
        return self.closed_bytes + self.writer.size

    def add(self, key: str, data: bytes, log_ns: int, seq: int = 0, gid: bytes | None = None) -> None:
        """Queue one sample in the current file (:meth:`BagWriter.add`)."""
        self.writer.add(key, data, log_ns, seq, gid)

    def flush(self) -> Counter[str]:
        """Write the queued messages (:meth:`BagWriter.flush`), then start the next file if the current
        one is as large or as long as allowed; returns the messages per key written."""
        w = self.writer
        wrote = w.flush()
        if wrote and self._first_ns is None:
            self._first_ns = time.time_ns()
        if self._first_ns is not None and (
                (self.max_size and w.size >= self.max_size)
                or (self.max_duration and time.time_ns() - self._first_ns >= self.max_duration * 1e9)):
            self.split()
        return wrote

    def split(self) -> None:
        """Close the current file whole, list it in ``metadata.yaml``, write on in the next one."""
        w = self.writer
        w.close()
        self.closed_bytes += w.size
        write_metadata(self.dir, self.metadata)
        self.writer = self._open(self.index + 1)
        self._first_ns = None
        self.splits += 1

    def close(self) -> None:
        """Close the current file (a file of a split that received nothing is removed) and write
        ``metadata.yaml`` over every file of the bag."""
        w = self.writer
        w.close()
        if len(self.files) > 1 and w.messages == 0:
            w.path.unlink()
            self.files.pop()
        else:
            self.closed_bytes += w.size
        write_metadata(self.dir, self.metadata)

    def abandon(self) -> None:
        self.writer.abandon()


class RrdSeries:
    """The ``.rrd`` files of one recorder process, split by size and duration as the bag is.

    ``move(path)`` points the recording stream's file sink at ``path`` (closing the current file whole);
    :meth:`after_flush` is called once every buffered row reached the file."""

    def __init__(self, first: str | Path, move: Callable[[Path], None], *, max_size: int = 0,
                 max_duration: float = 0.0) -> None:
        self.first = Path(first)
        self.files: list[Path] = [self.first]
        self._move = move
        self.max_size, self.max_duration = max_size, max_duration
        self.closed_bytes = 0  # bytes of this process's files closed so far
        self._first_ns: int | None = None  # wall time of the current file's first flush

    @property
    def path(self) -> Path:
        """The file being written."""
        return self.files[-1]

    def current_size(self) -> int:
        try:
            return self.path.stat().st_size
        except OSError:
            return 0

    @property
    def size(self) -> int:
        """Bytes this process wrote to the recording, every file of it."""
        return self.closed_bytes + self.current_size()

    def after_flush(self) -> tuple[Path, int] | None:
        """Start the next file if the current one is as large or as long as allowed; returns the file
        closed and its size, or None."""
        if not (self.max_size or self.max_duration):
            return None
        now = time.time_ns()
        if self._first_ns is None:
            self._first_ns = now
        size = self.current_size()
        if (self.max_size and size >= self.max_size) or (
                self.max_duration and now - self._first_ns >= self.max_duration * 1e9):
            return self.split()
        return None

    def split(self) -> tuple[Path, int]:
        """Close the current file whole and write on in the next one; returns the closed file and its size."""
        closed = self.path
        nxt = split_name(self.first, len(self.files))
        self._move(nxt)  # the old sink is flushed and its footer written before this returns
        size = closed.stat().st_size
        self.closed_bytes += size
        self.files.append(nxt)
        self._first_ns = None
        return closed, size


def stop_reason(run_dir: Path, used: int, max_size: int, min_free: int) -> str | None:
    """Why the recorder must stop now, or None: the run's recording holds ``used`` bytes, at or past
    ``max_size`` (0: no cap), or the run directory's file system has less than ``min_free`` free."""
    if max_size and used >= max_size:
        return f"the recording reached logger.max_size ({human_bytes(used)} of {human_bytes(max_size)})"
    if min_free:
        try:
            free = shutil.disk_usage(run_dir).free
        except OSError:
            return None
        if free < min_free:
            return (f"{human_bytes(free)} free on the run directory's disk, less than logger.min_free "
                    f"({human_bytes(min_free)})")
    return None
