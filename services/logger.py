"""The logger service: records every message of the simulation into a Rerun ``.rrd`` file and a
rosbag2 bag (MCAP) of the raw samples.

Reads: every data key of the domain (``logger.record`` key expressions under ``<domain>/``, ``**`` by
default), including each sample's attachment (sequence number and writer id, ``hilsim.core.transport``).
With ``logger.batch`` > 0 instead: the services' batches and batching tokens
(``<prefix>/batch/<domain>/<service>/<zid>/<node id>``, ``hilsim.core.batch``), the ROS 2 graph's publisher
tokens (``@ros2_lv/<domain>/…/MP/…``), and key by key, the keys with a writer no batch covers.
Writes: only its own health and log keys (``<prefix>/<robot>/health/logger``,
``<prefix>/<robot>/log/logger``), and files in the run directory (``logger.run_dir``, or
``<logger.out_dir>/<YYYYmmdd-HHMMSS>``):

- ``recording.rrd``       the Rerun recording, timeline ``sim_time`` (message stamps), with a
  default viewer layout (``hilsim.record.viewer``); split by ``logger.max_rrd_size`` /
  ``max_rrd_duration`` into ``recording.part-1.rrd``, … (``hilsim.record.limits.RrdSeries``), each
  closed file said in the log and as a notice on its log key (INFO), which ``hilsim up`` prints;
- ``bag/``                a rosbag2 bag (``metadata.yaml``, ``bag_0.mcap``; ``hilsim.record.bag``): every
  sample of every key as the raw CDR bytes that arrived (a composed service's message: the bytes
  the worker encoded it to, the same the rows are read from), stamped with its receive time,
  sim-time stamp, sequence number and writer gid; ``logger.bag: false`` turns it off;
- ``scenario.yaml``       the scenario of the run (written unless already there);
- ``record_summary.json`` ``{key: {received, recorded, bagged, rejected, lost, dropped, before_first,
  unannounced}}`` (``bagged``: messages of the key written to the bag, counted as the batches
  reached the file; ``unannounced``: samples from a writer that did not announce itself for the key,
  recorded all the same; their sequence numbers are not ours to count losses by; with batches also
  ``duplicates``; where some arrived ``suspect`` and ``contested``; ``batch_refused``: samples of the key
  in a service's batch that the key table does not let that service write, not recorded; ``lost`` never
  more than the key's services say they published and did not reach it: their final health) written at exit.

This module is the service's wiring: subscriptions, the queue, the worker thread, health and
lifecycle. Each writer's sequence and the loss accounting is ``hilsim.record.accounting`` (judged at
the end by ``hilsim.record.loss``); what is written for
each kind of message (and the entity layout) is ``hilsim.record.rows``; which keys are subscribed one
by one ``hilsim.record.routes``; what the summary file and lines say ``hilsim.record.report``; the
robot model and tool kinematics ``hilsim.sim.kinematics``.

Composed with other services (``--compose physics,sensors,controller,logger``, hilsim.run.compose),
it takes their samples as message objects in the process (none of them crosses Zenoh) and the
rest over Zenoh; the worker encodes a message object once, so both are recorded from the same
bytes, the same way.

The Zenoh callback only appends ``(key, payload, attachment, receive time)`` to a queue; a worker
thread hands the payload to the bag (``BagWriter.add``: a tuple appended, the chunk built with numpy
at the batch), decodes
(``hilsim.core.msgs.decode``), turns messages into rows (``RowWriter``) and sends them with
``send_columns`` every 0.5 s or every 20,000 rows. The per-step keys (clock, joint states, IMU)
take a fast path once one of their messages decoded: a payload laid out like it (same size, same
bytes but stamp and values) is kept as bytes and read into columns with numpy at the batch, its
values checked there (``RowWriter.raw``/``drain``). A payload that does not decode or validate
(on either path) is counted as rejected and still recorded, as a text row under
``rejected/…``. Every sample taken in is recorded: ``received == recorded == bagged``; a sample
counts as recorded once its batch reached the file (the bag's chunk is written and flushed with the
same batch, so a recorder killed with SIGKILL leaves both files holding the same samples up to its
last flush; ``hilsim bag recover`` or ``hilsim up`` make the bag whole).

Batches (``logger.batch`` > 0; docs/recording.md, "Batches"). The services do not put a sample on
its key for the recorder: they append it to their batch, put on their batch key when full, when
``logger.batch_max_age_ms`` old and at their stop. The recorder subscribes to the batch keys, and per
key only to writers whose publisher token is not a batching node's (ROS 2 nodes, tools, bridges) or
that are transient-local (a late-joiner subscription, for a recorder restarted mid-run; batching
services put their latched samples in the batch as well). Without batches the recorder also takes a
late-joiner subscription for each transient-local writer beside ``**``: a latched sample
(``/tf_static``, ``robot_description``) is put once, often before ``**`` reached its publisher, and
the publisher's cache then gives it; such keys are taken once per writer and sequence number too.
Each sample unpacked from a batch goes through
:meth:`_take` like one received on its key; since one can come both ways (a key written by a batching
service and another writer, or a batching token seen after the node's publisher tokens), samples are
taken once per (key, writer gid, sequence number, payload) (``hilsim.record.accounting``, each writer's
:class:`hilsim.core.provenance.Sequence`; ``duplicates``). A sample that does not fit its writer's
sequence (a forged number, a replay) is recorded and counted as ``suspect``, its writer's gaps then
``contested``, not ``lost`` (docs/keys.md, "Suspect samples"). A frame
that does not decode is recorded as a rejected sample of its key. Trade-offs: a writer without a
publisher token on a key only batching services announce is not seen (consumers reject it anyway);
a service killed with SIGKILL loses its unsent batch (at most ``batch_max_age_ms`` of samples), which
no sequence gap shows.

Losses. Lockstep: publishers block when the logger is slow (Zenoh congestion control BLOCK)
and the queue is unbounded, so nothing is lost (``lost`` is 0; anything else is a fault).
Realtime: the recorder never slows the loop. Publishers drop samples a slow logger cannot take
(congestion control DROP) and the queue holds at most ``REALTIME_QUEUE_LIMIT`` samples; what
is dropped is counted per key as ``lost``: the gaps in each writer's sequence numbers (lost in
transport) plus the samples dropped because the queue was full (``dropped``). Gaps are
counted from the first sample received from a writer on; the samples a writer had published
before it (``before_first``: the first sequence number minus 1, e.g. health published before
this subscription reached its writer) are not counted as lost. Samples lost after the last
one that arrived from a writer leave no gap and are not seen (with a logger far slower than a
realtime run, that can be most of what is missing: docs/recording.md).

At exit (SIGINT/SIGTERM) the logger keeps receiving until nothing arrived for ``QUIET_S`` (at
most ``DRAIN_LIMIT_S``), then the subscriber is undeclared, the queue drained, the file flushed,
and one line per key ``recorded <key>: received N recorded M[ lost L]`` plus a total line are
printed. ``HILSIM_LOGGER_DELAY_US`` (fault injection, for tests) slows the receive callback
by that many microseconds per sample while the simulation runs. Rerun analytics are off
(``hilsim.core.recording.disable_analytics``) and nothing is sent over the network: the recording
stream only saves to the file.
"""

from __future__ import annotations

import ctypes
import json
import os
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any

import zenoh

from hilsim.core import batch, msgs, rights, transport
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys, UnknownKey, message_type
from hilsim.core.recording import RECORDING_NAME, SUMMARY_NAME, disable_analytics, part_name
from hilsim.core.restart import restarted
from hilsim.core.scenario import write_scenario
from hilsim.core.service import LEVEL_WARN, Service

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

from hilsim.record import foxglove_live, live, loss, report  # noqa: E402
from hilsim.record.accounting import LossAccounts  # noqa: E402
from hilsim.record.bag import NO_ATTACHMENT, TIME_NOTE, BagError  # noqa: E402
from hilsim.record.bag_read import BAG_DIR, bag_paths, recover_file  # noqa: E402
from hilsim.record.limits import BagSeries, RrdSeries, human_bytes, stop_reason  # noqa: E402
from hilsim.record.routes import KeyRoutes  # noqa: E402
from hilsim.record.rows import RowWriter  # noqa: E402
from hilsim.record.viewer import default_blueprint  # noqa: E402
from hilsim.sim.kinematics import RobotModel  # noqa: E402
from hilsim.sim.scene import Scene  # noqa: E402

FLUSH_PERIOD_S = 0.5  # wall seconds between send_columns batches
FLUSH_ROWS = 20_000  # …or earlier when this many rows are buffered
FILE_FLUSH_TIMEOUT_S = 5.0  # at most this long waiting for a batch to reach the file
# Realtime: samples waiting for the worker at most (about 2 s of its work, some 25 MB for the
# arm's messages); a sample arriving at a full queue is dropped and counted as lost.
REALTIME_QUEUE_LIMIT = 50_000
# At exit: wait for what is still in flight until nothing arrived for QUIET_S, at most DRAIN_LIMIT_S.
QUIET_S = 0.25
DRAIN_LIMIT_S = 5.0
DELAY_ENV = "HILSIM_LOGGER_DELAY_US"  # fault injection: slow the receive callback (µs per sample)
LOG_INFO = 20  # rcl_interfaces/msg/Log's INFO: a notice hilsim up prints (a file of the recording closed)


def _name_thread(name: bytes) -> None:
    """Name the calling thread for the OS (``/proc/<pid>/task/<tid>/comm``, 15 bytes); Linux only, else nothing."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(15, ctypes.c_char_p(name[:15]), 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):
        pass


class LoggerService(Service):
    name = "logger"
    stop_rank = 100  # stopped last: it drains and closes the recording
    records = True

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        self.run_dir = self._choose_run_dir()
        self.rrd_path = self.run_dir / RECORDING_NAME
        self.summary_path = self.run_dir / SUMMARY_NAME
        if restarted() and self.rrd_path.exists():
            # restarted by hilsim up: what the killed recorder wrote stays as it is (hilsim up
            # makes it readable); this process records the rest of the run in a part of its own
            self.rrd_path = self.run_dir / part_name(restarted())
        self.rec: rr.RecordingStream | None = None
        self.rrd: RrdSeries | None = None  # the .rrd's files (logger.max_rrd_size, max_rrd_duration)
        self._blueprint: Any = None  # the viewer's layout, written to every file of the recording
        self.live: live.LiveStream | None = None  # logger.live: the second sink, to the live viewer
        self.fox: foxglove_live.FoxgloveLive | None = None  # logger.foxglove: the samples on a Foxglove server
        self.bag_dir = self.run_dir / BAG_DIR
        self.bag: BagSeries | None = None  # None: logger.bag is false, or the bag failed (a fault)
        self.bagged: Counter[str] = Counter()  # messages per key written to the bag
        self.rows: RowWriter | None = None
        self.model: RobotModel | None = None
        # (key, payload bytes or a composed service's message, attachment, receive time ns)
        self._queue: deque[tuple[str, Any, transport.Attachment | None, int]] = deque()
        self.realtime = scenario.clock.mode == "realtime"
        self.queue_limit: int | None = REALTIME_QUEUE_LIMIT if self.realtime else None
        self._key_names: dict[str, str] = {}
        self.recorded: Counter[str] = Counter()
        self._pending: Counter[str] = Counter()  # samples whose rows are buffered, not yet sent, per key
        self.dropped: Counter[str] = Counter()  # arrived at a full queue (or as the subscriber closed)
        self.unannounced: Counter[str] = Counter()  # from writers that did not announce themselves for the key
        self.delay_s = self._delay_from_env()
        self._subs: list[Any] = []
        self._worker: threading.Thread | None = None
        self._worker_stop = threading.Event()
        self._warned: set[str] = set()
        # pycdr2 serializes through one buffer per message class, and msgs.decode re-serializes to
        # check the size: the worker's decoding and this process's own health/log publishing
        # (DiagnosticArray, Log) must not interleave, or valid payloads are rejected.
        self._codec_lock = threading.RLock()
        self._intake_closed = False  # the subscriptions are going: own notices no longer published
        self._finished = False
        self._stopping = False  # set as the recorder stops (its end, or logger.max_size): no file split from here
        self._closed = False  # set once the subscribers are gone: late samples are dropped
        self._last_arrival = 0.0  # time.monotonic() of the latest sample
        # logger.batch: the services send batches; keys are subscribed one by one for the other writers
        self.batching = scenario.logger.batch > 0
        # loss accounting (under self.lock): each writer's sequence, gaps, suspect samples (hilsim.record.accounting)
        self.accounts = LossAccounts(self.lock, batching=self.batching)
        self.gaps = self.accounts.gaps  # lost in transport: sequence numbers never received
        self.suspect = self.accounts.suspect  # samples that do not fit their writer's sequence (recorded)
        self.before_first = self.accounts.before_first  # published before a writer's first received sample
        self.duplicates: Counter[str] = Counter()  # samples that came both ways (batching, latched), taken once
        # samples in a service's batch of a key the key table does not let it write (hilsim.core.rights)
        self.batch_refused: Counter[str] = Counter()
        self._batch_rights: dict[tuple[str, str], bool] = {}  # (service, key) -> may it write it
        self._service_rights: dict[str, rights.Rights | None] = {}
        self.routes = KeyRoutes(self.keys, scenario.logger.record, batching=self.batching)  # key by key
        self._malformed_warned = False
        # logger.max_size, logger.min_free: why the recording stopped (None: it goes on), when, what came after
        self.stopped: str | None = None
        self.stopped_at: dict[str, Any] = {}
        self.after_stop: Counter[str] = Counter()  # samples that arrived (or were queued) after the stop
        self.written_ns = -1  # the sim time up to which the .rrd holds every row (its last flush); -1: none yet

    # ------------------------------------------------------------------ setup
    def _choose_run_dir(self) -> Path:
        lc = self.sc.logger
        if lc.run_dir is not None:
            return Path(lc.run_dir)
        base = Path(lc.out_dir) / time.strftime("%Y%m%d-%H%M%S")
        d, i = base, 1
        while d.exists():  # two runs started within the same second
            d, i = base.with_name(f"{base.name}-{i}"), i + 1
        return d

    def _delay_from_env(self) -> float:
        raw = os.environ.get(DELAY_ENV, "").strip()
        if not raw:
            return 0.0
        try:
            us = float(raw)
        except ValueError:
            self.log.warning("%s=%r is not a number of microseconds; ignored", DELAY_ENV, raw)
            return 0.0
        return max(us, 0.0) * 1e-6

    def setup(self) -> None:
        assert self.session is not None
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if not (self.run_dir / "scenario.yaml").exists():
            write_scenario(self.sc, self.run_dir / "scenario.yaml")
        self._load_model()
        self.rec = rr.RecordingStream("hilsim", send_properties=True)
        m = self.model
        scene = self._load_scene()
        # file sink only: no viewer, no network; with logger.live a second sink feeds the live viewer
        self.live = live.start(self.sc.logger.live, self.run_dir, self.warn)
        self._blueprint = default_blueprint(m, scene)
        live.attach(self.live, self.rec, self.rrd_path, self._blueprint)
        lc = self.sc.logger
        self.rrd = RrdSeries(self.rrd_path, self._move_rrd, max_size=lc.max_rrd_size, max_duration=lc.max_rrd_duration)
        self.rec.send_recording_name(f"{self.sc.name} {self.run_dir.name}")
        self.rows = RowWriter(self.rec, self.sc.robot, m, self.fault, scene)
        if self.sc.logger.bag:
            self.bag = self._open_bag()
            self._bag_append = self.bag.append
        try:
            self.rows.log_model()
        except Exception as e:  # a model rerun cannot log must not stop the recording
            self.warn(f"robot model {self.sc.world.urdf} not recorded: {type(e).__name__}: {e}")
        try:
            self.rows.log_scene()
        except Exception as e:  # nor may the world's geometry
            self.warn(f"world geometry of {self.sc.world.model} not recorded: {type(e).__name__}: {e}")
        live.setup_done(self.live, self.rec)
        self.fox = foxglove_live.start(self.sc.logger.foxglove, self.warn, self.run_dir)
        self._worker = threading.Thread(target=self._work, name="logger-worker", daemon=True)
        self._worker.start()
        if self.delay_s:
            self.warn(f"{DELAY_ENV}: every received sample is delayed by {self.delay_s * 1e6:.0f} µs (fault injection)")
        # composed: samples of this process's own services never cross Zenoh (hilsim.run.compose)
        local = getattr(self.session, "local_subscriber", None)
        for expr in self.sc.logger.record:
            subs = []
            if not self.batching:
                subs.append(self.session.declare_subscriber(self.keys.scoped(expr), self._on_sample))
            if local is not None:
                subs.append(local(self.keys.scoped(expr), self._on_local))
            self._subs.extend(subs)
            self._declared.extend(subs)
        if self.batching:  # the services' batches; key by key the writers no batch covers (self.routes)
            sub = self.session.declare_subscriber(self.keys.all_batches, self._on_batch)
            self._subs.append(sub)
            self._declared.append(sub)
        # without batches too: a transient-local sample (/tf_static, robot_description) is put once, often
        # before `**` reaches its publisher: a late-joiner subscription per latched writer asks its cache
        self._declared.extend(self.routes.start(
            self.session, self.zenoh_session, self._zid, composed=local is not None,
            on_sample=self._on_sample, on_twice=self.accounts.takes_twice))
        limit = f"queue limit {self.queue_limit}" if self.queue_limit else "unbounded queue"
        self.log.info(
            "recording %s to %s (clock %s, %s)",
            ", ".join(self.keys.scoped(e) for e in self.sc.logger.record),
            self.rrd_path,
            self.sc.clock.mode,
            limit,
        )

    def _move_rrd(self, path: Path) -> None:
        """The recording's file sink to ``path`` (the live viewer's sink kept): the current file is
        closed whole, with its footer; the stream (one recording id) goes on in the new one, the
        viewer's layout written to it as well."""
        assert self.rec is not None
        sink = getattr(self.live, "sink", None)
        rr.set_sinks(rr.FileSink(path), *([sink] if sink is not None else []), default_blueprint=self._blueprint,
                     recording=self.rec)
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

    def _load_model(self) -> None:
        urdf = self.sc.world.urdf
        if urdf is None:
            return
        try:
            self.model = RobotModel.load(urdf)
        except Exception as e:  # a model rerun cannot load must not stop the recording
            self.warn(f"robot model {urdf} not recorded: {type(e).__name__}: {e}")

    def _load_scene(self) -> Scene | None:
        """The world's static geometry and datum (``hilsim.sim.scene``), or None if it cannot be read."""
        m = self.model
        try:
            return Scene.for_scenario(self.sc, m.links if m else (), m.root if m else None)
        except Exception as e:  # the recording goes on without the world's geometry
            self.warn(f"world geometry of {self.sc.world.model} not recorded: {type(e).__name__}: {e}")
            return None

    # ------------------------------------------------------------------ batches (logger.batch)
    def _on_batch(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        try:
            records = batch.decode(raw)
        except batch.BatchError as e:
            # recorded as a rejected sample of the batch key (bag and rows), and the recording goes on
            if not self._malformed_warned:
                self._malformed_warned = True
                self.warn(f"malformed batch on {sample.key_expr}: {e} (further ones are only counted)")
            self._take(str(sample.key_expr), None, raw)
            return
        service = Keys.batch_service(str(sample.key_expr)) or ""
        for r in records:
            if not self.routes.covers(r.key):
                continue
            if not self._batch_may_hold(service, r.key):
                # the router lets a service put only its own batches; what one holds is checked against the key
                # table as a sample on the key itself would be at the router: not the run's, not recorded
                with self.lock:
                    self.batch_refused[r.key] += 1
                    first = self.batch_refused[r.key] == 1
                if first:
                    self.warn(f"a batch of {service or '?'} holds a sample of {r.key}, which the key table does not "
                              f"let {service or 'it'} write: not recorded (further ones are only counted)")
                continue
            self._take(r.key, transport.Attachment(r.seq, r.source_ns, r.gid), r.payload)

    def _batch_may_hold(self, service: str, key: str) -> bool:
        """Whether ``service`` may write ``key`` (hilsim.core.rights, as its identity at the router), cached."""
        got = self._batch_rights.get((service, key))
        if got is None:
            if service not in self._service_rights:  # derived once per service (the type hashes are not free)
                try:
                    self._service_rights[service] = rights.service_rights(self.sc, service) if service else None
                except Exception:  # a service name the scenario does not know: nobody's batch
                    self._service_rights[service] = None
            r = self._service_rights[service]
            got = r is not None and r.may_put(key)
            self._batch_rights[(service, key)] = got
        return got

    # ------------------------------------------------------------------ receiving (Zenoh thread)
    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Only queue: decoding here would slow Zenoh's delivery to every other subscriber.
        self._take(str(sample.key_expr), transport.read_attachment(sample), sample.payload.to_bytes())

    def _on_local(self, key: str, msg: Any, att: transport.Attachment) -> None:
        # composed (hilsim.run.compose): a message object from a service of this process; encoded by
        # the worker, so it is recorded from the same bytes (and rows) as one that came over Zenoh
        self._take(key, att, msg)

    def _take(self, k: str, att: transport.Attachment | None, payload: Any) -> None:
        if self.delay_s and not self.stop_event.is_set():
            time.sleep(self.delay_s)
        k = self._key_names.setdefault(k, k)  # one string per key, not one per queued sample
        self._last_arrival = time.monotonic()
        if self.stopped is not None:  # the recording stopped (logger.max_size, min_free): not taken in
            with self.lock:
                self.after_stop[k] += 1
            return
        # The base's health thread iterates these counters under self.lock.
        with self.lock:
            prov = self.provenance
            if att is not None and (k not in prov.restricted or att.gid in prov.writers.get(k, ())):
                if not self.accounts.sequence(k, att, payload):
                    # it came both ways (in a batch, or from a latched writer's cache, and on its key): once
                    self.duplicates[k] += 1
                    return
            elif k in prov.restricted:
                # Batching: a writer whose token is not known yet (a race at its start) can send a sample
                # both ways too; taken once all the same, its gaps not counted (not announced yet)
                if att is not None and self.batching and not self.accounts.sequence(k, att, payload, counted=False):
                    self.duplicates[k] += 1
                    return
                # recorded like everything received, but a stranger's gaps are no loss of ours
                self.unannounced[k] += 1
            if self.stopped is not None:
                self.after_stop[k] += 1
                return
            t_ns = time.time_ns()
            queued = not (self._closed or (self.queue_limit is not None and len(self._queue) >= self.queue_limit))
            if queued:
                self.counts_in[k] += 1
                self._queue.append((k, payload, att, t_ns))
            else:
                self.dropped[k] += 1
        fox = self.fox
        if fox is not None and isinstance(payload, bytes):
            # Foxglove's clients get it as it arrives, not once the worker wrote it: a live view stays live
            # when the files fall behind (seen: minutes behind, the queue full, in a realtime run); the
            # server never waits for a client (its backlog drops a slow one's oldest)
            fox.add(k, payload, t_ns)
        if not queued:
            return
        if k in self.routes.latched:
            self.routes.got(k)  # its publisher's cache need not be asked again
        if self.accounts.say_suspect:
            said, self.accounts.say_suspect = self.accounts.say_suspect, ""
            self.warn(said)

    def lost(self) -> Counter[str]:
        """Samples lost per key: gaps in the sequence numbers plus drops at the full queue."""
        with self.lock:
            return self.gaps + self.dropped

    # ------------------------------------------------------------------ the worker
    def _ordinary_class(self) -> None:
        """The worker (this thread) in the ordinary scheduling class: hilsim up gives the recorder's threads
        SCHED_FIFO in realtime for its receiving; writing the files must not take a core from the loop."""
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass

    def _work(self) -> None:
        _name_thread(b"logger-worker")  # as the OS sees it: hilsim up leaves it out of SCHED_FIFO
        q = self._queue
        rows = self.rows
        assert rows is not None
        last_flush = time.monotonic()
        period = live.FLUSH_PERIOD_S if self.live is not None else FLUSH_PERIOD_S
        while True:
            try:
                key, payload, att, t = q.popleft()
            except IndexError:
                if self._worker_stop.is_set():
                    break
                if rows.buffered and time.monotonic() - last_flush >= period:
                    self._ordinary_class()
                    self._flush()
                    last_flush = time.monotonic()
                    if self._limit_reached():
                        break
                time.sleep(0.002)
                continue
            self._handle(key, payload, att, t)
            if rows.buffered >= FLUSH_ROWS or time.monotonic() - last_flush >= period:
                self._ordinary_class()
                self._flush()
                last_flush = time.monotonic()
                if self._limit_reached():
                    break

    def _handle(self, key: str, payload: Any, att: transport.Attachment | None = None, t_ns: int = 0) -> None:
        rows = self.rows
        assert rows is not None
        local = not isinstance(payload, bytes)
        if local:  # a message object of this process (_on_local)
            try:
                payload = msgs.encode(payload)  # pycdr2's buffer is per thread (hilsim.core.msgs.codec)
            except Exception as e:  # not encodable: still recorded, as the error and the message's text
                self.fault(f"cannot encode {key} from this process: {type(e).__name__}: {e}", exc=e)
                rows.error(key, e, payload)
                self._pending[key] += 1
                return  # no bytes: nothing for the bag (bagged < recorded for this key)
        if self.bag is not None:  # every payload as it arrived, valid or not
            self._bag_append((key, payload, NO_ATTACHMENT if att is None else att, t_ns))
        if self.fox is not None and local:  # a composed service's message: to Foxglove once encoded (_take: the rest)
            self.fox.add(key, payload, t_ns)
        if rows.raw(key, payload):  # a clock, joint state or IMU sample of a layout seen before
            self.sim_ns = rows.clock_ns
            self._pending[key] += 1
            return
        try:
            cls = message_type(key)
            with self._codec_lock:
                msg = msgs.decode(cls, payload)
        except (UnknownKey, msgs.BadMessage) as e:
            self._reject(key, e)
            rows.rejected(key, len(payload), e)
            self._pending[key] += 1
            return
        if isinstance(msg, msgs.DiagnosticArray) and "/health/" in key:
            self.accounts.note_published(key, msg)
        try:
            rows.message(key, msg)
            rows.learn(key, payload, msg)
        except Exception as e:  # a bug here must not lose the sample: record it as text
            self.fault(f"cannot turn {key} into rows: {type(e).__name__}: {e}", exc=e)
            rows.error(key, e, msg)
        self.sim_ns = rows.clock_ns
        self._pending[key] += 1

    def _reject(self, key: str, e: Exception) -> None:
        with self.lock:
            self.rejected[key] += 1
        if key not in self._warned:  # one warning per key; the rest are counted
            self._warned.add(key)
            self.warn(f"rejected payload on {key}: {e} (further ones on this key are only counted)")

    def _flush(self) -> None:
        """Send every buffered row and push it through Rerun's batcher into the file, then count
        the samples they came from as recorded. A recorder killed with SIGKILL (no footer
        written) thus leaves a file that holds everything up to its last flush, FLUSH_PERIOD_S
        ago at most; ``hilsim.core.recording.recover_rrd`` makes it a complete .rrd again."""
        assert self.rows is not None and self.rec is not None
        ok = self.rows.flush()
        for key, e in self.rows.rejections:  # found while the fast path's batches were turned into rows
            self._reject(key, e)
        self.rows.rejections.clear()
        if ok:
            try:
                self.rec.flush(timeout_sec=FILE_FLUSH_TIMEOUT_S)
            except Exception as e:  # a slow disk: the rows are still on their way to the file
                self.warn(f"the recording was not written to {self.rrd_path} within {FILE_FLUSH_TIMEOUT_S:g} s: {e}")
            if self.live is not None:
                self.live.pump()  # never waits: a slow viewer's frames are dropped, counted in health
            with self.lock:
                self.recorded.update(self._pending)
                self.written_ns = self.rows.clock_ns  # every row up to this sim time is in the file now
            self._split_rrd()
        self._pending.clear()
        if self.bag is not None:
            n_files, closed_bytes = len(self.bag.files), self.bag.closed_bytes
            try:
                wrote = self.bag.flush()  # and on in a new file, if this one is as large or long as allowed
            except Exception as e:  # a full disk, a bug: the .rrd goes on, the bag stops here (a fault)
                self.fault(f"the bag {self.bag.path} stopped: {type(e).__name__}: {e}", exc=e)
                self.bag.abandon()
                self.bag = None
                return
            self._bag_append = self.bag.append
            with self.lock:
                self.bagged.update(wrote)
            if len(self.bag.files) > n_files:  # split: the bag's file before the current one closed
                self._say_closed(self.bag.files[-2], self.bag.closed_bytes - closed_bytes, self.bag.path)

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

    # ------------------------------------------------------------------ limits (logger.max_size, min_free)
    def recording_bytes(self) -> int:
        """Bytes of this run's recording on disk: the ``.rrd``'s and the bag's files of this process."""
        rrd = self.rrd.size if self.rrd is not None else 0
        return rrd + (self.bag.size if self.bag is not None else 0)

    def _limit_reached(self) -> bool:
        """In the worker, after a flush: if the recording reached ``logger.max_size`` or the disk's free
        space ``logger.min_free``, stop recording (:meth:`_stop_recording`) and return True (the worker ends)."""
        lc = self.sc.logger
        if not (lc.max_size or lc.min_free):
            return False
        why = stop_reason(self.run_dir, self.recording_bytes(), lc.max_size, lc.min_free)
        if why is None:
            return False
        self._stop_recording(why)
        return True

    def _stop_recording(self, why: str) -> None:
        """Stop recording, cleanly, while the run goes on: no sample is taken in from here (the
        subscriptions go; samples still queued are counted as ``after_stop``, not received), what was
        taken in is written, and both files are closed whole (the bag's summary, footer and
        ``metadata.yaml``; the ``.rrd``'s footer). Said in one line (log and health) and in
        ``record_summary.json``."""
        self._begin_stop()
        with self.lock:  # _take checks it under the lock: nothing is queued after this
            self.stopped = why
            while self._queue:  # taken in, not written: no longer counted as received
                k = self._queue.popleft()[0]
                self.counts_in[k] -= 1
                self.after_stop[k] += 1
        subs = [*self._subs, *self.routes.close()]
        for sub in subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        self._subs.clear()
        assert self.rec is not None
        self._flush()
        self.rec.flush()
        self.rec.disconnect()
        self._close_bag()
        live.stop(self.live)
        foxglove_live.stop(self.fox)
        self.fox = None
        used = self.recording_bytes()
        self.stopped_at = {"reason": why, "sim_time": round(self.sim_ns / 1e9, 3), "bytes": used,
                           "wall_time": time.strftime("%Y-%m-%dT%H:%M:%S")}
        self.warn(f"recording stopped at sim time {self.sim_ns / 1e9:.3f} s: {why}; the files hold the run up to "
                  f"here ({human_bytes(used)}, closed whole), the run goes on")

    # ------------------------------------------------------------------ health
    def publish_health(self) -> None:
        with self._codec_lock:
            super().publish_health()

    def _publish_log(self, level: int, text: str) -> None:
        with self._codec_lock:
            # once its subscriptions go, a notice of the recorder's own would reach nobody's recording and
            # be counted published, never recorded (a split the worker finished late, CI): the process log
            # has it; a fault goes out all the same (the run fails on it anyway)
            if self._intake_closed and level <= LOG_INFO:
                return
            super()._publish_log(level, text)

    def health(self) -> msgs.DiagnosticArray:  # called under self.lock
        h = super().health()
        if any(self.gaps.values()) or any(self.dropped.values()):
            h.status[0].level = max(h.status[0].level, LEVEL_WARN)
        return h

    def health_values(self) -> dict[str, Any]:  # called under self.lock
        lost = +(self.gaps + self.dropped)
        return {
            "queue": len(self._queue),
            "queue_limit": self.queue_limit or "none",
            "recorded": sum(self.recorded.values()),
            "batch_refused": sum(self.batch_refused.values()),
            "lost": sum(lost.values()),
            "dropped": sum(self.dropped.values()),
            "suspect": sum(self.suspect.values()),
            **({"duplicates": sum(self.duplicates.values()), "key_subscriptions": len(self.routes.key_subs)}
               if self.batching else {}),
            "rrd": str(self.rrd_path),
            **({"rrd_files": len(self.rrd.files)} if self.rrd is not None and len(self.rrd.files) > 1 else {}),
            "written_sim_time": f"{self.written_ns / 1e9:.3f}" if self.written_ns >= 0 else "none",
            **({"bagged": sum(self.bagged.values()), "bag": str(self.bag.path), "bag_files": len(self.bag.files)}
               if self.bag is not None else {}),
            **({"recording_stopped": f"at sim time {self.stopped_at.get('sim_time', '?')} s: {self.stopped}"}
               if self.stopped_at else {}),
            **{f"lost:{k}": v for k, v in sorted(lost.items())},
            **(self.live.health() if self.live is not None else {}),
        }

    # ------------------------------------------------------------------ stopping
    def loop(self) -> None:
        while not self.stop_event.wait(0.2):
            if self._worker is not None and not self._worker.is_alive() and self.stopped is None:
                raise RuntimeError("the recording worker stopped unexpectedly")
            for key in self.routes.ask_again():
                self.log.info("latched %s: nothing from its publisher's cache yet, asked again", key)
        self._finish()

    def teardown(self) -> None:
        self._finish()

    def _finish(self) -> None:
        """Stop receiving, record everything queued, close the file, report the counts."""
        if self._finished:
            return
        self._finished = True
        self._begin_stop()
        self._await_quiet()
        key_subs = self.routes.close()  # no key subscription declared after this
        with self._codec_lock:  # a notice being put now reaches the subscription; none after (_publish_log)
            self._intake_closed = True
        for sub in [*self._subs, *key_subs]:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass  # already gone with the session
        with self.lock:  # a callback still running now counts its sample as dropped
            self._closed = True
        self._worker_stop.set()
        if self._worker is not None:
            self._worker.join()
        if self.rec is None:
            return
        if self.stopped is None:
            while self._queue:  # anything that arrived while the worker was stopping
                self._handle(*self._queue.popleft())
            self._flush()
            self.rec.flush()
            self.rec.disconnect()
            self._close_bag()
        live.stop(self.live)
        foxglove_live.stop(self.fox)
        self._report()

    def _close_bag(self) -> None:
        """Write the bag's summary and footer, then its ``metadata.yaml`` over all its files."""
        if self.bag is None:
            return
        try:
            self.bag.close()
        except (OSError, BagError) as e:
            self.fault(f"the bag {self.bag_dir} was not closed: {type(e).__name__}: {e}", exc=e)

    def _await_quiet(self) -> None:
        """Before closing: keep receiving what is still in flight (samples a realtime publisher's
        link holds for a slow logger, up to the kernel's socket buffers) until nothing arrived
        for ``QUIET_S``, at most ``DRAIN_LIMIT_S``. What is still in flight then is not seen."""
        t0 = time.monotonic()
        with self.lock:
            n0 = sum(self.counts_in.values()) + sum(self.dropped.values())
        while time.monotonic() - t0 < DRAIN_LIMIT_S and time.monotonic() - self._last_arrival < QUIET_S:
            time.sleep(0.02)
        with self.lock:
            n = sum(self.counts_in.values()) + sum(self.dropped.values()) - n0
        self.log.info("stopping: %d samples still arrived in %.2f s", n, time.monotonic() - t0)

    def _report(self) -> None:
        with self.lock:
            c = report.Counts(
                received=Counter(self.counts_in), recorded=Counter(self.recorded), bagged=Counter(self.bagged),
                rejected=Counter(self.rejected), lost=Counter(), dropped=Counter(self.dropped),
                before_first=Counter(self.before_first), unannounced=Counter(self.unannounced),
                duplicates=Counter(self.duplicates), after_stop=Counter(self.after_stop),
                suspect=Counter(self.suspect), contested=Counter(), batch_refused=Counter(self.batch_refused))
        c.plain = self.routes.plain_keys()
        c.expected = loss.expected_keys(self.sc, self.keys, self.routes.covers) if self.stopped is None else set()
        with self.lock:
            gaps = Counter(self.gaps)
        c.lost = self.accounts.judged_lost(gaps, c.dropped, c.received)
        c.contested = self.accounts.contested()
        for k in gaps:  # gaps its writers' own counts say are not losses: said apart, as contested ones
            c.contested[k] += gaps[k] - (c.lost[k] - c.dropped[k])
        bag = self.sc.logger.bag
        stopped_at = self.stopped_at if self.stopped is not None else None
        tmp = self.summary_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(report.summary(c, bag=bag, batching=self.batching, stopped_at=stopped_at),
                                  indent=1, sort_keys=True) + "\n")
        tmp.replace(self.summary_path)
        lines = report.lines(c, rrd=self.rrd_path, bag_dir=self.bag_dir if bag else None, clock=self.sc.clock.mode,
                             stopped_at=stopped_at)
        total_in, total_rec, total_lost = sum(c.received.values()), sum(c.recorded.values()), sum(c.lost.values())
        try:
            print("\n".join(lines), flush=True)
        except BrokenPipeError:
            # whoever read our stdout is gone (a killed launcher); the summary file is written
            self.log.warning("stdout closed; per-key counts are in %s", self.summary_path)
        if total_in != total_rec:
            self.fault(f"received {total_in} messages but recorded {total_rec}")
        if bag and sum(c.bagged.values()) != total_rec:
            self.fault(f"recorded {total_rec} messages but bagged {sum(c.bagged.values())}")
        if total_lost and not self.realtime:
            self.fault(f"lost {total_lost} samples in lockstep, where nothing may be lost")
        elif total_lost:
            self.warn(f"lost {total_lost} samples: the recorder could not keep up with the realtime loop")
