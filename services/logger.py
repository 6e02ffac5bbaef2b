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

This module is the service's wiring: its setup (subscriptions, files, the worker thread), health and
lifecycle; its parts are its bases, each in a module of its own: the intake (the subscriptions'
callbacks, taking a sample once into the queue) ``hilsim.services.logger_intake``; the worker (the queue
into rows and the bag, flushing) ``hilsim.services.logger_worker``; the files (the ``.rrd``'s and the bag's,
split and closed) ``hilsim.services.logger_files``; the stop (at ``logger.max_size`` / ``min_free``, or at the
end: draining, the summary) ``hilsim.services.logger_stop``. Each writer's sequence and the loss accounting
is ``hilsim.record.accounting`` (judged at the end by ``hilsim.record.loss``); what is written for
each kind of message (and the entity layout) is ``hilsim.record.rows``; which keys are subscribed one
by one ``hilsim.record.routes``; what the summary file and lines say ``hilsim.record.report``; the
robot model and tool kinematics ``hilsim.sim.kinematics``.

Composed with other services (``--compose physics,sensors,controller,logger``, hilsim.launch.compose),
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

import os
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any

from hilsim.core import msgs, rights, transport
from hilsim.core.config import Scenario
from hilsim.core.recording import RECORDING_NAME, SUMMARY_NAME, disable_analytics, part_name
from hilsim.core.restart import restarted
from hilsim.core.scenario import write_scenario
from hilsim.core.service import LEVEL_WARN

disable_analytics()  # before rerun is imported: its SDK reads the analytics config at start-up
import rerun as rr  # noqa: E402

from hilsim.record import foxglove_live, live  # noqa: E402
from hilsim.record.accounting import LossAccounts  # noqa: E402
from hilsim.record.bag_read import BAG_DIR  # noqa: E402
from hilsim.record.limits import BagSeries, RrdSeries  # noqa: E402
from hilsim.record.routes import KeyRoutes  # noqa: E402
from hilsim.record.rows import RowWriter  # noqa: E402
from hilsim.record.viewer import default_blueprint  # noqa: E402
from hilsim.services.logger_files import LOG_INFO  # noqa: E402
from hilsim.services.logger_intake import LoggerIntake  # noqa: E402
from hilsim.services.logger_stop import LoggerStop  # noqa: E402
from hilsim.sim.kinematics import RobotModel  # noqa: E402
from hilsim.sim.scene import Scene  # noqa: E402

# Realtime: samples waiting for the worker at most (about 2 s of its work, some 25 MB for the
# arm's messages); a sample arriving at a full queue is dropped and counted as lost.
REALTIME_QUEUE_LIMIT = 50_000
DELAY_ENV = "HILSIM_LOGGER_DELAY_US"  # fault injection: slow the receive callback (µs per sample)


class LoggerService(LoggerIntake, LoggerStop):
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
        # file sink only: no viewer, no network; with logger.live a second stream feeds the live viewer
        self.live = live.start(self.sc.logger.live, self.run_dir, self.warn)
        self._blueprint = default_blueprint(m, scene)
        rows_rec = live.attach(self.live, self.rec, self.rrd_path, self._blueprint)  # the file's, or both
        lc = self.sc.logger
        self.rrd = RrdSeries(self.rrd_path, self._move_rrd, max_size=lc.max_rrd_size, max_duration=lc.max_rrd_duration)
        rows_rec.send_recording_name(f"{self.sc.name} {self.run_dir.name}")
        self.rows = RowWriter(rows_rec, self.sc.robot, m, self.fault, scene,
                              model_from_truth=self.routes.covers(self.keys.truth("joint_states")))
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
        live.setup_done(self.live)
        self.fox = foxglove_live.start(self.sc.logger.foxglove, self.warn, self.run_dir)
        self._worker = threading.Thread(target=self._work, name="logger-worker", daemon=True)
        self._worker.start()
        if self.delay_s:
            self.warn(f"{DELAY_ENV}: every received sample is delayed by {self.delay_s * 1e6:.0f} µs (fault injection)")
        # composed: samples of this process's own services never cross Zenoh (hilsim.launch.compose)
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
