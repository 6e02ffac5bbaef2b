"""The recorder's files: the ``.rrd``'s and the bag's, opened, split and closed (a part of the logger service).

A part of :class:`hilsim.services.logger.LoggerService` (one of its bases, not a service of its own).
Reads no key. Writes, in the run directory, ``recording.rrd`` and its parts (``recording.part-1.rrd``, …:
``logger.max_rrd_size`` / ``max_rrd_duration``, ``hilsim.record.limits.RrdSeries``) and ``bag/`` (``bag_0.mcap``,
… split by ``logger.max_bag_size`` / ``max_bag_duration``, and ``metadata.yaml``:
``hilsim.record.limits.BagSeries``); a restarted recorder first makes its predecessors' bag files whole.
Each file closed by a split is said in the log and as a notice (INFO) on the recorder's log key
(``<prefix>/<robot>/log/logger``), which ``hilsim up`` prints. Once the recorder stops no file splits
(:meth:`LoggerFiles._begin_stop`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hilsim.core.recording import disable_analytics
from hilsim.core.service import Service

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

from hilsim.record import live  # noqa: E402
from hilsim.record.bag import TIME_NOTE, BagError  # noqa: E402
from hilsim.record.bag_read import bag_paths, recover_file  # noqa: E402
from hilsim.record.limits import BagSeries, RrdSeries, human_bytes  # noqa: E402

LOG_INFO = 20  # rcl_interfaces/msg/Log's INFO: a notice hilsim up prints (a file of the recording closed)


class LoggerFiles(Service):
    """The recording's files: the ``.rrd`` series and the bag series."""

    rec: rr.RecordingStream | None
    rrd: RrdSeries | None
    rrd_path: Path
    run_dir: Path
    bag_dir: Path
    bag: BagSeries | None
    live: live.LiveStream | None
    written_ns: int
    _blueprint: Any
    _stopping: bool

    def _move_rrd(self, path: Path) -> None:
        """The recording's file sink to ``path`` (the live viewer's stream is another): the current file is
        closed whole, with its footer; the stream (one recording id) goes on in the new one, the
        viewer's layout written to it as well."""
        assert self.rec is not None
        rr.set_sinks(rr.FileSink(path), default_blueprint=self._blueprint, recording=self.rec)
        self.rrd_path = path

    def _say_closed(self, path: Path, size: int, nxt: Path | None) -> None:
        """A file of the recording closed (a split): one line in the log, and on the run's screen (a
        notice on the log key, which ``hilsim up`` prints)."""
        def name(p: Path) -> str:
            return str(p.relative_to(self.run_dir)) if p.is_relative_to(self.run_dir) else str(p)

        text = f"closed {name(path)} ({human_bytes(size)}, up to sim time {self.written_ns / 1e9:.3f} s)" + (
            f"; recording on in {name(nxt)}" if nxt is not None else "")
        self.log.info(text)
        self._publish_log(LOG_INFO, text)

    def _open_bag(self) -> BagSeries:
        """The bag's files of this process: ``bag_0.mcap`` (and on, split by ``logger.max_bag_size`` and
        ``max_bag_duration``); a restarted recorder (hilsim up) first makes its predecessors' files whole
        (a SIGKILL leaves no footer), then writes the next one."""
        index = 0
        if self.bag_dir.is_dir():
            try:
                _, files = bag_paths(self.bag_dir)
            except BagError:
                files = []
            for f in files:
                try:
                    got = recover_file(f)
                    if got.rewritten:
                        self.log.info("bag file %s of the killed recorder recovered: %d messages", f, got.messages)
                except BagError as e:
                    self.warn(f"bag file {f} of the killed recorder not recovered: {e}")
            index = len(files)
            while (self.bag_dir / f"bag_{index}.mcap").exists():
                index += 1
        lc = self.sc.logger
        return BagSeries(self.bag_dir, index, max_size=lc.max_bag_size, max_duration=lc.max_bag_duration,
                         custom={"scenario": self.sc.name, "robot": self.sc.robot},
                         metadata={"scenario": self.sc.name, "robot": self.sc.robot, "times": TIME_NOTE})

    def _begin_stop(self) -> None:
        """The recorder stops: no file of the .rrd or the bag split from here (see :meth:`_split_rrd`)."""
        self._stopping = True
        if self.bag is not None:
            self.bag.max_size, self.bag.max_duration = 0, 0.0

    def _split_rrd(self) -> None:
        """After a flush: on in the next ``.rrd`` file if this one is as large or as long as allowed. Not
        once the recorder is stopping: its files close anyway, and a notice published then would no
        longer reach its own subscription (a sample of log/logger published, never recorded)."""
        if self.rrd is None or self._stopping:
            return
        try:
            closed = self.rrd.after_flush()
        except Exception as e:  # the file sink could not move: the recording goes on in the current file
            self.fault(f"the recording could not go on in a new file after {self.rrd_path}: {type(e).__name__}: {e}",
                       exc=e)
            self.rrd.max_size = self.rrd.max_duration = 0
            return
        if closed is not None:
            self._say_closed(*closed, self.rrd.path)

    def _close_bag(self) -> None:
        """Write the bag's summary and footer, then its ``metadata.yaml`` over all its files."""
        if self.bag is None:
            return
        try:
            self.bag.close()
        except (OSError, BagError) as e:
            self.fault(f"the bag {self.bag_dir} was not closed: {type(e).__name__}: {e}", exc=e)

    # ------------------------------------------------------------------ the recording's size (logger.max_size)
    def recording_bytes(self) -> int:
        """Bytes of this run's recording on disk: the ``.rrd``'s and the bag's files of this process."""
        rrd = self.rrd.size if self.rrd is not None else 0
        return rrd + (self.bag.size if self.bag is not None else 0)
