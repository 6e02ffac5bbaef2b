"""The fast path of the per-step keys (clock, joint states, IMU): their rows read straight from the
payloads' bytes, one numpy pass per batch, without building message objects (:meth:`FastRows.raw`,
:meth:`FastRows.learn`, :meth:`FastRows.drain`, :class:`_Layout`).

Writes the same entity paths as the message path (``tests/test_rows_fast.py``): ``clock``;
``joints/<joint>/<q>/<source>`` (as :mod:`hilsim.record.rows.joints`) and
``robot/joint_transforms/<joint>`` (from ``truth/joint_states``, every 10 ms of sim time);
``imu/<truth|measured>/<field>/<axis>`` (as :mod:`hilsim.record.rows.imu`); ``rejected/<key>``
for a sample with a non-finite value.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import numpy as np

from hilsim.core import msgs
from hilsim.core.msgs import fastcdr
from hilsim.record.rows.common import IMU_SOURCES, JOINT_SOURCES, MODEL_PERIOD_NS, RowsBase, part, topic_parts
from hilsim.sim.kinematics import RobotModel

_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header: XCDR1, little-endian
_TIME = struct.Struct("<iI")
IMU_DOUBLES = 37  # orientation 4, then 9 covariance, 3 + 9 (angular velocity), 3 + 9 (acceleration)
IMU_VALUES = (0, 1, 2, 3, 13, 14, 15, 25, 26, 27)  # the recorded ones among them


@dataclasses.dataclass
class _Layout:
    """The bytes of one key's JointState or Imu messages, learnt from one that decoded and validated.

    Every later payload of exactly this layout (same size; the same bytes everywhere but the
    stamp and the doubles: frame id, joint names, sequence lengths, padding) is the same message
    but for its stamp and values, and is read straight into columns by :meth:`RowWriter.drain`
    (numpy over the concatenated payloads) without building a message object. The finiteness
    check ``msgs.validate`` makes is done there, for the whole batch at once."""

    cls: type
    size: int
    checks: tuple[tuple[int, bytes], ...]  # (offset, bytes that must be there)
    dtype: np.dtype
    blocks: tuple[tuple[str, tuple[str, ...]], ...]  # dtype field of doubles, entities of its columns (or ())
    rows: int  # rows buffered per sample
    model_names: tuple[str, ...] = ()  # truth/joint_states of the scenario's robot: the joints of the model
    payloads: list[bytes] = dataclasses.field(default_factory=list)
    clocks: list[int] = dataclasses.field(default_factory=list)  # clock_ns at arrival (a rejected row's time)

    def fits(self, data: bytes) -> bool:
        if len(data) != self.size:
            return False
        for off, b in self.checks:
            if not data.startswith(b, off):
                return False
        return True


def _layout(cls: type, data: bytes, doubles: list[tuple[int, int]], blocks: tuple[tuple[str, ...], ...],
            rows: int) -> _Layout:
    """A layout from a payload whose doubles lie at ``doubles`` ((offset, count) each)."""
    checks, pos = [(0, data[:4])], 12  # bytes 4..12: the stamp
    for off, n in doubles:
        if off > pos:
            checks.append((pos, data[pos:off]))
        pos = off + 8 * n
    dtype = np.dtype({"names": ["sec", "nsec", *(f"d{i}" for i in range(len(doubles)))],
                      "formats": ["<i4", "<u4", *(("<f8", (n,)) for _, n in doubles)],
                      "offsets": [4, 8, *(off for off, _ in doubles)], "itemsize": len(data)})
    return _Layout(cls, len(data), tuple(checks), dtype,
                   tuple((f"d{i}", b) for i, b in enumerate(blocks)), rows)


class FastRows(RowsBase):
    """The fast path's methods of :class:`~hilsim.record.rows.writer.RowWriter`."""

    model: RobotModel | None
    _layouts: dict[str, _Layout | None]
    _fast_rows: list[tuple[tuple[str, ...], np.ndarray, np.ndarray]]
    rejections: list[tuple[str, msgs.BadMessage]]
    _fleet_covered: set[str]
    _last_model_ns: int | None
    _model_rows: dict[str, tuple[list[int], list[float]]]

    # ------------------------------------------------------------------ the fast path
    def raw(self, key: str, data: bytes) -> bool:
        """Rows of a payload on a key whose layout is known (:meth:`learn`), without decoding it
        into a message: True if taken (its rows buffered, or its validation left to
        :meth:`drain`), False if it must go the ordinary way (decode, validate, :meth:`message`)."""
        if self._fleet_covered and self.covered(key):  # type: ignore[attr-defined]
            return True  # a fleet robot's own joint key: its rows come from the fleet sample
        lay = self._layouts.get(key, False)
        if lay is False:
            return False
        if lay is None:  # <prefix>/clock: 12 bytes, no floats to check
            if len(data) != 12 or not data.startswith(_LE):
                return False
            sec, ns = _TIME.unpack_from(data, 4)
            t = sec * 1_000_000_000 + ns
            if t > self.clock_ns:
                self.clock_ns = t
            self._scalar("clock", t, t * 1e-9)
            return True
        if not lay.fits(data):
            self.drain(key)  # rows in arrival order: what came before goes first
            return False
        lay.payloads.append(data)
        lay.clocks.append(self.clock_ns)
        self.buffered += lay.rows
        return True

    def learn(self, key: str, data: bytes, msg: Any) -> None:
        """After ``msg`` (decoded and validated from ``data``) went through :meth:`message`: let
        later payloads of the same layout on ``key`` take the fast path (clock, joint states, IMU)."""
        if key in self._layouts:
            return
        parts = topic_parts(key)
        if len(parts) == 2 and isinstance(msg, msgs.Clock):
            self._layouts[key] = None
            return
        if len(parts) < 3 or not data.startswith(_LE):
            return
        robot, topic = parts[1], "/".join(parts[2:])
        root = "" if robot == self.robot else f"robots/{part(robot)}/"
        try:
            if topic in JOINT_SOURCES and isinstance(msg, msgs.JointState):
                lay = self._joint_layout(root, JOINT_SOURCES[topic], data)
                # the model's joint transforms come from the positions: d0 when there are any
                if lay is not None and msg.position and topic == "truth/joint_states" and not root:
                    lay.model_names = tuple(msg.name)
            elif topic in IMU_SOURCES and isinstance(msg, msgs.Imu):
                lay = self._imu_layout(root, IMU_SOURCES[topic], data)
            else:
                return
        except (ValueError, struct.error):  # not laid out as expected: the ordinary way it stays
            return
        if lay is not None:
            self._layouts[key] = lay

    def _joint_layout(self, root: str, source: str, data: bytes) -> _Layout | None:
        r = fastcdr._Reader(data)
        r.time()
        r.string()
        names = tuple(r.strseq())
        doubles, blocks, rows = [], [], 0
        for quantity in ("position", "velocity", "effort"):
            n = r.u32()
            if not n:
                continue
            r.align(8)
            doubles.append((r.pos, n))
            r.pos += 8 * n
            blocks.append(tuple(f"{root}joints/{part(nm)}/{quantity}/{source}" for nm in names))
            rows += n
        if r.pos != len(data) or any(n != len(names) for _, n in doubles):
            return None
        return _layout(msgs.JointState, data, doubles, tuple(blocks), rows)

    def _imu_layout(self, root: str, source: str, data: bytes) -> _Layout | None:
        r = fastcdr._Reader(data)
        r.time()
        r.string()
        r.align(8)
        if r.pos + 8 * IMU_DOUBLES != len(data):
            return None
        base = f"{root}imu/{source}"
        entities = tuple(f"{base}/orientation/{a}" for a in "xyzw") + tuple(
            f"{base}/{f}/{a}" for f in ("angular_velocity", "linear_acceleration") for a in "xyz")
        return _layout(msgs.Imu, data, [(r.pos, IMU_DOUBLES)], (entities,), len(entities))

    def drain(self, key: str) -> None:
        """Turn the payloads the fast path holds for ``key`` into rows: one numpy view over all of
        them; a sample with a non-finite value is rejected (``rejected/<key>``, :attr:`rejections`)."""
        lay = self._layouts.get(key)
        if lay is None or not lay.payloads:
            return
        payloads, clocks = lay.payloads, lay.clocks
        lay.payloads, lay.clocks = [], []
        arr = np.frombuffer(b"".join(payloads), dtype=lay.dtype)
        ok = np.ones(len(arr), dtype=bool)
        for f, _ in lay.blocks:
            ok &= np.isfinite(arr[f]).all(axis=1)
        if not ok.all():
            for i in np.flatnonzero(~ok).tolist():
                self.buffered -= lay.rows
                try:
                    msgs.decode(lay.cls, payloads[i])
                    reason = msgs.BadMessage(f"{lay.cls.__name__} has a non-finite value")  # not expected
                except msgs.BadMessage as e:
                    reason = e
                self.rejections.append((key, reason))
                self._text(f"rejected/{part(key)}", clocks[i], f"{len(payloads[i])} bytes: {reason}", "WARN")
            arr = arr[ok]
            if not len(arr):
                return
        t = arr["sec"].astype(np.int64) * 1_000_000_000 + arr["nsec"]
        if lay.cls is msgs.Imu:
            values = arr["d0"][:, IMU_VALUES]
            self._fast_rows.append((lay.blocks[0][1], t, np.ascontiguousarray(values.T)))
            return
        for f, entities in lay.blocks:
            self._fast_rows.append((entities, t, np.ascontiguousarray(arr[f].T)))
        if lay.model_names:
            self._model_fast(lay.model_names, t, arr["d0"])

    def _model_fast(self, names: tuple[str, ...], t: np.ndarray, position: np.ndarray) -> None:
        """The joint transforms of ``truth/joint_states``, every MODEL_PERIOD_NS (as :meth:`_joint_state`)."""
        joints = self.model.joints if self.model is not None else {}
        if not joints:
            return
        last, picked = self._last_model_ns, []
        for i, ti in enumerate(t.tolist()):
            if last is None or ti - last >= MODEL_PERIOD_NS or ti < last:
                last = ti
                picked.append(i)
        self._last_model_ns = last
        if not picked:
            return
        ts = t[picked].tolist()
        for j, name in enumerate(names):
            if name in joints:
                col = self._model_rows.setdefault(name, ([], []))
                col[0].extend(ts)
                col[1].extend(position[picked, j].tolist())
                self.buffered += len(ts)
